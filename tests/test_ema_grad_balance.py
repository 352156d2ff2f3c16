"""The weights' EMA in the training loop, and how the loop's gradient reaches the light denoiser
(training/nn/grad_balance.py: truncated back-propagation and per-loss gradient normalisation)."""

from __future__ import annotations

from dataclasses import replace

import torch
from test_checkpoint import CFG, TCFG, ToyBatch, ToyData, ToyModel

from msdnet.training.nn.grad_balance import GradBalance, loop_steps
from msdnet.training.recipe.checkpoint import MODEL_FILE, load_weights, read_checkpoint
from msdnet.training.recipe.loop import RunSpec, train

EMA_TCFG = replace(TCFG, ema_decay=0.8)


def _run(out, epochs=3, tcfg=EMA_TCFG, **kw):
    torch.manual_seed(tcfg.seed)
    model = ToyModel()
    spec = RunSpec(kind="teacher", out=out, epochs=epochs, **kw)
    state = train(model, CFG, tcfg, ToyData(20, 1), ToyData(6, 2), spec, collate_fn=ToyBatch)
    return model, state


def test_ema_is_scored_and_kept_in_best_while_last_keeps_the_raw_weights(tmp_path):
    model, state = _run(tmp_path / "ema")
    raw, _ = _run(tmp_path / "raw", tcfg=TCFG)
    assert torch.equal(model.lin.weight, raw.lin.weight)  # the EMA never feeds back into training
    last = ToyModel()
    load_weights(last, tmp_path / "ema" / "last" / MODEL_FILE)
    assert torch.equal(last.lin.weight, model.lin.weight)  # last/: raw weights
    best = ToyModel()
    load_weights(best, tmp_path / "ema" / "best" / MODEL_FILE)
    assert not torch.equal(best.lin.weight, model.lin.weight)  # best/: the EMA
    ema_hist = [h["val_loss"] for h in state.history]
    raw_hist = [h["val_loss"] for h in read_checkpoint(tmp_path / "raw" / "last")[2].history]
    assert ema_hist != raw_hist  # validation scored other weights


def test_resume_continues_the_ema_bit_for_bit(tmp_path):
    _run(tmp_path / "full")
    _run(tmp_path / "cut", stop_after=1)
    _run(tmp_path / "cut", resume=True)
    a, b = ToyModel(), ToyModel()
    load_weights(a, tmp_path / "full" / "best" / MODEL_FILE)
    load_weights(b, tmp_path / "cut" / "best" / MODEL_FILE)
    assert torch.equal(a.lin.weight, b.lin.weight)


class _Step(torch.nn.Module):
    """x -> x * w (a one-weight 'denoiser step' whose gradient is easy to write down)."""

    def __init__(self) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(0.9))

    def forward(self, x, t, a, b):
        return x * self.w


def _loop(steps, x):
    for s in steps:
        x = s(x, None, None, None)
    return x


def test_truncated_loop_passes_gradient_through_the_last_k_steps_only():
    step = _Step()
    x = torch.tensor(2.0, requires_grad=True)  # upstream (RGFD) gets its gradient in every mode
    for k, expected in ((0, 4 * 2 * 0.9**3), (1, 2 * 0.9**3), (-1, None)):
        step.w.grad, x.grad = None, None
        _loop(loop_steps(step, 4, k, None), x).backward()
        # d(x w^4)/dw through all 4 uses = 4 x w^3; through the last one only = x w^3
        assert abs(x.grad.item() - 0.9**4) < 1e-6
        if expected is None:
            assert step.w.grad is None
        else:
            assert abs(step.w.grad.item() - expected) < 1e-5


def test_normalised_loop_gradient_is_scaled_to_the_ratio_of_eq10s():
    step, balance = _Step(), GradBalance(ratio=0.5)
    x = torch.tensor(2.0)
    for _ in range(2):  # the first pass measures, the second applies the scale
        balance.fold()
        step.w.grad = None
        loop_out = _loop(loop_steps(step, 4, 0, balance), x)
        diff = torch.func.functional_call(step, balance.tapped(step, 0, torch.ones(())), (x, 0, 0, 0))
        (loop_out + 3.0 * diff).backward()
    g_loop, g_diff = 4 * 2 * 0.9**3, 3.0 * 2
    scale = 0.5 * g_diff / g_loop
    assert abs(balance.scale().item() - scale) < 1e-6
    assert abs(step.w.grad.item() - (g_diff + scale * g_loop)) < 1e-5
