"""The gated8 head retrained from a student: targets pooled from the source head's decoding, a
loss that falls and leaves the trunk alone for the gates, and the command on a tiny checkpoint."""

from __future__ import annotations

import dataclasses

import torch
from click.testing import CliRunner
from export_helpers import make_checkpoint, one_torch_thread, tiny_config

from msdnet.training.models.assembly import bev_shape
from msdnet.training.nn.head_gated import FixedGroupNorm
from msdnet.training.nn.head_gated8 import Gated8ReconHead
from msdnet.training.nn.heads import build_head
from msdnet.training.recipe.checkpoint import load_checkpoint
from msdnet.training.recipe.gated8_distill import RetrainConfig, dense_targets, frame_loss, pool_up
from msdnet.training.recipe.gated_head import pooled_statistics
from msdnet.training.recipe.retrain_gated8 import main, norms_to_calibrate


def _heads(seed: int = 0) -> tuple[torch.nn.Module, Gated8ReconHead]:
    """(dense head, gated8 head with its weights, norms not calibrated yet)."""
    torch.manual_seed(seed)
    cfg = tiny_config()
    dense = build_head(cfg).eval()
    g8 = build_head(dataclasses.replace(cfg, head_kind="gated8")).eval()
    g8.load_state_dict(dense.state_dict(), strict=False)
    assert isinstance(g8, Gated8ReconHead)
    return dense, g8


def test_pool_up_takes_the_largest_child_and_drops_crops() -> None:
    occ = torch.arange(3 * 2 * 2, dtype=torch.float32).reshape(3, 2, 2)  # D 3: the last parent is cropped
    got = pool_up(occ, (2, 1, 1))
    assert got.tolist() == [[[7.0]], [[11.0]]]  # parent 1 has only the children at z = 2


def test_gate_targets_bound_every_decoded_child() -> None:
    dense, _ = _heads(1)
    x = torch.randn(1, *bev_shape(tiny_config()))
    (t,) = dense_targets(dense, [x], lambda z: z)
    g8, g4, g2 = (g.float() for g in t.gates)
    occ = t.occ.float()[0]  # (8, D2, H2, W2)
    assert torch.allclose(g2, occ.amax(0), atol=1e-3)  # float16 cache
    d2, h2, w2 = g2.shape
    up = g4.repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)[:d2, :h2, :w2]
    assert torch.all(up >= g2) and g8.max() == g2.max()


def test_a_gated_source_keeps_its_folded_norm() -> None:
    """From a dense head all three fixed norms are calibrated; from a gated head the 1/2 norm after
    the conv is fixed already (its statistics folded in), so only the two before it."""
    dense, g8 = _heads(0)
    gated = build_head(dataclasses.replace(tiny_config(), head_kind="gated"))
    assert norms_to_calibrate(g8, dense) == g8.fixed_norms()
    assert norms_to_calibrate(g8, gated) == g8.fixed_norms()[:2]


def test_retraining_falls_and_the_gates_do_not_move_the_trunk() -> None:
    dense, g8 = _heads(2)
    xs = list(torch.randn(2, 1, *bev_shape(tiny_config())))
    ts = dense_targets(dense, xs, lambda z: z)
    cfg = RetrainConfig(gate_weight=1.0)
    with one_torch_thread():
        for norm in g8.fixed_norms():
            norm.fold(*pooled_statistics(norm, lambda: [g8.packed(x) for x in xs]))
        for p in g8.parameters():
            p.requires_grad_(True)
        g8.zero_grad()
        frame_loss(g8, xs[0], ts[0], dataclasses.replace(cfg, gate_weight=0.0))[0].backward()
        no_gates = {n: p.grad.clone() for n, p in g8.named_parameters() if p.grad is not None}
        g8.zero_grad()
        frame_loss(g8, xs[0], ts[0], cfg)[0].backward()
        grads = {n: p.grad for n, p in g8.named_parameters() if p.grad is not None}
        gates = {"occ8.weight", "occ.0.weight", "occ.1.weight"}
        assert all(not no_gates[n].any() and grads[n].abs().sum() > 0 for n in gates)
        for n, g in no_gates.items():  # the gate terms only reach the gates' own convs
            if n.split(".")[0] not in ("occ8", "occ"):
                torch.testing.assert_close(grads[n], g, rtol=1e-5, atol=1e-7)
        opt = torch.optim.Adam(g8.parameters(), lr=1e-3)
        first = sum(float(frame_loss(g8, x, t, cfg)[0].detach()) for x, t in zip(xs, ts, strict=True))
        for _ in range(15):
            for x, t in zip(xs, ts, strict=True):
                opt.zero_grad()
                frame_loss(g8, x, t, cfg)[0].backward()
                opt.step()
        last = sum(float(frame_loss(g8, x, t, cfg)[0].detach()) for x, t in zip(xs, ts, strict=True))
    assert last < 0.9 * first


def test_command_writes_the_best_gated8_checkpoint(tmp_path, vod_root) -> None:
    ckpt = make_checkpoint(tmp_path / "dense", "student")
    out = tmp_path / "g8"
    args = [str(ckpt), "--dataset", "vod", "--data", str(vod_root), "--holdout", "0.3", "--threads", "1"]
    res = CliRunner().invoke(main, [*args, "--epochs", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "epoch 0 (calibrated)" in res.output and "epoch 2 (" in res.output and "fixed norm 2" in res.output
    model, cfg, state = load_checkpoint(out)
    head = model.teacher.head
    assert cfg.head_kind == "gated8" and isinstance(head, Gated8ReconHead) and state.init == str(ckpt)
    dense, _, _ = load_checkpoint(ckpt)
    assert isinstance(head.post2[0], FixedGroupNorm)
    assert not torch.equal(dense.teacher.head.post2[0].weight, head.post2[0].weight)  # folded
    again = CliRunner().invoke(main, [str(out), *args[1:], "--out", str(tmp_path / "x")])
    assert again.exit_code != 0 and "retrain from a dense or gated head" in again.output
    assert not (tmp_path / "x").exists()

    # --refit-gates: only the three gates move, and the slice gates' KL does not rise
    res = CliRunner().invoke(main, [str(out), *args[1:], "--refit-gates", "2", "--out", str(tmp_path / "g")])
    assert res.exit_code == 0, res.output
    refit, cfg2, state2 = load_checkpoint(tmp_path / "g")
    assert cfg2 == cfg and state2.init == str(ckpt) and "gates epoch 2" in res.output
    before, after = (float(v) for v in res.output.split("slice gates KL ")[-1].split(";")[0].split(" -> "))
    assert after <= before
    old, new = model.state_dict(), refit.state_dict()
    gates = [
        k for k in old if k.startswith(("teacher.head.occ8.", "teacher.head.occ.0.", "teacher.head.occ.1."))
    ]
    assert len(gates) == 6 and (after == before or any(not torch.equal(old[k], new[k]) for k in gates))
    assert all(torch.equal(old[k], new[k]) for k in old if k not in gates)
    bad = CliRunner().invoke(main, [str(ckpt), *args[1:], "--refit-gates", "1", "--out", str(tmp_path / "y")])
    assert bad.exit_code != 0 and "gated8 checkpoint" in bad.output and not (tmp_path / "y").exists()
