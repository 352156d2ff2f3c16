"""Graph sessions: onnxruntime execution providers by short name, intra-op threads, no spinning;
and ``openvino``: OpenVINO runs every graph it can load, onnxruntime's CPU provider the rest;
``auto``: per graph, whichever of the two measured faster here (``runtime.providers.provider_auto``);
``openvino-bf16`` and ``auto-bf16``: the same with OpenVINO computing in bfloat16 (``BF16`` below).

onnxruntime and numba share the CPU cores; a spinning intra-op pool would starve the numba
voxelizer between graph calls, so spinning is off in every session's own pool
(``session.intra_op.allow_spinning``). ``cpu-shared`` instead gives every graph of the process
one onnxruntime thread pool (``set_global_thread_pool_sizes``), whose workers spin between the
graphs of a frame: faster a frame in 7 of 8 rounds on the 2-core test machine (1-12 %), where
per-session pools that spin were 2.4x slower (docs/results/latency-tenth). The pool is the
process's: its thread count is fixed by the first ``cpu-shared`` session, and its spinning slows
OpenVINO or torch running in the same process, so it is opt-in and stays off ``auto``.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any

import onnxruntime as ort
import onnxruntime.capi._pybind_state as ort_c  # set_global_thread_pool_sizes: no public alias

from msdnet.runtime.errors import MsdnetError

# short name -> onnxruntime execution provider
PROVIDERS: dict[str, str] = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
}
SHARED = "cpu-shared"  # onnxruntime's CPU provider, one process-wide thread pool for every graph
_shared_threads: list[int] = []  # the process-wide pool's intra-op threads, once created
OPENVINO = (
    "openvino"  # not an onnxruntime provider: runtime.providers.openvino_session (the [openvino] extra)
)
# per graph, the faster of onnxruntime's CPU provider and OpenVINO (runtime.providers.provider_auto)
AUTO = "auto"
# Graphs ``openvino`` runs with OpenVINO (f32, same threads): the heads, where it was faster in every
# msdnet-bench latency run (docs/results/latency-*: sim-lite 2.5-2.75x, paper-width 1.5x, paper 1.0x).
# The encoder (onnxruntime as fast or faster in 3 of 4 runs) and the step graph (50 calls a frame:
# OpenVINO's per-call cost made the loop 1.06-2x slower in every preset) stay on onnxruntime, so
# does rgfd_adapter.onnx (DeformConv: OpenVINO cannot load it).
OPENVINO_GRAPHS = ("recon_head.onnx", "recon_head_sparse.onnx")
# bfloat16 variants: OpenVINO compiles with INFERENCE_PRECISION_HINT bf16 (f32 inputs and outputs,
# bf16 matmuls and convolutions; about 3 significant digits). They need a CPU whose OpenVINO
# capabilities list BF16 (AVX512-BF16 or AMX). ``openvino-bf16`` runs every graph OpenVINO can load
# (in bf16 the encoder and step graph gain too); ``auto-bf16`` picks per graph between onnxruntime
# (f32) and OpenVINO bf16. Opt-in: outputs are not within the f32 export tolerances, and
# ``msdnet-bench steps --provider auto-bf16`` measures what it costs in CD and F-score.
BF16 = "-bf16"
OPENVINO_BF16, AUTO_BF16 = OPENVINO + BF16, AUTO + BF16


def base_provider(provider: str) -> str:
    """The provider without its precision: ``auto-bf16`` -> ``auto``, ``cpu`` -> ``cpu``."""
    name = provider.strip().lower()
    return name[: -len(BF16)] if name in (OPENVINO_BF16, AUTO_BF16) else name


def precision_of(provider: str) -> str:
    """``bf16`` for the bfloat16 providers, else ``f32``."""
    return "bf16" if provider.strip().lower() in (OPENVINO_BF16, AUTO_BF16) else "f32"


def openvino_has_bf16() -> bool:
    """Whether OpenVINO's CPU plugin lists BF16 among its optimization capabilities here."""
    import openvino as ov

    return "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


def available_providers() -> list[str]:
    """Short names of the providers this onnxruntime build offers (``cpu`` and ``auto`` always)."""
    have = set(ort.get_available_providers())
    names = [name for name, full in PROVIDERS.items() if full in have]
    ov = [OPENVINO, OPENVINO_BF16] if importlib.util.find_spec("openvino") is not None else []
    return names + [SHARED] + ov + [AUTO] + ([AUTO_BF16] if ov else [])


def resolve_providers(provider: str) -> list[str]:
    """Short provider name -> onnxruntime provider list, with CPU as the fallback for ops.

    Raises :class:`MsdnetError` naming the available providers when ``provider`` is unknown
    or not built into the installed onnxruntime.
    """
    name = provider.strip().lower()
    have = available_providers()
    if name in (OPENVINO, OPENVINO_BF16, AUTO_BF16) and name not in have:
        raise MsdnetError("provider", f"{name} needs the OpenVINO runtime: pip install 'msdnet[openvino]'")
    if precision_of(name) == "bf16" and not openvino_has_bf16():
        raise MsdnetError("provider", f"{name}: OpenVINO has no bfloat16 on this CPU (no BF16 capability)")
    # the graphs OpenVINO cannot load (or loses) run on the CPU provider
    if name in (SHARED, OPENVINO, AUTO, OPENVINO_BF16, AUTO_BF16):
        return [PROVIDERS["cpu"]]
    if name not in PROVIDERS or name not in have:
        raise MsdnetError(
            "provider",
            f"{provider!r} is not available in onnxruntime {ort.__version__} (available: {', '.join(have)})",
        )
    chain = [PROVIDERS[name]]
    if name == "tensorrt" and "cuda" in have:
        chain.append(PROVIDERS["cuda"])
    if name != "cpu":
        chain.append(PROVIDERS["cpu"])
    return chain


def device_of(provider: str) -> str:
    """OrtValue device type for buffers that live next to ``provider``'s kernels."""
    return "cpu" if base_provider(provider) in ("cpu", SHARED, OPENVINO, AUTO) else "cuda"


def session_options(threads: int | None = None) -> ort.SessionOptions:
    """Options shared by every graph: ``threads`` intra-op threads (None: ORT default), no spin."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.inter_op_num_threads = 1
    if threads is not None:
        if threads < 1:
            raise MsdnetError("threads", f"must be >= 1, got {threads}")
        opts.intra_op_num_threads = int(threads)
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    opts.log_severity_level = 3  # errors only
    return opts


def shared_session_options(threads: int | None = None) -> ort.SessionOptions:
    """:func:`session_options` on the process-wide pool of ``threads`` intra-op threads (None: one
    per core), created by the first call; a later call asking for another count is refused."""
    n = int(threads) if threads is not None else os.cpu_count() or 1
    if n < 1:
        raise MsdnetError("threads", f"must be >= 1, got {n}")
    if not _shared_threads:
        ort_c.set_global_thread_pool_sizes(n, 1)
        _shared_threads.append(n)
    elif _shared_threads[0] != n:
        raise MsdnetError(
            "threads", f"{SHARED}: this process's shared pool has {_shared_threads[0]} threads, not {n}"
        )
    opts = session_options(None)
    opts.use_per_session_threads = False
    return opts


def create_session(model: bytes, name: str | Path, provider: str = "cpu", threads: int | None = None) -> Any:
    """An inference session from serialized ONNX ``model`` bytes (already hash-checked).

    Sessions are built from bytes so the file checked is exactly the file run. ``name`` is only
    used in error messages. ``provider`` ``openvino``: an :class:`OpenVinoSession` (same API
    subset) for the ``OPENVINO_GRAPHS`` (``name`` is the file name) when OpenVINO can load them,
    else onnxruntime on the CPU; ``openvino-bf16``: the same for every graph, in bfloat16;
    ``get_providers()`` says which.
    """
    providers = resolve_providers(provider)
    name_l = provider.strip().lower()
    if (name_l == OPENVINO and Path(str(name)).name in OPENVINO_GRAPHS) or name_l == OPENVINO_BF16:
        from msdnet.runtime.providers.openvino_session import OpenVinoSession

        if threads is not None and threads < 1:
            raise MsdnetError("threads", f"must be >= 1, got {threads}")
        try:
            return OpenVinoSession(model, threads, precision_of(name_l))
        except Exception:  # noqa: BLE001 - any conversion failure: this graph stays on onnxruntime
            pass
    opts = shared_session_options(threads) if name_l == SHARED else session_options(threads)
    try:
        return ort.InferenceSession(model, sess_options=opts, providers=providers)
    except Exception as err:  # onnxruntime raises its own exception types
        cause = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise MsdnetError(name, f"onnxruntime cannot load this graph: {cause}") from err
