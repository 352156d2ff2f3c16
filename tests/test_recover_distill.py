"""A checkpoint read back from an exported model (export/recover.py), and few-step distillation
of a student's loop (``msdnet-train student --distill N --loop-steps K``) on real Astyx frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner
from export_helpers import make_exported_checkpoint, one_torch_thread

from msdnet.export.recover import main as recover_main
from msdnet.export.recover import recover_checkpoint, recover_model
from msdnet.runtime.errors import MsdnetError
from msdnet.training.cli import main as train_main
from msdnet.training.recipe.checkpoint import load_checkpoint, read_checkpoint


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """(tiny random student checkpoint, the artifact exported from it), Astyx columns."""
    return make_exported_checkpoint(tmp_path_factory.mktemp("exported"), dataset="astyx")


@pytest.fixture(scope="module")
def recovered(exported, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("recovered") / "ckpt"
    with one_torch_thread():
        recover_checkpoint(exported[1], out)
    return out


def test_recovered_weights_are_the_checkpoints_own(exported, recovered):
    """Every weight of the radar path comes back exactly; the teacher's LiDAR branch is in no
    graph (zeros), and the checkpoint says where it came from."""
    original = load_checkpoint(exported[0])[0].state_dict()
    back, _, state = load_checkpoint(recovered)
    back = back.state_dict()
    radar = [k for k in original if k.split(".")[0] in ("encoder", "rgfd", "adapter", "step")]
    assert radar and all(torch.equal(original[k], back[k]) for k in radar)
    coarse = ("teacher.head.occ.0.", "teacher.head.off.0.", "teacher.head.off.1.")  # training-only scales
    used = [k for k in original if k.startswith("teacher.head.") and not k.startswith(coarse)]
    assert len(used) > 20 and all(torch.equal(original[k], back[k]) for k in used)
    assert state.recovered_from == str(exported[1])
    lidar = [k for k in back if k.startswith(("teacher.encoder.", "teacher.s2d."))]
    assert lidar and all(not back[k].any() for k in lidar)


def test_recover_refuses_a_graph_this_export_does_not_write(exported, tmp_path):
    """A graph whose nodes are not where this msdnet's export puts them (here: one renamed; the
    manifest re-hashed, so the folder loads) is refused, naming the file and the weight."""
    from export_helpers import copy_artifact

    from msdnet.export.manifest import build_manifest, write_manifest

    folder = copy_artifact(exported[1], tmp_path / "edited")
    path = folder / "denoiser_step.onnx"
    model = onnx.load(str(path))
    weight = model.graph.initializer[0].name
    node = next(n for n in model.graph.node if weight in n.input)
    node.name = "/somewhere/else"
    onnx.save(model, str(path))
    manifest = json.loads((folder / "manifest.json").read_text())
    cfg = read_checkpoint(exported[0])[1]
    write_manifest(folder, build_manifest(folder, "student", cfg, manifest["parameters"], "edited"))
    with one_torch_thread(), pytest.raises(MsdnetError, match=f"denoiser_step.onnx.*{weight}"):
        recover_model(folder)


def test_recover_cli_names_what_no_graph_holds_and_refuses_in_one_line(exported, tmp_path):
    r = CliRunner().invoke(recover_main, [str(exported[1]), "--out", str(tmp_path / "ok")])
    assert r.exit_code == 0 and "re-export identical" in r.output, r.output
    assert "teacher.encoder" in r.output and "teacher.s2d" in r.output  # the LiDAR branch
    r = CliRunner().invoke(recover_main, [str(exported[1]), "--out", str(exported[1])])
    assert r.exit_code == 2 and "exists" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(recover_main, [str(tmp_path / "none"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "Traceback" not in r.output


def _args(root: Path, init: Path, out: Path, *extra: str) -> list[str]:
    return ["student", "--dataset", "astyx", "--data", str(root), "--preset", "tiny", "--frames", "6"] + [
        "--init",
        str(init),
        "--out",
        str(out),
        *extra,
    ]


def test_distillation_trains_only_the_denoiser_toward_the_long_loop(recovered, astyx_root, tmp_path):
    """--distill 8 --loop-steps 1: only the step's weights move, the K-step loop gets closer to
    the 8-step one than the undistilled K-step loop is, and the config records T_m = 1."""
    out = tmp_path / "d"
    args = _args(astyx_root, recovered, out, "--distill", "8", "--loop-steps", "1", "--distill-head", "1")
    r = CliRunner().invoke(train_main, [*args, "--lr", "1e-3", "--epochs", "3"])
    assert r.exit_code == 0, r.output
    before = load_checkpoint(recovered)[0].state_dict()
    after, cfg, state = load_checkpoint(out / "last")
    after = after.state_dict()
    moved = {k for k in before if not torch.equal(before[k], after[k])}
    assert moved and all(k.startswith("step.denoiser.") for k in moved)
    assert (cfg.train_sample_steps, cfg.diffusion.sample_steps, state.train.distill_steps) == (1, 1, 8)
    from msdnet.training.cli import _init_model

    with one_torch_thread():  # the run's model loops K = 1 times, not --init's T_m
        model = _init_model(recovered, "student", cfg, None, distill=True)
    assert len(model.train_coeffs) == 1 and read_checkpoint(recovered)[1].train_sample_steps > 1
    epochs = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    last = [e for e in epochs if e["event"] == "epoch"][-1]
    # on the held-out frame (same noise every epoch): closer to the 8-step loop than before (-25 %)
    assert last["val_distill"] < 0.9 * last["val_undistilled"]
    assert np.isfinite(last["val_distill_occ"]) and last["train_span"] > 0


def test_distillation_options_are_checked(recovered, exported, astyx_root, tmp_path):
    cases = [
        (["--distill", "8"], "--loop-steps"),  # no K
        (["--distill", "2", "--loop-steps", "2"], "--distill"),  # K must be < N
        (["--distill-head", "1"], "--distill-head"),  # without --distill
        (["--loop-steps", "1"], "read back from an exported model"),  # full training on a recovered one
    ]
    for extra, message in cases:
        r = CliRunner().invoke(train_main, _args(astyx_root, recovered, tmp_path / "x", *extra))
        assert r.exit_code == 2 and message in r.output and "Traceback" not in r.output, (extra, r.output)
    assert read_checkpoint(exported[0])[2].recovered_from is None


def test_recover_records_the_training_split_for_split_select(exported, astyx_root, tmp_path):
    from msdnet.benchmarks.stages import split_frames
    from msdnet.training.recipe.checkpoint import load_checkpoint

    out = tmp_path / "split"
    args = [str(exported[1]), "--out", str(out), "--dataset", "astyx", "--data", str(astyx_root)]
    with one_torch_thread():
        r = CliRunner().invoke(recover_main, args)
    assert r.exit_code == 0, r.output
    record = load_checkpoint(out)[2].dataset
    first, last, n = record["val_frames"]
    fit_first, fit_last, n_fit = record["train_frames"]
    assert record["holdout"] == 0.15 and n == round(0.15 * (n + n_fit)) and fit_last < first
    _, ids = split_frames(record, "astyx", astyx_root, "select", None)
    assert (ids[0], ids[-1], len(ids)) == (first, last, n)  # what --split select then scores
    r = CliRunner().invoke(recover_main, [str(exported[1]), "--out", str(tmp_path / "o"), "--dataset", "sim"])
    assert r.exit_code == 2 and "go together" in r.output and "Traceback" not in r.output
