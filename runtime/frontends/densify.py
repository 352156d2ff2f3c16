"""The options of a densify run and the one Pipeline call every front-end makes with them.

Each front-end builds one :class:`DensifyOptions` from its command line (``msdnet-infer`` in every
mode: files, ``--workers`` processes, Ray actors, ``--dataset``, bags; ``msdnet-node``) and
passes it to :func:`densify`, so the options reach the pipeline the same way everywhere and the
same scan, seed and options give the same bytes in every mode. Frozen and made of plain values,
it pickles to ``--workers`` processes and Ray actors as it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class DensifyOptions:
    """How every scan of one run is densified and written."""

    steps: int | None = None  # DDIM steps (--steps); None: the manifest's T_m
    threshold: float | None = None  # occupancy threshold (--threshold); None: the manifest's
    seed: int = 0  # noise seed (--seed): same seed, same output in every mode
    keep_radar: bool = False  # append the input radar points inside the grid, confidence 1
    fmt: str = "npy"  # output file format (--format): bin, npy, pcd or ply (files, --dataset)
    png: bool = False  # also write a BEV picture next to each output (--png; files, --dataset)
    bin_columns: tuple[str, ...] | None = None  # .bin columns (file mode); None: the path/size rule


def densify(pipe: Any, cloud: Any, options: DensifyOptions) -> Any:
    """``pipe(cloud, ...)`` with the run's ``steps``, ``threshold``, ``seed`` and ``keep_radar``;
    -> the pipeline's ``Result``."""
    return pipe(
        cloud,
        steps=options.steps,
        threshold=options.threshold,
        seed=options.seed,
        keep_radar=options.keep_radar,
    )
