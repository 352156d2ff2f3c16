"""The 2026-12 training recipe: augmentation, the held-out selection slice, unit-variance latents,
the denoiser learning Eq. 10 only, the ablation switches, and the stage report."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from export_helpers import one_torch_thread, tiny_config

from msdnet.runtime.spec.grid import GRID_PRESETS
from msdnet.training.config import AugmentConfig
from msdnet.training.data.augment import augment_pair
from msdnet.training.data.batch import collate
from msdnet.training.data.datasets import make_splits, run_splits
from msdnet.training.models.assembly import build_model
from msdnet.training.models.latent import measure_latent_norm
from msdnet.training.recipe.distributed import DistInfo, EpochSampler

GRID = GRID_PRESETS["tiny"]


@pytest.fixture(autouse=True)
def _one_thread():
    with one_torch_thread():
        yield


def _cloud(n: int, cols: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(GRID.point_range[:3]), np.asarray(GRID.point_range[3:])
    xyz = lo + (0.1 + 0.8 * rng.random((n, 3))) * (hi - lo)
    return np.concatenate([xyz, rng.normal(size=(n, cols - 3))], axis=1).astype(np.float32)


def test_augmentation_moves_radar_and_lidar_alike_and_is_seeded():
    pts = _cloud(300, 5, 0)
    pts[:, 0] = np.clip(np.abs(pts[:, 0]), 1.0, 11.0)  # in front of the sensor, inside the grid
    no_drop = dataclasses.replace(AugmentConfig(), dropout_p=0.0, mirror_p=1.0)
    before = pts.copy()
    r, lidar = augment_pair(pts, pts[:, :3].copy(), GRID, no_drop, np.random.default_rng(1))
    assert np.array_equal(pts, before)  # inputs untouched (datasets cache them)
    # the same points went through the same transform (the LiDAR is also cut to the field of view)
    assert len(lidar) > 0 and {tuple(p) for p in lidar} <= {tuple(p) for p in r[:, :3]}
    assert set(r[:, 3]) <= set(pts[:, 3])  # the other columns are kept as they were
    # mirrored: y changed sign for most points (a small yaw and scale on top)
    assert np.corrcoef(r[:, 1], pts[np.isin(pts[:, 3], r[:, 3]), 1])[0, 1] < -0.9
    again = augment_pair(pts, pts[:, :3].copy(), GRID, no_drop, np.random.default_rng(1))
    assert np.array_equal(again[0], r) and np.array_equal(again[1], lidar)
    off = augment_pair(pts, pts[:, :3].copy(), GRID, AugmentConfig.off(), np.random.default_rng(1))
    assert np.array_equal(off[0], pts) and not AugmentConfig.off().enabled


def test_radar_dropout_thins_but_never_empties():
    pts = _cloud(400, 5, 2)
    pts[:, 0] = np.clip(np.abs(pts[:, 0]), 1.0, 11.0)
    thin = AugmentConfig(mirror_p=0.0, yaw_deg=0.0, scale=0.0, dropout_p=1.0, keep_min=0.0)
    sizes = [len(augment_pair(pts, pts[:, :3], GRID, thin, np.random.default_rng(s))[0]) for s in range(20)]
    assert min(sizes) >= 1 and max(sizes) <= 400 and np.mean(sizes) < 300


def test_holdout_is_the_end_of_the_training_range_and_never_validation(astyx_root):
    cfg = tiny_config("astyx")
    train, val = make_splits("astyx", astyx_root, cfg, val_fraction=0.25, max_frames=40)
    fit, select = make_splits("astyx", astyx_root, cfg, val_fraction=0.25, max_frames=40, holdout=0.2)
    assert fit.frame_ids + select.frame_ids == train.frame_ids  # contiguous, in order
    assert select.frame_ids == train.frame_ids[-6:]
    assert not set(select.frame_ids) & set(val.frame_ids)


def test_run_splits_are_the_ones_the_run_recorded(astyx_root):
    cfg = tiny_config("astyx")
    fit, select = run_splits("astyx", astyx_root, cfg, {"holdout": 0.15, "val_fraction": 0.25})
    want_fit, want_select = make_splits("astyx", astyx_root, cfg, val_fraction=0.25, holdout=0.15)
    assert select.frame_ids and select.frame_ids == want_select.frame_ids
    assert fit.frame_ids == want_fit.frame_ids
    train, val = run_splits("astyx", astyx_root, cfg, {"val_fraction": 0.25})  # a run with no holdout
    assert train.frame_ids == fit.frame_ids + select.frame_ids and val.frame_ids
    assert not set(val.frame_ids) & set(train.frame_ids)


def test_augmented_keys_are_reproducible_and_the_sampler_yields_them(astyx_root):
    cfg = tiny_config("astyx")
    fit, select = make_splits("astyx", astyx_root, cfg, max_frames=10, holdout=0.2, augment=AugmentConfig())
    assert fit.augments and not select.augments
    a, b = fit[(3, 1)], fit[(3, 1)]
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    c = fit[(4, 1)]
    assert not np.array_equal(a[1], c[1])  # another epoch, another transform
    assert np.array_equal(fit[1][1], fit._frame(1)[1])  # a plain index is the frame as it is
    sampler = EpochSampler(fit, DistInfo(), seed=0, with_epoch=True)
    sampler.set_position(2, 0)
    keys = list(sampler)
    assert all(k[0] == 2 for k in keys) and sorted(k[1] for k in keys) == list(range(len(fit)))


def _astyx_batch(astyx_root: Path, n: int = 2):
    cfg = tiny_config("astyx")
    fit, _ = make_splits("astyx", astyx_root, cfg, max_frames=8, holdout=0.25)
    return cfg, fit, collate([fit[i] for i in range(n)], cfg)


def test_latent_norm_whitens_the_teacher_and_the_head_folds_it_back(astyx_root):
    cfg, fit, batch = _astyx_batch(astyx_root)
    torch.manual_seed(0)
    teacher = build_model("teacher", cfg)
    norm = measure_latent_norm(teacher, fit, cfg, frames=len(fit))
    assert len(norm) == cfg.bev_channels
    student = build_model("student", dataclasses.replace(cfg, latent_norm=norm), teacher=teacher)
    z, _ = student._teacher_latent(collate([fit[i] for i in range(len(fit))], cfg))
    assert abs(float(z.mean())) < 0.05 and abs(float(z.std()) - 1.0) < 0.05
    with torch.no_grad():
        f = teacher.features(batch.lidar)
        z2, _ = student._teacher_latent(batch)
        occ_raw, _ = teacher.head(f)
        occ_norm, _ = student.head(z2)
    torch.testing.assert_close(occ_norm, occ_raw, atol=1e-5, rtol=1e-4)
    assert "latent_shift" not in student.state_dict()  # the config carries it, not the weights


def _student_terms(cfg, batch, **loss_fields: object) -> tuple[torch.nn.Module, dict[str, torch.Tensor]]:
    """A fresh tiny student with ``cfg.losses`` fields replaced, and its loss terms on ``batch``
    (same weights and noise every call)."""
    losses = dataclasses.replace(cfg.losses, **loss_fields)
    torch.manual_seed(0)
    model = build_model("student", dataclasses.replace(cfg, losses=losses)).train()
    torch.manual_seed(1)
    return model, model.losses(batch)


def test_the_denoiser_learns_eq10_only_unless_asked(astyx_root):
    cfg, _, batch = _astyx_batch(astyx_root)

    def denoiser_grads(grad_through_loop: bool, diff_only: bool) -> list[torch.Tensor]:
        model, terms = _student_terms(cfg, batch, denoiser_distill_grad=grad_through_loop)
        loss = cfg.losses.lambdas[3] * terms["diff"] if diff_only else terms["loss"]
        loss.backward()
        grads = [p.grad for p in model.step.parameters()]
        assert model.rgfd.down1.conv.weight.grad is not None or diff_only  # the loop still trains RGFD
        return grads

    eq10 = denoiser_grads(False, diff_only=True)
    for a, b in zip(denoiser_grads(False, diff_only=False), eq10, strict=True):
        torch.testing.assert_close(a, b)
    full = denoiser_grads(True, diff_only=False)
    assert any(not torch.allclose(a, b) for a, b in zip(full, eq10, strict=True))


@pytest.mark.parametrize("switch", ["use_rgfd", "use_dgfd", "use_adapter"])
def test_ablation_switches_build_and_train(astyx_root, switch):
    cfg, _, batch = _astyx_batch(astyx_root)
    torch.manual_seed(0)
    model = build_model("student", dataclasses.replace(cfg, **{switch: False})).train()
    terms = model.losses(batch)
    terms["loss"].backward()
    assert torch.isfinite(terms["loss"])
    if switch == "use_dgfd":
        assert float(terms["distill_diff"]) == 0.0 and float(terms["diff"]) == 0.0
        assert all(p.grad is None for p in model.step.parameters())
    else:
        assert float(terms["diff"].detach()) > 0.0
    assert ("gate" in terms) == (switch not in ("use_dgfd", "use_adapter"))
    occ, off = model.eval().predict(batch.radar)
    assert occ.shape[0] == 2 and off.shape[1] == 3


def test_stage_report_on_a_tiny_student(astyx_root, tmp_path):
    from click.testing import CliRunner

    from msdnet.benchmarks.cli import main
    from msdnet.training.config import TrainConfig
    from msdnet.training.recipe.checkpoint import CheckpointState, save_checkpoint

    cfg = tiny_config("astyx")
    torch.manual_seed(0)
    model = build_model("student", cfg)
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, model, cfg, CheckpointState(kind="student", train=TrainConfig(), epochs=1))
    args = ["stages", str(ckpt), "--dataset", "astyx", "--data", str(astyx_root), "--max-frames", "2"]
    res = CliRunner().invoke(main, [*args, "--threads", "1", "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    import json

    doc = json.loads((tmp_path / "out" / "stages.json").read_text())
    assert len(doc["eps_mse"]["buckets"]) == 10 and doc["frames"] == 2
    assert 0.0 < doc["gate"]["all"]["min"] <= doc["gate"]["all"]["max"] < 1.0
    # x_t is nearly eps at t -> T: the trivial baseline is near 0 there and near 1+ at small t
    buckets = doc["eps_mse"]["buckets"]
    assert buckets[-1]["x_t"] < 0.01 < buckets[0]["x_t"]
    assert {"before_loop", "after_loop"} == set(doc["loop"])
    teacher = tmp_path / "teacher"
    state = CheckpointState(kind="teacher", train=TrainConfig(), epochs=1)
    save_checkpoint(teacher, model.teacher, cfg, state)
    res = CliRunner().invoke(main, ["stages", str(teacher), *args[2:], "--out", str(tmp_path / "o2")])
    assert res.exit_code != 0 and "teacher checkpoint" in res.output


def test_conditioning_report_on_a_tiny_r2ldm(astyx_root, tmp_path):
    import json

    from click.testing import CliRunner

    from msdnet.benchmarks.cli import main
    from msdnet.training.config import TrainConfig
    from msdnet.training.recipe.checkpoint import CheckpointState, save_checkpoint

    cfg = tiny_config("astyx")
    torch.manual_seed(0)
    model = build_model("r2ldm", cfg)
    torch.nn.init.normal_(model.unet.out[2].weight, std=0.1)  # zero-initialised: ignores the condition
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, model, cfg, CheckpointState(kind="r2ldm", train=TrainConfig(), epochs=1))
    args = ["conditioning", str(ckpt), "--dataset", "astyx", "--data", str(astyx_root), "--max-frames", "3"]
    res = CliRunner().invoke(
        main, [*args, "--sample-frames", "1", "--threads", "1", "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "o" / "conditioning.json").read_text())
    assert doc["frames"] == 3 and len(doc["eps_mse"]["buckets"]) == 10
    mean = doc["eps_mse"]["mean_over_t"]
    assert mean["own"] != mean["shuffled"] and doc["eps_mse"]["own_over_shuffled"] > 0
    assert doc["samples"]["frames"] == 1 and doc["samples"]["own_vs_shuffled_relative_difference"] > 0
    assert (tmp_path / "o" / "conditioning.md").read_text().startswith("# Conditioning of")
    res = CliRunner().invoke(main, ["stages", *args[1:], "--out", str(tmp_path / "o2")])
    assert res.exit_code != 0 and "r2ldm checkpoint" in res.output


def test_the_gate_learns_from_the_alignment_loss_alone(astyx_root):
    """adapter_align > 0: the adapter's gradient is exactly that of the alignment term (the loop
    sees the gate as a constant); 0: the gate learns end to end through Eq. 14."""
    cfg, _, batch = _astyx_batch(astyx_root)

    def adapter_grads(align: float, term: str) -> list[torch.Tensor]:
        model, terms = _student_terms(cfg, batch, adapter_align=align)
        (terms[term] * (align if term == "align" else 1.0)).backward()
        return [p.grad if p.grad is not None else torch.zeros_like(p) for p in model.adapter.parameters()]

    for a, b in zip(adapter_grads(1.0, "loss"), adapter_grads(1.0, "align"), strict=True):
        torch.testing.assert_close(a, b)
    assert any(float(g.abs().sum()) > 0 for g in adapter_grads(0.0, "distill_diff"))
    assert all(float(g.abs().sum()) == 0 for g in adapter_grads(1.0, "distill_diff"))


def test_the_no_dgfd_ablation_exports_with_an_identity_loop(astyx_root, tmp_path):
    """w/o DGFD runs in the unchanged runtime: the adapter graph passes F_r^R, the step graph is
    the identity; onnxruntime gives the torch model's points."""
    from msdnet.benchmarks.eval_methods import PipelineMethod, RunSettings, TorchMethod
    from msdnet.export.cli import export_model
    from msdnet.runtime.io.datasets import open_dataset
    from msdnet.runtime.io.datasets.preprocess import preprocess_frame
    from msdnet.training.config import TrainConfig
    from msdnet.training.recipe.checkpoint import CheckpointState, save_checkpoint

    cfg = dataclasses.replace(tiny_config("astyx"), use_dgfd=False)
    torch.manual_seed(0)
    model = build_model("student", cfg).eval()
    ckpt = tmp_path / "ckpt"
    save_checkpoint(ckpt, model, cfg, CheckpointState(kind="student", train=TrainConfig(), epochs=1))
    export_model(model, "student", cfg, tmp_path / "onnx", str(ckpt))
    frame = preprocess_frame(open_dataset("astyx", astyx_root).get("000000"), cfg.grid)
    settings = RunSettings(threads=1)
    onnx_pts = PipelineMethod(tmp_path / "onnx", settings).run(frame.radar, seed=3)
    torch_pts = TorchMethod(ckpt, settings).run(frame.radar, seed=4)  # no noise reaches the output
    assert len(onnx_pts) > 0 and onnx_pts.shape == torch_pts.shape
    np.testing.assert_allclose(onnx_pts, torch_pts, atol=1e-4)
