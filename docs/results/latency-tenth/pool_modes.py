"""How onnxruntime's threads were compared before ``--provider cpu-shared`` existed (tenth cycle).

One process: ``models/astyx-lite`` over the 53 selection-slice frames (two passes after three
warm-up frames), 2 threads, onnxruntime's threads as MODE asks:

- ``today``: every session its own pool, no spinning (``--provider cpu``);
- ``spin``: every session its own pool, spinning;
- ``spinstop``: the same, the spin stopped when each run ends (``session.force_spinning_stop``);
- ``global``: one process-wide pool of 2 threads for every session (what ``cpu-shared`` became).

    python docs/results/latency-tenth/pool_modes.py cpu|auto MODE
"""

from __future__ import annotations

import os
import runpy
import sys

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import onnxruntime as ort  # noqa: E402
import onnxruntime.capi._pybind_state as ort_c  # noqa: E402

import msdnet.runtime.engine.session as session  # noqa: E402
from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402

PLAIN = session.session_options


def options(mode: str, threads: int | None) -> ort.SessionOptions:
    """``session.session_options`` changed as MODE asks (module docstring)."""
    opts = PLAIN(None if mode == "global" else threads)
    if mode == "global":
        opts.use_per_session_threads = False
    if mode in ("spin", "spinstop"):
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1")
    if mode == "spinstop":
        opts.add_session_config_entry("session.force_spinning_stop", "1")
    return opts


def main(provider: str, mode: str) -> None:
    if mode == "global":
        ort_c.set_global_thread_pool_sizes(2, 1)
    session.session_options = lambda threads=None: options(mode, threads)
    pipe = Pipeline.from_dir("models/astyx-lite", provider, 2)
    frames = runpy.run_path("docs/results/latency-tenth/frames.py")  # not as __main__
    print(f"{provider} {mode:8s} ms: {frames['stage_medians'](pipe)}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
