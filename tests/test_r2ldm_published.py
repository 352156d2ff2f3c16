"""R2LDM as published (``--recipe published``): schedule, loss weights, latent, sampler parity."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from export_helpers import one_torch_thread, tiny_config

from msdnet.runtime.spec import cosine_logsnr as cs
from msdnet.training.published_config import with_recipe

# torch vs onnxruntime tolerances of the published sampler on the tiny preset
STEP_REL_TOL = 1e-4  # largest relative error of one step graph call
POINTS_DIFFER_TOL = 0.002  # share of decoded points that may differ end to end
SHIFT_TOL = 1e-4  # metres: largest shift of a matched point


def _cfg():
    return dataclasses.replace(with_recipe(tiny_config("sim"), "published"), threshold=0.45)


def test_cosine_log_snr_hand_values():
    # lambda(0) = 15, lambda(1) = -15; at t = 1/2 the two atan ends sum to pi / 2, so tan = 1, lambda = 0
    assert cs.log_snr(0.0) == pytest.approx(15.0, abs=1e-9)
    assert cs.log_snr(1.0) == pytest.approx(-15.0, abs=1e-9)
    assert cs.log_snr(0.5) == pytest.approx(0.0, abs=1e-12)
    a, s = cs.alpha_sigma(0.0)  # SNR 1: alpha = sigma = sqrt(1/2)
    assert a == pytest.approx(math.sqrt(0.5)) and s == pytest.approx(math.sqrt(0.5))
    lam = cs.log_snr(np.linspace(0, 1, 11))
    assert np.all(np.diff(lam) < 0)  # monotone: noisier as t grows


def test_min_snr_weights_hand_values():
    # w = min(SNR, 5) / SNR: SNR 10 -> 0.5, SNR 1 -> 1, SNR 2 -> 1, SNR 50 -> 0.1
    lam = np.log([10.0, 1.0, 2.0, 50.0])
    np.testing.assert_allclose(cs.min_snr_weight(lam), [0.5, 1.0, 1.0, 0.1], rtol=1e-12)


def test_renoise_brings_the_marginal_back_to_t():
    lam_t, lam_s = 1.0, 3.0
    a, b = cs.renoise_coefficients(lam_t, lam_s)
    at, st = cs.alpha_sigma(lam_t)
    as_, ss = cs.alpha_sigma(lam_s)
    assert a * as_ == pytest.approx(at)  # signal scale of x_t
    assert a**2 * ss**2 + b**2 == pytest.approx(st**2)  # noise variance of x_t


def test_plan_repeats_every_step_but_the_last():
    plan = cs.sampler_plan(3, 4)
    assert plan.coefficients.shape == (9, 3)  # (N - 1) R + 1
    renoised = np.isfinite(plan.renoise[:, 0])
    assert renoised.tolist() == [True, True, True, False] * 2 + [False]
    assert plan.coefficients[0, 0] == pytest.approx(-15.0)  # first call at t = 1
    assert plan.coefficients[-1, 2] == pytest.approx(1 / (1 + math.exp(-15.0)))  # ends at t = 0


def test_latent_is_bounded_and_empty_cells_are_minus_one():
    from msdnet.training.data.batch import make_encoder_input
    from msdnet.training.models.r2ldm_published import LPCRAutoencoder, latent_shape

    cfg = _cfg()
    torch.manual_seed(0)
    with one_torch_thread():
        model = LPCRAutoencoder(cfg)
        pts = np.array([[3.0, 0.0, 0.5], [3.1, 0.1, 0.6], [8.0, -2.0, 1.0]], np.float32)
        z = model.features(make_encoder_input([pts], cfg.grid, cfg.max_voxels_lidar))
    assert tuple(z.shape[1:]) == latent_shape(cfg)
    assert z.min() >= -1.0 and z.max() < 1.0
    occupied = (z > -1.0).any(1)[0]  # (H4, W4): cells with any channel above -1
    assert 0 < int(occupied.sum()) <= 2 * 9 * 2  # only near the two point clusters


def test_loss_applies_min_snr_weights(monkeypatch):
    from msdnet.training.models import r2ldm_published as rp

    lam = torch.tensor([math.log(10.0), math.log(50.0)])
    expect = torch.tensor([0.5, 0.1])
    snr = lam.exp()
    assert torch.allclose(snr.clamp(max=5.0) / snr, expect)
    t = torch.tensor([0.0, 0.5, 1.0])
    ref = torch.from_numpy(cs.log_snr(t.numpy())).float()
    assert torch.allclose(rp.log_snr_torch(t, -15.0, 15.0), ref, atol=1e-4)


def test_torch_and_onnxruntime_sample_the_same_points(tmp_path):
    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest, write_manifest
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.engine.pointcloud import PointCloud
    from msdnet.training.data.batch import make_encoder_input
    from msdnet.training.models.assembly import build_model

    cfg = dataclasses.replace(_cfg(), occupancy_prior=0.5)
    torch.manual_seed(0)
    with one_torch_thread():
        teacher = build_model("teacher", cfg)
        model = build_model("r2ldm", cfg, teacher).eval()
        params, _ = export_all(model, "r2ldm", cfg, tmp_path)
        manifest = build_manifest(tmp_path, "r2ldm", cfg, params, "test")
        assert manifest["sampler"]["resample"] == cfg.published.resample
        write_manifest(tmp_path, manifest)
        pipe = Pipeline.from_dir(tmp_path, threads=1)
        rng = np.random.default_rng(5)
        pts = np.zeros((200, 3), np.float32)
        lo, hi = np.array(cfg.grid.point_range[:3]), np.array(cfg.grid.point_range[3:])
        pts[:] = lo + (hi - lo) * rng.random((200, 3)) * 0.99
        got = pipe(PointCloud(pts, ("x", "y", "z")), seed=3)
        assert got.stats["network_calls"] == (cfg.published.sample_steps - 1) * cfg.published.resample + 1
        gen = np.random.default_rng(3)
        noise = gen.standard_normal(pipe.bev_shape, dtype=np.float32)
        enc = make_encoder_input([pts], cfg.grid, cfg.max_voxels_radar)
        with torch.no_grad():
            occ, off = model.predict(enc, noise=torch.from_numpy(noise), rng=gen)
    from msdnet.export.verify import compare_points
    from msdnet.runtime.engine.decode import decode_occupancy

    ref, _ = decode_occupancy(occ[0].numpy(), off[0].numpy(), cfg.grid, cfg.threshold)
    assert len(ref) > 100
    differ, shift = compare_points(ref, got.points, cfg.grid)
    assert differ <= POINTS_DIFFER_TOL * len(ref)
    assert shift <= SHIFT_TOL
    # one step graph call against torch, at the first (noisiest) row of the plan
    row = pipe.coefficients()[0]
    feeds = {"x_t": noise, "cond": np.tanh(noise), "t": row[0:1], "abar_t": row[1:2], "abar_prev": row[2:3]}
    (ort_out,) = pipe.sessions["r2ldm_step.onnx"].run(None, feeds)
    with torch.no_grad():
        ref_out = model.step(
            *(torch.from_numpy(feeds[k]) for k in ("x_t", "cond", "t", "abar_t", "abar_prev"))
        )
    rel = np.abs(ort_out - ref_out.numpy()).max() / np.abs(ref_out.numpy()).max()
    assert rel <= STEP_REL_TOL


def test_resampling_draws_fresh_noise():
    from msdnet.training.models.assembly import build_model

    cfg = _cfg()
    torch.manual_seed(0)
    with one_torch_thread():
        model = build_model("r2ldm", cfg, build_model("teacher", cfg)).eval()
        cond = torch.zeros(1, *model.encoder.shape4[1:]).expand(1, cfg.published.latent_channels, -1, -1)
        x = torch.randn_like(cond)
        with torch.no_grad():
            a = model.sample(cond, x, 4, np.random.default_rng(1))
            b = model.sample(cond, x, 4, np.random.default_rng(1))
            c = model.sample(cond, x, 4, np.random.default_rng(2))
    assert torch.equal(a, b)  # same draws, same sample
    assert not torch.equal(a, c)  # the re-noising draws change the sample
    assert a.abs().max() <= 1.01  # x0 clipped to +-1; the last step ends at sigma(15) = 5.5e-4


def test_published_recipe_refuses_the_student(tmp_path):
    from click.testing import CliRunner

    from msdnet.training.cli import main

    res = CliRunner().invoke(
        main,
        [
            "student",
            "--recipe",
            "published",
            "--dataset",
            "sim",
            "--data",
            str(tmp_path),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert res.exit_code == 2 and "published is an R2LDM recipe" in res.output


def test_latency_times_it_on_msdnets_scan_by_column_name(tmp_path):
    """``msdnet-bench latency --model MSDNET --r2ldm PUBLISHED``: the published R2LDM reads x y z
    only, MSDNet's scan has more columns; the suite hands it the scan by column name (regression:
    "points must be (N, 3)" on Astyx models)."""
    from msdnet.benchmarks.latency.suite import _named
    from msdnet.benchmarks.latency.timing import synthetic_radar, time_stages
    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest, write_manifest
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.errors import MsdnetError
    from msdnet.training.models.assembly import build_model

    cfg = _cfg()
    msdnet_columns = ("x", "y", "z", "v_r", "mag")  # an Astyx MSDNet's radar columns
    torch.manual_seed(0)
    with one_torch_thread():
        model = build_model("r2ldm", cfg, build_model("teacher", cfg)).eval()
        params, _ = export_all(model, "r2ldm", cfg, tmp_path)
        write_manifest(tmp_path, build_manifest(tmp_path, "r2ldm", cfg, params, "test"))
    pipe = Pipeline.from_dir(tmp_path, threads=1)
    assert pipe.columns == ("x", "y", "z")
    scan = synthetic_radar(msdnet_columns, cfg.grid, 200, seed=1)  # (200, 5)
    with pytest.raises(MsdnetError, match="points must be"):
        pipe(scan)
    runs = time_stages(pipe, _named(scan, msdnet_columns), None, 0.5, 1)
    assert all(len(v) == 1 and v[0] > 0 for v in runs.seconds.values() if v)
    ref = pipe(scan[:, :3].copy(), threshold=0.5)
    assert runs.decoded == len(ref.points)  # the same x y z, the same seed: the same points
