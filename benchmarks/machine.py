"""The machine a benchmark ran on, and its measured single-precision matmul rate (the yardstick)."""

from __future__ import annotations

import os
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort


@dataclass(frozen=True)
class MachineInfo:
    """What every results.json records about where it was measured."""

    cpu: str  # processor model name
    logical_cores: int  # os.cpu_count()
    python: str  # interpreter version
    numpy: str  # numpy version
    onnxruntime: str  # onnxruntime version
    providers: tuple[str, ...]  # onnxruntime execution providers available
    system: str  # OS and kernel
    sgemm_gflops: float  # measured numpy float32 matmul rate, GFLOP/s

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def shown_path(path: Path | str) -> str:
    """``path`` as a results document records it: relative to the working folder (or to the
    installed package's root, for bundled models) so that no document names a folder of the
    machine it ran on; outside both, only its last two parts."""
    p = Path(path).absolute()
    package_root = Path(__file__).resolve().parents[1]  # the msdnet package (models/ is under it)
    for root in (Path.cwd(), package_root):
        try:
            return p.relative_to(root).as_posix()
        except ValueError:
            continue
    return Path(*p.parts[-2:]).as_posix()


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (falls back to platform.processor())."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def measure_sgemm_gflops(n: int = 1024, repeats: int = 5) -> float:
    """Best-of-``repeats`` float32 (n x n) @ (n x n) rate in GFLOP/s (2 n^3 flops per product)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b  # warm-up
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best / 1e9


def machine_info(sgemm: bool = True) -> MachineInfo:
    """Describe this machine; ``sgemm=False`` skips the (about one second) matmul measurement."""
    return MachineInfo(
        cpu=cpu_model(),
        logical_cores=os.cpu_count() or 0,
        python=platform.python_version(),
        numpy=np.__version__,
        onnxruntime=ort.__version__,
        providers=tuple(ort.get_available_providers()),
        system=f"{platform.system()} {platform.release()}",
        sgemm_gflops=measure_sgemm_gflops() if sgemm else float("nan"),
    )
