"""Unit-variance latents: the per-channel shift and scale of the teacher's F_l^D.

The trained teacher's BEV features are far from N(0, I) (Astyx lite: std ~0.39 around per-channel
means ~0.22), so at the start step m = 500 of the forward chain (Eq. 9) the signal-to-noise ratio is
~0.006 and end-to-end training switches the diffusion off (the adapter's gate goes to 1). Diffusion
(Eq. 9-13), the adapter's mix with N(0, I) (Eq. 12) and the distillation losses (Eq. 8, 14) therefore
work on ``z = (F_l^D - shift) / scale``, measured per channel on training frames once the teacher is
trained and kept in ``ModelConfig.latent_norm``. The shared head sees ``F = z * scale + shift``:
:class:`LatentHead` folds that into ``recon_head.onnx``, so the runtime is unchanged.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig


def norm_tensors(cfg: ModelConfig) -> tuple[Tensor, Tensor]:
    """(shift (1, C, 1, 1), scale (1, C, 1, 1)) float32 of ``cfg.latent_norm`` (identity when empty)."""
    c = cfg.bev_channels
    if not cfg.latent_norm:
        return torch.zeros(1, c, 1, 1), torch.ones(1, c, 1, 1)
    arr = torch.tensor(cfg.latent_norm, dtype=torch.float32)  # (C, 2) [shift, scale]
    return arr[:, 0].reshape(1, c, 1, 1), arr[:, 1].reshape(1, c, 1, 1)


class LatentHead(nn.Module):
    """The teacher's head on normalised latents: every call de-normalises first.

    Models build it on the fly (``StudentModel.head``) rather than keep it, so the head's weights
    are listed once in a state dict, under the teacher; ``shift`` / ``scale`` export as constants.
    """

    def __init__(self, head: nn.Module, shift: Tensor, scale: Tensor) -> None:
        super().__init__()
        self._head = head
        self.register_buffer("shift", shift, persistent=False)  # (1, C, 1, 1)
        self.register_buffer("scale", scale, persistent=False)  # (1, C, 1, 1)

    def _f(self, z: Tensor) -> Tensor:
        return z * self.scale + self.shift  # (B, C, H8, W8) back to the teacher's scale

    def multi_scale(self, z: Tensor, rows: Tensor | None = None) -> list[tuple[Tensor, Tensor]]:
        """As ``ReconHead.multi_scale`` on de-normalised z."""
        return self._head.multi_scale(self._f(z), rows)

    def packed(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """As ``ReconHead.packed`` on de-normalised z (``recon_head.onnx``)."""
        return self._head.packed(self._f(z))

    def sparse(self, z: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """As ``ReconHead.sparse`` on de-normalised z (``recon_head_sparse.onnx``)."""
        return self._head.sparse(self._f(z), gate)

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor]:
        return self._head(self._f(z))


@torch.no_grad()
def measure_latent_norm(
    teacher: nn.Module, dataset: object, cfg: ModelConfig, frames: int = 64
) -> tuple[tuple[float, float], ...]:
    """Per-channel (mean, std) of the teacher's F_l^D over all BEV cells of up to ``frames``
    evenly spaced frames of ``dataset`` (a training split; plain, un-augmented frames).

    Returns ``cfg.bev_channels`` pairs (shift, scale), scale floored at 1e-3.
    """
    from msdnet.training.data.batch import collate

    n = len(dataset)  # type: ignore[arg-type]
    picks = sorted({int(i) for i in np.linspace(0, n - 1, min(frames, n))})
    total = torch.zeros(cfg.bev_channels, dtype=torch.float64)
    total_sq = torch.zeros(cfg.bev_channels, dtype=torch.float64)
    count = 0
    teacher.eval()
    for i in picks:
        batch = collate([dataset[i]], cfg)  # type: ignore[index]
        f = teacher.features(batch.lidar).double()  # (1, C, H8, W8)
        total += f.sum(dim=(0, 2, 3))
        total_sq += (f * f).sum(dim=(0, 2, 3))
        count += f.shape[0] * f.shape[2] * f.shape[3]
    mean = total / count
    std = (total_sq / count - mean * mean).clamp_min(0.0).sqrt().clamp_min(1e-3)
    return tuple((float(m), float(s)) for m, s in zip(mean, std, strict=True))
