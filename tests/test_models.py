"""Assembled models: shapes per preset, parameter budget, gradients through the DDIM loop,
and the tiny teacher / student each overfitting one real Astyx frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msdnet.benchmarks.params import PAPER_MILLIONS, parameter_table
from msdnet.training.config import MODEL_PRESETS, ModelConfig
from msdnet.training.data.batch import Batch, EncoderInput, collate
from msdnet.training.data.targets import scale_shapes
from msdnet.training.models.assembly import StudentModel, TeacherModel, bev_shape, build_model

# Astyx radar columns (x y z v_r mag); the normalisation defaults follow the names.
ASTYX_TINY = dataclasses.replace(
    MODEL_PRESETS["tiny"], radar_columns=("x", "y", "z", "v_r", "mag"), radar_feature_norm=()
)


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Tiny tensors: one intra-op thread is fastest, and on the shared 2 cores a second
    thread's spin-waiting cost ~10x the CPU time of these tests."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _synthetic_batch(cfg: ModelConfig, seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    lo = np.asarray(cfg.grid.point_range[:3])
    hi = np.asarray(cfg.grid.point_range[3:])

    def cloud(n: int, cols: int) -> np.ndarray:
        xyz = lo + rng.random((n, 3)) * (hi - lo)
        return np.concatenate([xyz, rng.normal(size=(n, cols - 3))], axis=1).astype(np.float32)

    samples = [(cloud(n, len(cfg.radar_columns)), cloud(8 * n, 3)) for n in (120, 40)]
    return collate(samples, cfg)


def _meta_batch(cfg: ModelConfig, batch: int = 2) -> Batch:
    """Shapes only (torch 'meta' device): no memory, no arithmetic."""

    def inp(n_cols: int) -> EncoderInput:
        v = (900, 400, 200, 100)  # voxels per level

        def rules(n: int) -> torch.Tensor:
            return torch.empty(n, 27, dtype=torch.long, device="meta")

        return EncoderInput(
            torch.empty(v[0], n_cols, device="meta"),
            [rules(n) for n in v],
            [rules(n) for n in v[1:]],
            torch.empty(v[-1], 4, dtype=torch.long, device="meta"),
            batch,
        )

    targets = [
        (torch.empty(batch, *s, device="meta"), torch.empty(batch, 3, *s, device="meta"))
        for s in scale_shapes(cfg.grid)
    ]
    return Batch(inp(len(cfg.radar_columns)), inp(len(cfg.lidar_columns)), targets, batch)


def test_tiny_full_forward_every_kind():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    batch = _synthetic_batch(cfg)
    d, h, w = cfg.grid.shape_zyx
    teacher = build_model("teacher", cfg)
    scale_terms = {f"{t}_{s}" for t in ("occ", "off") for s in ("s4", "s2", "s1")}
    want = {
        "teacher": {"loss", "recon"} | scale_terms,
        "student": {"loss", "recon", "distill_rec", "distill_diff", "diff", "gate", "align"} | scale_terms,
        "r2ldm": {"loss", "diff"},
    }
    for kind in ("teacher", "student", "r2ldm"):
        model = teacher if kind == "teacher" else build_model(kind, cfg, teacher)
        terms = model.losses(batch)
        assert set(terms) == want[kind]
        assert all(v.shape == () and torch.isfinite(v) for v in terms.values())
        inp = batch.lidar if kind == "teacher" else batch.radar
        noise = torch.randn(2, *bev_shape(cfg))
        with torch.no_grad():
            occ, off = model.predict(inp, noise)
            occ2, _ = model.predict(inp, noise)
        assert occ.shape == (2, d, h, w) and off.shape == (2, 3, d, h, w)
        assert torch.equal(occ, occ2)  # same noise, same output
        assert 0.0 <= float(occ.min()) and float(occ.max()) <= 1.0
        half = torch.tensor(cfg.grid.voxel_size).reshape(1, 3, 1, 1, 1) / 2
        assert torch.all(off.abs() <= half)
    assert torch.equal(
        torch.tensor(teacher.losses(batch)["loss"].item()),
        torch.tensor(teacher.losses(batch)["loss"].item()),
    )


@pytest.mark.parametrize("preset", ["lite", "paper"])
def test_shapes_on_meta_device(preset):
    cfg = MODEL_PRESETS[preset]
    batch = _meta_batch(cfg)
    with torch.device("meta"):
        student = build_model("student", cfg)
        r2ldm = build_model("r2ldm", cfg, student.teacher)
    for model in (student.teacher, student, r2ldm):
        assert model.losses(batch)["loss"].shape == ()
    d, h, w = cfg.grid.shape_zyx
    for model in (student, r2ldm):
        occ, off = model.predict(batch.radar, sample_steps=2)
        assert occ.shape == (2, d, h, w) and off.shape == (2, 3, d, h, w)
    outs = student.head.multi_scale(torch.empty(2, *bev_shape(cfg), device="meta"))
    for (logits, off), shape in zip(outs, scale_shapes(cfg.grid), strict=True):
        assert logits.shape == (2, 1, *shape) and off.shape == (2, 3, *shape)


def test_parameter_budget():
    paper = parameter_table(MODEL_PRESETS["paper"])
    assert paper["student.total"] <= PAPER_MILLIONS["student"] * 1e6
    assert paper["r2ldm.total"] <= PAPER_MILLIONS["r2ldm"] * 1e6
    assert paper["r2ldm.total"] > 5 * paper["student.total"]  # the heavy baseline stays heavy
    parts = ("encoder", "rgfd", "adapter", "denoiser", "head")
    assert paper["student.total"] == sum(paper[f"student.{p}"] for p in parts)
    lite = parameter_table(MODEL_PRESETS["lite"])
    assert lite["student.total"] < paper["student.total"]
    # The counts are those of the real modules.
    student = StudentModel(MODEL_PRESETS["tiny"])
    tiny = parameter_table(MODEL_PRESETS["tiny"])
    assert tiny["student.rgfd"] == sum(p.numel() for p in student.rgfd.parameters())


def test_teacher_frozen_head_shared_and_gradients_reach_rgfd_through_ddim_loop():
    cfg = MODEL_PRESETS["tiny"]
    assert cfg.train_sample_steps >= 2
    torch.manual_seed(0)
    batch = _synthetic_batch(cfg, seed=3)
    student = build_model("student", cfg, TeacherModel(cfg))
    assert student.head._head is student.teacher.head  # the head on de-normalised latents
    student.train()
    assert not student.teacher.training and student.rgfd.training
    trainable = {id(p) for p in student.parameters() if p.requires_grad}
    assert not any(id(p) in trainable for p in student.teacher.parameters())
    terms = student.losses(batch)
    # Only through the loop: F_r^R -> adapter -> DDIM steps -> F_r^D -> head / distillation.
    (terms["recon"] + terms["distill_diff"]).backward()
    for name, p in student.rgfd.named_parameters():
        assert p.grad is not None, name
    assert sum(float(p.grad.abs().sum()) for p in student.rgfd.parameters()) > 0
    assert all(p.grad is None for p in student.denoiser.parameters())  # it learns Eq. 10 only
    assert all(p.grad is None for p in student.teacher.parameters())
    losses = dataclasses.replace(cfg.losses, denoiser_distill_grad=True)  # the old recipe
    student = build_model("student", dataclasses.replace(cfg, losses=losses), TeacherModel(cfg)).train()
    terms = student.losses(batch)
    (terms["recon"] + terms["distill_diff"]).backward()
    assert float(student.denoiser.head[2].weight.grad.abs().sum()) > 0  # (the head starts at zero)


@pytest.fixture(scope="module")
def astyx_batch(astyx_root) -> Batch:
    from msdnet.runtime.io.datasets.astyx import AstyxDataset
    from msdnet.runtime.io.datasets.preprocess import preprocess_frame

    cfg = ASTYX_TINY
    frame = preprocess_frame(AstyxDataset(astyx_root).get("000000"), cfg.grid)
    radar = frame.radar.select(cfg.radar_columns).points
    lidar = frame.lidar.select(cfg.lidar_columns).points
    assert len(radar) > 50 and len(lidar) > 500
    return collate([(radar, lidar)], cfg)


def _fit(model: torch.nn.Module, batch: Batch, steps: int, lr: float) -> tuple[float, float]:
    """Adam on one batch; (loss before, loss after), both with the same fixed noise."""

    def loss_at_seed() -> float:
        torch.manual_seed(123)
        with torch.no_grad():
            return float(model.losses(batch)["loss"])

    before = loss_at_seed()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    for _ in range(steps):
        loss = model.losses(batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    return before, loss_at_seed()


@pytest.fixture(scope="module")
def fitted_teacher(astyx_batch) -> tuple[TeacherModel, float, float]:
    torch.manual_seed(0)
    teacher = build_model("teacher", ASTYX_TINY)
    before, after = _fit(teacher, astyx_batch, steps=350, lr=3e-3)
    return teacher, before, after


def test_tiny_teacher_overfits_one_astyx_frame(fitted_teacher):
    _, before, after = fitted_teacher
    assert after <= before / 10, (before, after)


def test_tiny_student_overfits_one_astyx_frame(fitted_teacher, astyx_batch):
    teacher = fitted_teacher[0]
    torch.manual_seed(0)
    student = build_model("student", ASTYX_TINY, teacher)
    head_before = [p.detach().clone() for p in teacher.head.parameters()]
    torch.manual_seed(123)
    with torch.no_grad():
        rec_before = float(student.losses(astyx_batch)["distill_rec"])
    before, after = _fit(student, astyx_batch, steps=150, lr=3e-3)
    torch.manual_seed(123)
    with torch.no_grad():
        rec_after = float(student.losses(astyx_batch)["distill_rec"])
    # Both fall well: the total keeps the adapter's noise at m (gate ~0.7), which also slows Eq. 8
    assert rec_after <= rec_before / 2, (rec_before, rec_after)
    assert after <= before / 2, (before, after)
    for p, q in zip(teacher.head.parameters(), head_before, strict=True):
        assert torch.equal(p, q)  # the shared head stayed frozen
