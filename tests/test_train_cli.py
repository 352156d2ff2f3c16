"""``msdnet-train`` on real Astyx frames (tiny preset, 4 frames): teacher, student, R2LDM,
kill + resume, NaN stop, one-line errors; and the torch datasets of training/data/datasets.py."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from msdnet.training.cli import main
from msdnet.training.config import MODEL_PRESETS
from msdnet.training.data.datasets import config_for_dataset, make_splits
from msdnet.training.recipe.checkpoint import load_checkpoint, read_checkpoint

# 6 frames: validation split frame 5 (never read), fitted 0-3, held-out selection slice frame 4
TINY = ["--preset", "tiny", "--frames", "6"]


def _astyx(root: Path) -> list[str]:
    return ["--dataset", "astyx", "--data", str(root), *TINY]


def _train(args: list[str]) -> None:
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output


def _log(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def teacher_run(tmp_path_factory, astyx_root) -> Path:
    """A tiny teacher trained for the preset's 2 epochs on Astyx frames 0-3 (selection: frame 4)."""
    out = tmp_path_factory.mktemp("teacher") / "run"
    _train(["teacher", *_astyx(astyx_root), "--out", str(out)])
    return out


def test_teacher_run_writes_checkpoints_log_and_metrics(teacher_run):
    assert sorted(p.name for p in teacher_run.iterdir()) == ["best", "last", "log.jsonl"]
    model, cfg, state = load_checkpoint(teacher_run / "last")
    assert cfg == config_for_dataset(MODEL_PRESETS["tiny"], "astyx")
    assert cfg.radar_columns == ("x", "y", "z", "v_r", "mag")
    assert (state.kind, state.epoch, state.step, state.epochs) == ("teacher", 2, 4, 2)
    assert state.dataset["train_frames"] == ["000000", "000003", 4]
    assert state.dataset["val_frames"] == ["000004", "000004", 1] and state.dataset["holdout"] == 0.15
    epochs = [e for e in _log(teacher_run) if e["event"] == "epoch"]
    assert [e["epoch"] for e in epochs] == [1, 2]
    for e in epochs:
        assert np.isfinite(e["val_loss"]) and np.isfinite(e["train_loss"])
        assert 0.0 <= e["occ_iou"] <= 1.0 and e["occ_tp"] + e["occ_fn"] > 0  # LiDAR voxels exist
    assert epochs[1]["train_loss"] < epochs[0]["train_loss"]  # it learns something
    best = read_checkpoint(teacher_run / "best")[2]
    assert best.best_val_loss == min(e["val_loss"] for e in epochs)
    assert all(p.requires_grad for p in model.parameters())


def test_publish_keeps_weights_and_json_only_with_relative_paths(astyx_root, tmp_path, monkeypatch):
    """--publish copies a finished run's best/ without optimizer state, paths relative to the
    working directory; the copy starts a student as --teacher like best/ itself."""
    monkeypatch.chdir(tmp_path)
    root = Path(os.path.relpath(astyx_root, tmp_path))
    published = Path("checkpoints") / "m" / "teacher"
    _train(["teacher", "--dataset", "astyx", "--data", str(root), *TINY, "--epochs", "1",
            "--out", str(tmp_path / "t"), "--publish", str(published)])  # fmt: skip
    assert sorted(p.name for p in published.iterdir()) == ["checkpoint.json", "model.safetensors"]
    assert (tmp_path / "t" / "best" / "training.safetensors").exists()  # the run keeps its own
    text = (published / "checkpoint.json").read_text()
    meta = json.loads(text)

    def strings(obj) -> list[str]:
        if isinstance(obj, dict):
            return [s for v in obj.values() for s in strings(v)]
        return [s for v in obj for s in strings(v)] if isinstance(obj, list) else [obj] * isinstance(obj, str)

    assert strings(meta) and not [v for v in strings(meta) if os.path.isabs(v)]  # no machine's path
    assert meta["published_from"] == "t/best" and meta["training"] == {}
    assert meta["state"]["dataset"]["root"] == root.as_posix()
    same = (published / "model.safetensors").read_bytes() == (
        tmp_path / "t/best/model.safetensors"
    ).read_bytes()
    assert same
    a, _, _ = load_checkpoint(published)
    b, _, _ = load_checkpoint(tmp_path / "t" / "best")
    assert all(torch.equal(a.state_dict()[k], v) for k, v in b.state_dict().items())
    _train(["student", "--dataset", "astyx", "--data", str(root), *TINY, "--epochs", "1",
            "--teacher", str(published), "--out", str(tmp_path / "s")])  # fmt: skip
    assert read_checkpoint(tmp_path / "s" / "last")[2].teacher == str(published.resolve())


@pytest.mark.parametrize("kind", ["student", "r2ldm"])
def test_student_and_r2ldm_train_against_the_frozen_teacher(kind, teacher_run, astyx_root, tmp_path):
    out = tmp_path / kind
    _train([kind, *_astyx(astyx_root), "--epochs", "1", "--teacher", str(teacher_run / "best"),
            "--out", str(out)])  # fmt: skip
    model, cfg, state = load_checkpoint(out / "last")
    teacher, _, _ = load_checkpoint(teacher_run / "best")
    assert state.kind == kind and state.teacher == str((teacher_run / "best").resolve())
    for name, p in teacher.state_dict().items():  # carried along and left untouched
        assert torch.equal(model.teacher.state_dict()[name], p), name
    rec = _log(out)[1]
    assert rec["event"] == "epoch" and np.isfinite(rec["val_loss"]) and "occ_iou" in rec
    assert "val_diff" in rec


def test_killed_run_resumes_to_the_uninterrupted_result(teacher_run, astyx_root, tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "msdnet.training.cli", "teacher", *_astyx(astyx_root), "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (out / "last").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)  # no chance to clean up: like a crash or OOM kill
    finally:
        proc.wait()
    assert read_checkpoint(out / "last")[2].epoch == 1  # killed during epoch 2
    r = CliRunner().invoke(main, ["teacher", *_astyx(astyx_root), "--out", str(out)])
    assert r.exit_code == 2 and "pass --resume" in r.output
    _train(["teacher", *_astyx(astyx_root), "--out", str(out), "--resume"])
    resumed, _, state = load_checkpoint(out / "last")
    full, _, full_state = load_checkpoint(teacher_run / "last")
    assert (state.epoch, state.step) == (full_state.epoch, full_state.step) == (2, 4)
    for name, p in full.state_dict().items():
        assert torch.equal(resumed.state_dict()[name], p), name
    for h, f in zip(state.history, full_state.history, strict=True):  # same numbers, not times
        assert {k: v for k, v in h.items() if k != "seconds"} == {
            k: v for k, v in f.items() if k != "seconds"
        }
    starts = [e for e in _log(out) if e["event"] == "start"]
    assert [(e["resume"], e["step"]) for e in starts] == [(False, 0), (True, 2)]


def test_nan_loss_stops_with_one_line_and_nonzero_exit(astyx_root, tmp_path):
    r = CliRunner().invoke(main, ["teacher", *_astyx(astyx_root), "--lr", "1e30", "--out", str(tmp_path)])
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "non-finite loss at epoch 1, step 2: " in lines[0], r.output
    assert "=nan" in lines[0] and "Traceback" not in r.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["teacher", "--dataset", "astyx", "--data", "/nonexistent/astyx"], "dataset folder not found"),
        (["teacher", "--dataset", "astyx", "--preset", "huge"], "unknown preset 'huge'"),
        (["teacher", "--dataset", "kitti"], "unknown dataset 'kitti'"),
        (["teacher", "--dataset", "astyx", "--epochs", "0"], "--epochs must be >= 1"),
        (["critic", "--dataset", "astyx"], "unknown model kind 'critic'"),
        (["student", "--dataset", "astyx"], "student needs --teacher CKPT"),
        (["r2ldm", "--dataset", "astyx", "--teacher", "/nonexistent/ckpt"], "no such checkpoint"),
        (["teacher", "--dataset", "astyx", "--resume"], "has no checkpoint 'last' to resume"),
        (["teacher", "--dataset", "astyx", "--frames", "1"], "both need at least one"),
    ],
)
def test_bad_input_is_one_line_error(args, message, astyx_root, tmp_path):
    if "--data" not in args:
        args = [*args, "--data", str(astyx_root)]
    r = CliRunner().invoke(main, ["--out", str(tmp_path / "o"), "--preset", "tiny", *args])
    assert r.exit_code == 2, r.output
    assert r.output.count("\n") == 1 and r.output.startswith("error: ") and message in r.output


def test_teacher_checkpoint_must_be_a_teacher_of_the_same_config(teacher_run, astyx_root, tmp_path):
    args = ["student", *_astyx(astyx_root), "--preset", "lite", "--teacher", str(teacher_run / "best")]
    r = CliRunner().invoke(main, [*args, "--out", str(tmp_path)])
    assert r.exit_code == 2
    assert "teacher config differs from this run: preset 'tiny' (now 'lite')" in r.output


def test_splits_are_contiguous_cached_and_use_the_dataset_columns(astyx_root, vod_root):
    cfg = config_for_dataset(MODEL_PRESETS["tiny"], "astyx")
    train, val = make_splits("astyx", astyx_root, cfg, val_fraction=0.25, max_frames=8)
    assert train.frame_ids == [f"{i:06d}" for i in range(6)] and val.frame_ids == ["000006", "000007"]
    radar, lidar = train[0]
    assert radar.dtype == lidar.dtype == np.float32
    assert radar.shape[1] == 5 and lidar.shape[1] == 3 and len(lidar) > len(radar) > 0
    lo, hi = np.array(cfg.grid.point_range[:3]), np.array(cfg.grid.point_range[3:])
    assert ((lidar >= lo) & (lidar <= hi)).all()  # cropped to the grid
    assert train[0][0] is radar  # cached: same arrays back
    assert np.isfinite(radar).all()

    vcfg = config_for_dataset(MODEL_PRESETS["tiny"], "vod")
    vtrain, vval = make_splits("vod", vod_root, vcfg)
    assert (len(vtrain), len(vval)) == (2, 1) and vval.frame_ids == ["01201"]
    assert vtrain[0][0].shape[1] == len(vcfg.radar_columns) == 5
    assert vcfg.radar_feature_norm != cfg.radar_feature_norm  # re-derived for Astyx's columns


def test_teacher_config_check_ignores_r2ldm_only_fields(tmp_path):
    import dataclasses

    from export_helpers import make_checkpoint, tiny_config

    from msdnet.runtime.errors import MsdnetError
    from msdnet.training.cli import _teacher

    ckpt = make_checkpoint(tmp_path / "t", "teacher", "vod")
    cfg = tiny_config("vod")
    assert _teacher(ckpt, dataclasses.replace(cfg, r2ldm_channels=(8, 16), r2ldm_sample_steps=4)) is not None
    with pytest.raises(MsdnetError, match="bev_channels"):
        _teacher(ckpt, dataclasses.replace(cfg, bev_channels=8))


def test_init_starts_a_new_run_from_a_checkpoints_weights(teacher_run, astyx_root, tmp_path):
    from msdnet.training.recipe.checkpoint import load_checkpoint, read_checkpoint

    out = tmp_path / "warm"
    one = [*_astyx(astyx_root), "--epochs", "1"]
    _train(["teacher", *one, "--init", str(teacher_run / "best"), "--out", str(out), "--lr", "1e-9"])
    state = read_checkpoint(out / "last")[2]
    assert state.init == str((teacher_run / "best").resolve()) and state.epochs == 1
    before = load_checkpoint(teacher_run / "best")[0].state_dict()
    after = load_checkpoint(out / "last")[0].state_dict()
    moved = max(
        (after[k].float() - before[k].float()).abs().max().item() for k in before if before[k].numel()
    )
    assert moved < 1e-3  # a near-zero learning rate keeps the initial weights: they were loaded
    r = CliRunner().invoke(
        main, ["student", *one, "--init", str(teacher_run / "best"), "--out", str(tmp_path / "s")]
    )
    assert r.exit_code == 2 and "is a teacher checkpoint, this run trains a student" in r.output
    r = CliRunner().invoke(
        main,
        [
            "teacher",
            *_astyx(astyx_root),
            "--preset",
            "lite",
            "--init",
            str(teacher_run / "best"),
            "--out",
            str(tmp_path / "l"),
        ],
    )
    assert r.exit_code == 2 and "--init config differs" in r.output


def test_new_head_on_a_trained_encoder_then_students_keep_their_weights(astyx_root, tmp_path):
    """``--head sparse --head-only --init DENSE_TEACHER``: the encoder and S2D stay as they were
    (the students' distillation target), the head changes; a student then takes its own weights
    from ``--init`` and the new frozen teacher from ``--teacher``."""
    one = [*_astyx(astyx_root), "--epochs", "1"]
    dense, sparse = tmp_path / "dense", tmp_path / "sparse"
    _train(["teacher", *one, "--head", "dense", "--out", str(dense)])
    _train(
        [
            "teacher",
            *one,
            "--init",
            str(dense / "best"),
            "--head",
            "sparse",
            "--head-only",
            "--out",
            str(sparse),
        ]
    )
    a, a_cfg, _ = load_checkpoint(dense / "best")
    b, b_cfg, b_state = load_checkpoint(sparse / "best")
    assert (a_cfg.head_kind, b_cfg.head_kind, b_state.train.head_only) == ("dense", "sparse", True)
    sa, sb = a.state_dict(), b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa if k.startswith(("encoder.", "s2d.")))
    assert any(not torch.equal(sa[k], sb[k]) for k in sa if k.startswith("head.") and k in sb)
    s_old, s_new = tmp_path / "s_old", tmp_path / "s_new"
    _train(["student", *one, "--head", "dense", "--teacher", str(dense / "best"), "--out", str(s_old)])
    _train(
        ["student", *one, "--lr", "1e-9", "--head", "sparse", "--teacher", str(sparse / "best")]
        + ["--init", str(s_old / "best")]
        + ["--out", str(s_new)]
    )
    old, new = (
        load_checkpoint(s_old / "best")[0].state_dict(),
        load_checkpoint(s_new / "best")[0].state_dict(),
    )
    own = [k for k in old if not k.startswith("teacher.") and old[k].is_floating_point()]
    assert own and max((new[k] - old[k]).abs().max().item() for k in own) < 1e-3  # taken from --init
    assert all(torch.equal(new[k], sb[k[len("teacher.") :]]) for k in new if k.startswith("teacher."))
    r = CliRunner().invoke(
        main,
        ["student", *one, "--head", "sparse", "--init", str(s_old / "best")] + ["--out", str(tmp_path / "y")],
    )
    assert r.exit_code == 2 and "needs --teacher" in r.output
    r = CliRunner().invoke(main, ["student", *one, "--head-only", "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "--head-only" in r.output
    # --head-only on a student: its head copy learns on its own F_r^D, nothing else moves
    s_head = tmp_path / "s_head"
    _train(
        [
            "student",
            *one,
            "--lr",
            "1e-2",
            "--head",
            "sparse",
            "--head-only",
            "--init",
            str(s_new / "best"),
            "--out",
            str(s_head),
        ]
    )
    tuned, _, t_state = load_checkpoint(s_head / "best")
    tuned = tuned.state_dict()
    assert t_state.train.head_only and tuned.keys() == new.keys()
    moved = {k for k in new if not torch.equal(new[k], tuned[k])}
    assert moved and all(k.startswith("teacher.head.") for k in moved)
