"""How Eq. 14 (and the reconstruction loss) reach the light denoiser's weights through the DDIM loop.

MSDNet's Eq. 15 trains the denoiser on Eq. 10 (predict the noise) and, through the loop, on
Eq. 14 (the loop's output should be the teacher's feature) at once. Left alone, the loop's
gradient on the denoiser is orders of magnitude larger than Eq. 10's and the denoiser stops
predicting noise; detached, the loop stops paying (docs/training.md). This module gives the
training loop the rules in between (``LossWeights.denoiser_grad*``):

- ``steps``: the loop's gradient reaches the weights only through its last ``steps`` DDIM steps
  (truncated back-propagation; the earlier steps run with detached weights, their activations
  still carry gradients to RGFD and the adapter);
- ``ratio``: per-loss gradient normalisation. A tap on the weights measures the loop gradient's
  norm ``|g_loop|`` and Eq. 10's ``|g_diff|`` at every backward pass and scales the loop's part to
  ``ratio * |g_diff|`` (norms smoothed over steps, the scale of step k taken from steps < k, so it
  is known before the backward pass runs). ``ratio = 0`` leaves the loop gradient unscaled.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.func import functional_call

NORM_MOMENTUM = 0.9  # smoothing of the two squared gradient norms between steps


class _Tap(torch.autograd.Function):
    """Identity forward; backward adds |grad|^2 to ``sink[slot]`` and multiplies grad by ``scale``."""

    @staticmethod
    def forward(ctx, p: Tensor, sink: Tensor, slot: int, scale: Tensor) -> Tensor:  # type: ignore[override]
        ctx.sink, ctx.slot = sink, slot
        ctx.save_for_backward(scale)
        return p.clone()

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, None, None]:  # type: ignore[override]
        (scale,) = ctx.saved_tensors
        ctx.sink[ctx.slot] += grad.detach().pow(2).sum()
        return grad * scale, None, None, None


class GradBalance(nn.Module):
    """State of the gradient normalisation: smoothed squared norms [|g_diff|^2, |g_loop|^2] and
    this step's raw sums, in persistent buffers (so a resumed run continues them)."""

    def __init__(self, ratio: float) -> None:
        super().__init__()
        self.ratio = float(ratio)
        self.register_buffer("smoothed", torch.zeros(2, dtype=torch.float64))  # [diff, loop]
        # this step's squared norms, summed by the taps' backward (persistent: a checkpoint taken
        # between a backward pass and the next forward resumes bit for bit)
        self.register_buffer("sink", torch.zeros(2, dtype=torch.float64))

    def scale(self) -> Tensor:
        """The loop gradient's multiplier for this step (1 until both norms were seen)."""
        d, loop = self.smoothed.tolist()
        if self.ratio <= 0 or d <= 0 or loop <= 0:
            return torch.ones((), dtype=torch.float32)
        return torch.tensor(self.ratio * (d / loop) ** 0.5, dtype=torch.float32)

    def fold(self) -> None:
        """Move this step's norms into the smoothed ones (called at the next forward)."""
        seen = self.sink > 0
        if bool(seen.any()):
            first = self.smoothed == 0
            mixed = NORM_MOMENTUM * self.smoothed + (1 - NORM_MOMENTUM) * self.sink
            self.smoothed.copy_(torch.where(seen & first, self.sink, torch.where(seen, mixed, self.smoothed)))
        self.sink.zero_()

    def tapped(self, module: nn.Module, slot: int, scale: Tensor) -> dict[str, Tensor]:
        """``module``'s parameters seen through taps (slot 0: Eq. 10, 1: the loop) + its buffers."""
        state = {k: _Tap.apply(p, self.sink, slot, scale) for k, p in module.named_parameters()}
        state.update(dict(module.named_buffers()))
        return state


def loop_steps(
    step: nn.Module, n_steps: int, grad_steps: int, balance: GradBalance | None
) -> list[Callable[..., Tensor]]:
    """One callable per DDIM step of a training loop of ``n_steps``: the last ``grad_steps`` (all
    when 0, none when < 0) pass the loop's gradient to ``step``'s weights (through ``balance``'s
    tap when given), the others run on detached weights."""
    detached = {k: v.detach() for k, v in step.named_parameters()}
    detached.update(dict(step.named_buffers()))
    if balance is not None:
        live_state = balance.tapped(step, 1, balance.scale())
    else:
        live_state = None

    def frozen(*args: Tensor) -> Tensor:
        return functional_call(step, detached, args)

    def live(*args: Tensor) -> Tensor:
        return step(*args) if live_state is None else functional_call(step, live_state, args)

    if grad_steps < 0:
        first_live = n_steps
    else:
        first_live = 0 if grad_steps == 0 else max(0, n_steps - grad_steps)
    return [frozen if k < first_live else live for k in range(n_steps)]
