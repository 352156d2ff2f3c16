"""The gated head built from a dense student: the fixed norm from pooled statistics, the 1/4 branch
refit as the gate, and the command on a tiny checkpoint."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from click.testing import CliRunner
from export_helpers import make_checkpoint, one_torch_thread, tiny_config

from msdnet.training.models.assembly import bev_shape, build_model
from msdnet.training.nn.head_gated import GatedReconHead
from msdnet.training.recipe.checkpoint import load_checkpoint
from msdnet.training.recipe.gated_head import (
    calibrate,
    fit_quarter_gate,
    gated_student,
    main,
    quarter_targets,
)


def _pair(seed: int = 0) -> tuple[torch.nn.Module, torch.nn.Module]:
    """(dense student, gated student with the same weights, statistics unset)."""
    torch.manual_seed(seed)
    cfg = tiny_config()
    dense = build_model("student", cfg).eval()
    gated = build_model("student", dataclasses.replace(cfg, head_kind="gated")).eval()
    gated.load_state_dict(dense.state_dict())
    return dense, gated


def test_one_frame_statistics_reproduce_the_dense_head() -> None:
    """Pooled over one frame, the fixed statistics are that frame's GroupNorm statistics, so the
    gated head gives the dense head's outputs on it (and not on another frame)."""
    dense, gated = _pair()
    z, other = torch.randn(2, 1, *bev_shape(dense.cfg))
    with one_torch_thread(), torch.no_grad():
        before = gated.head.packed(z)[0]
        calibrate(gated, [z])
        ref, got = dense.head.packed(z), gated.head.packed(z)
        far = (dense.head.packed(other)[0] - gated.head.packed(other)[0]).abs().max()
    assert (before - ref[0]).abs().max() > 1e-3  # statistics 0 / 1 are not the frame's
    torch.testing.assert_close(got[0], ref[0], rtol=0, atol=2e-5)
    torch.testing.assert_close(got[1], ref[1], rtol=0, atol=2e-5)
    assert far > 1e-4  # another frame has statistics of its own


def test_two_frames_pool_like_one_volume() -> None:
    _, gated = _pair(1)
    zs = list(torch.randn(2, 1, *bev_shape(gated.cfg)))
    seen = []
    norm = gated.teacher.head.fixed_norm()
    hook = norm.register_forward_pre_hook(lambda m, i: seen.append(i[0].detach().clone()))
    with one_torch_thread(), torch.no_grad():
        report = calibrate(gated, zs)
    hook.remove()
    g = norm.num_groups
    both = torch.cat([x.reshape(g, -1) for x in seen[: len(zs)]], 1).double()  # first pass: 2 frames
    mean, var = (torch.tensor(report[k], dtype=torch.float64) for k in ("mean", "var"))
    torch.testing.assert_close(mean, both.mean(1), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(var, both.var(1, unbiased=False), rtol=1e-4, atol=1e-6)


def test_quarter_gate_fit_follows_the_decoded_occupancy() -> None:
    _, gated = _pair(2)
    zs = list(torch.randn(3, 1, *bev_shape(gated.cfg)))
    with one_torch_thread():
        calibrate(gated, zs)
        x, t = quarter_targets(gated, zs)
        report = fit_quarter_gate(gated, zs)
        head = gated.teacher.head
        with torch.no_grad():
            logits = head.occ[0](head._trunk(gated.head._f(zs[0]))[0]).reshape(-1)
            occ, off = gated.head.packed(zs[0])
            s_occ, *_ = gated.head.sparse(zs[0], torch.zeros(1))
    assert x.shape == (3 * logits.numel(), head.c4) and float(t.min()) >= 0 and float(t.max()) <= 1
    assert report["bce_after"] < report["bce_before"]
    corr = np.corrcoef(torch.sigmoid(logits).numpy(), t[: logits.numel()].numpy())[0, 1]
    assert corr > 0.3  # the refit 1/4 occupancy tracks where the head decodes
    torch.testing.assert_close(s_occ, occ.reshape(8, -1).t(), rtol=0, atol=1e-5)  # gate 0: exact


def test_command_writes_a_gated_checkpoint(tmp_path, vod_root) -> None:
    ckpt = make_checkpoint(tmp_path / "dense", "student")
    out = tmp_path / "gated"
    args = [str(ckpt), "--dataset", "vod", "--data", str(vod_root), "--out", str(out), "--threads", "1"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "1/4 gate" in res.output and "gated head calibrated on" in res.output
    model, cfg, state = load_checkpoint(out)
    assert cfg.head_kind == "gated" and isinstance(model.teacher.head, GatedReconHead)
    assert state.init == str(ckpt)
    dense, _, _ = load_checkpoint(ckpt)
    d_norm, g_norm = dense.teacher.head.post2[2][1], model.teacher.head.fixed_norm()
    assert not torch.equal(d_norm.weight, g_norm.weight)  # statistics folded in
    again = CliRunner().invoke(main, [str(out), *args[1:-4], "--out", str(tmp_path / "x")])
    assert again.exit_code != 0 and "calibrate a dense head" in again.output
    assert not (tmp_path / "x").exists()
    model2, _, _ = gated_student(ckpt)
    assert isinstance(model2.teacher.head, GatedReconHead)
