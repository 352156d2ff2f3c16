"""The DDIM schedule (runtime/spec/ddim.py) against hand-computed values and a numpy DDIM reference."""

from __future__ import annotations

import numpy as np
import pytest

from msdnet.runtime.spec import ddim

CFG = ddim.DiffusionConfig()


def ddim_update_reference(x_t, eps, abar_t, abar_prev):
    """Numpy reference of one deterministic DDIM step (eta = 0)."""
    x0 = (x_t - np.sqrt(1.0 - abar_t) * eps) / np.sqrt(abar_t)
    return np.sqrt(abar_prev) * x0 + np.sqrt(1.0 - abar_prev) * eps


def test_alphas_cumprod_by_hand():
    abar = ddim.alphas_cumprod(CFG)
    assert abar.shape == (CFG.num_train_steps + 1,)
    assert abar[0] == 1.0
    assert abar[1] == pytest.approx(1.0 - 1e-4)
    assert abar[2] == pytest.approx((1.0 - 1e-4) * (1.0 - (1e-4 + (0.02 - 1e-4) / 999)))
    assert np.all(np.diff(abar) < 0)


def test_paper_timesteps_interval_ten():
    ts = ddim.timesteps(CFG)
    assert ts[0] == 500 and ts[-1] == 10 and len(ts) == 50
    assert np.all(np.diff(ts) == -10)


@pytest.mark.parametrize("steps", [1, 3, 10, 50, 100])
def test_any_step_count(steps):
    coeffs = ddim.step_coefficients(CFG, steps)
    assert coeffs.shape == (steps, 3) and coeffs.dtype == np.float32
    assert coeffs[0, 0] == 500
    assert coeffs[-1, 2] == 1.0  # the last step lands on the clean abar_0
    np.testing.assert_array_equal(coeffs[:-1, 2], coeffs[1:, 1])  # chained


def test_bad_step_counts():
    with pytest.raises(ValueError):
        ddim.timesteps(CFG, 0)
    with pytest.raises(ValueError):
        ddim.timesteps(CFG, 501)


def test_exact_eps_recovers_x0():
    """With the true noise, DDIM steps from x_m land exactly on x_0."""
    rng = np.random.default_rng(0)
    x0 = rng.standard_normal((4, 8)).astype(np.float64)
    eps = rng.standard_normal((4, 8))
    x = ddim.q_sample(x0, 500, eps, CFG)
    for _, abar_t, abar_prev in ddim.step_coefficients(CFG, 10).astype(np.float64):
        x = ddim_update_reference(x, eps, abar_t, abar_prev)
    np.testing.assert_allclose(x, x0, atol=1e-5)
