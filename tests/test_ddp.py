"""Data-parallel training through torchrun: two CPU processes, gloo, tiny preset, real frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from msdnet.training.recipe.checkpoint import read_checkpoint


def test_torchrun_two_processes_train_and_write_one_checkpoint(tmp_path, astyx_root):
    out = tmp_path / "run"
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
        "-m", "msdnet.training.cli", "teacher", "--dataset", "astyx", "--data", str(astyx_root),
        "--preset", "tiny", "--frames", "6", "--epochs", "1", "--out", str(out),
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == ["best", "last", "log.jsonl"]
    _, cfg, state = read_checkpoint(out / "last")
    # 5 train frames, 1 held out -> 4 fitted over 2 ranks -> 2 per rank -> 1 step of 2.
    assert (state.world_size, state.epoch, state.step) == (2, 1, 1)
    assert cfg.radar_columns == ("x", "y", "z", "v_r", "mag")
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [e["event"] for e in log] == ["start", "epoch", "stop"]  # rank 0 alone writes
    assert log[0]["world_size"] == 2 and log[1]["val_loss"] > 0
