"""Torch datasets over the runtime's readers: frames -> preprocess -> (radar, LiDAR) arrays.

One sample is ``(radar (N, len(cfg.radar_columns)), lidar (M, len(cfg.lidar_columns)))``,
float32, radar frame, after ``msdnet.runtime.io.datasets.preprocess.preprocess_frame`` (LiDAR cropped to
the grid and the radar's field of view, ground removed), which is what
``msdnet.training.data.batch.collate`` takes. Train and validation are contiguous frame ranges
(the real datasets are drives in sequence; a random split would leak neighbouring frames).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import Dataset

from msdnet.runtime.errors import MsdnetError
from msdnet.training.config import AugmentConfig, ModelConfig

# --dataset choices; "sim" is the simulator's VoD layout, "sim-astyx" its Astyx rig
DATASETS = ("vod", "astyx", "sim", "sim-astyx")
# Radar columns fed to the model per dataset (Astyx has magnitude instead of RCS and no
# ego-motion-compensated velocity).
RADAR_COLUMNS: dict[str, tuple[str, ...]] = {
    "vod": ("x", "y", "z", "rcs", "v_r_compensated"),
    "sim": ("x", "y", "z", "rcs", "v_r_compensated"),
    "astyx": ("x", "y", "z", "v_r", "mag"),
    "sim-astyx": ("x", "y", "z", "v_r", "mag"),  # as Astyx: pretrain here, fine-tune on astyx
}
CACHE_BYTES = 2 << 30  # preprocessed frames kept in memory per process, at most


def config_for_dataset(cfg: ModelConfig, dataset: str) -> ModelConfig:
    """``cfg`` with the dataset's radar columns (and their normalisation re-derived)."""
    if dataset not in RADAR_COLUMNS:
        raise MsdnetError(None, f"unknown dataset {dataset!r} (choose from {', '.join(DATASETS)})")
    cols = RADAR_COLUMNS[dataset]
    if cols == cfg.radar_columns:
        return cfg
    return replace(cfg, radar_columns=cols, radar_feature_norm=())


def split_indices(frame_ids: list[str], val_fraction: float) -> tuple[list[int], list[int]]:
    """(train, val) positions in ``frame_ids``: contiguous ranges by ``split_contiguous``.

    Both parts must be non-empty (MsdnetError otherwise).
    """
    from msdnet.runtime.io.datasets import split_contiguous

    if not 0.0 < val_fraction < 1.0:
        raise MsdnetError(None, f"validation fraction must be in (0, 1), got {val_fraction}")
    train_ids, val_ids = split_contiguous(frame_ids, val_fraction)
    if not train_ids or not val_ids:
        raise MsdnetError(
            None,
            f"{len(frame_ids)} frames give {len(train_ids)} train / {len(val_ids)} validation "
            f"frames at validation fraction {val_fraction}: both need at least one",
        )
    pos = {fid: i for i, fid in enumerate(frame_ids)}
    return [pos[f] for f in train_ids], [pos[f] for f in val_ids]


class PairDataset(Dataset):
    """Preprocessed (radar, LiDAR) pairs of some frames of a runtime reader, cached in memory.

    With ``augment`` (training frames), a key ``(epoch, i)`` returns frame ``i`` under the random
    transform seeded by ``(augment_seed, epoch, i)`` (``training.data.augment``); a plain index
    returns the frame as it is.
    """

    def __init__(
        self,
        frames: Any,
        indices: range | list[int],
        cfg: ModelConfig,
        cache: bool = True,
        augment: AugmentConfig | None = None,
        augment_seed: int = 0,
    ) -> None:
        self.frames = frames  # runtime reader
        self.indices = list(indices)  # reader indices of this split, in order
        self.cfg = cfg  # grid and column choice
        self.cache = cache  # keep preprocessed frames (up to CACHE_BYTES)
        self.augment = augment if augment is not None and augment.enabled else None  # transforms
        self.augment_seed = augment_seed  # mixed into every sample's transform seed
        self._cached: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._bytes = 0

    @property
    def augments(self) -> bool:
        """True when keys ``(epoch, i)`` give augmented frames (the sampler then yields them)."""
        return self.augment is not None

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def frame_ids(self) -> list[str]:
        """The reader's frame ids of this split."""
        return [self.frames.frame_ids[i] for i in self.indices]

    def __getitem__(self, key: int | tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """-> (radar (N, Cr) float32 [cfg.radar_columns], lidar (M, Cl) float32 [cfg.lidar_columns]).

        key: a position ``i`` in this split, or ``(epoch, i)`` for the augmented frame."""
        if isinstance(key, tuple):
            epoch, i = (int(k) for k in key)
            radar, lidar = self._frame(i)
            if self.augment is None:
                return radar, lidar
            from msdnet.training.data.augment import augment_pair

            rng = np.random.default_rng([self.augment_seed, epoch, i])
            return augment_pair(radar, lidar, self.cfg.grid, self.augment, rng)
        return self._frame(int(key))

    def _frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if i in self._cached:
            return self._cached[i]
        from msdnet.runtime.io.datasets.preprocess import preprocess_frame

        frame = preprocess_frame(self.frames[self.indices[i]], self.cfg.grid)
        pair = (
            np.ascontiguousarray(frame.radar.select(self.cfg.radar_columns).points, dtype=np.float32),
            np.ascontiguousarray(frame.lidar.select(self.cfg.lidar_columns).points, dtype=np.float32),
        )
        size = pair[0].nbytes + pair[1].nbytes
        if self.cache and self._bytes + size <= CACHE_BYTES:
            self._cached[i] = pair
            self._bytes += size
        return pair


def make_splits(
    dataset: str,
    root: str | Path,
    cfg: ModelConfig,
    val_fraction: float = 0.2,
    max_frames: int | None = None,
    radar_frames: int = 1,
    holdout: float = 0.0,
    augment: AugmentConfig | None = None,
    augment_seed: int = 0,
) -> tuple[PairDataset, PairDataset]:
    """(fit, select) PairDatasets over the first ``max_frames`` frames (all when None).

    The frames are first split into a training range and the validation split: a VoD-layout
    folder with published ``ImageSets/train.txt`` and ``val.txt`` (VoD itself, and what the
    simulator writes) by those files, exactly as ``msdnet-bench quality --split val`` reads it,
    unless ``max_frames`` asks for a smoke run; anything else by contiguous ranges
    (``split_indices``, ``val_fraction``).

    ``holdout > 0``: the last ``holdout`` share of the training range is held out (contiguous)
    as the *selection* slice for the best checkpoint and the decoding threshold, the rest is
    fitted, and the validation split is never returned (it is for reporting only).
    ``holdout == 0``: (training range, validation split): checkpoints selected on validation.
    ``augment`` applies to the fitted frames only.
    """
    from msdnet.runtime.io.datasets import VodDataset, open_dataset

    if dataset not in DATASETS:
        raise MsdnetError(None, f"unknown dataset {dataset!r} (choose from {', '.join(DATASETS)})")
    if not 0.0 <= holdout < 1.0:
        raise MsdnetError(None, f"holdout fraction must be in [0, 1), got {holdout}")
    frames = open_dataset(dataset, root, radar_frames=radar_frames)
    ids = list(frames.frame_ids) if max_frames is None else list(frames.frame_ids[:max_frames])
    published = isinstance(frames, VodDataset) and all(frames.split_file(n) for n in ("train", "val"))
    if published and max_frames is None:
        pos = {fid: i for i, fid in enumerate(ids)}
        parts = [VodDataset(root, split=n, radar_frames=radar_frames).frame_ids for n in ("train", "val")]
        train_idx, val_idx = ([pos[f] for f in part if f in pos] for part in parts)
        if not train_idx or not val_idx:
            raise MsdnetError(root, "ImageSets/train.txt or val.txt names none of the frames found")
    else:
        train_idx, val_idx = split_indices(ids, val_fraction)
    if holdout > 0.0:  # at least one frame each side (smoke runs have a handful)
        n_hold = max(1, int(round(holdout * len(train_idx))))
        if len(train_idx) - n_hold < 1:
            raise MsdnetError(root, f"{len(train_idx)} training frames leave none to fit after the holdout")
        train_idx, val_idx = train_idx[:-n_hold], train_idx[-n_hold:]
    fit = PairDataset(frames, train_idx, cfg, augment=augment, augment_seed=augment_seed)
    return fit, PairDataset(frames, val_idx, cfg)


def run_splits(
    dataset: str, root: str | Path, cfg: ModelConfig, recorded: dict[str, Any]
) -> tuple[PairDataset, PairDataset]:
    """:func:`make_splits` as a training run made them, from what its checkpoint recorded
    (``TrainState.dataset``: ``holdout``, ``val_fraction``): (fit, selection slice) when the run held
    frames out, else (training range, validation split)."""
    holdout = float(recorded.get("holdout", 0.0) or 0.0)
    val_fraction = float(recorded.get("val_fraction", 0.2))
    return make_splits(dataset, root, cfg, val_fraction=val_fraction, holdout=holdout)
