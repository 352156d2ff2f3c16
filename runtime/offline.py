"""Nothing leaves the machine: the engines msdnet loads are told not to send usage data.

Applied once, by ``msdnet.runtime``'s ``__init__``, before any engine is imported, whatever the
user's environment and home folder:

- onnxruntime (>= 1.29 sends telemetry on Linux and writes a device id under
  ``~/.cache/Microsoft``) reads ``ORT_DISABLE_TELEMETRY`` / ``ORT_TELEMETRY_DISABLED`` when it
  loads: both are set to ``1`` for the process and the processes it starts.
- OpenVINO imports its ``openvino_telemetry`` package on ``import openvino``; on a first run that
  package writes a client id under ``~/intel`` and starts a sender that looks up Google
  Analytics' host. Its documented opt-out (``opt_in_out --opt_out``) writes a consent file under
  ``~/intel`` itself, so instead the package is marked absent in ``sys.modules``: OpenVINO then
  falls back to its own no-op telemetry stub (``openvino.tools.ovc.telemetry_stub``), which sends
  nothing and writes nothing. Inference does not use the package.

No I/O, no third-party import: importing this module is cheap.
"""

from __future__ import annotations

import os
import sys

# Environment variables onnxruntime reads at load time; each forced to the value that turns it off.
ENV_OFF = {"ORT_DISABLE_TELEMETRY": "1", "ORT_TELEMETRY_DISABLED": "1"}
# Python packages that only send usage data; marked absent so that importing them fails.
BLOCKED_MODULES = ("openvino_telemetry",)


def telemetry_off() -> list[str]:
    """Turn every engine's telemetry off for this process (idempotent).

    Returns the names of blocked packages that were already imported before this call (their
    sender may already run; empty in every msdnet entry point, which call this first).
    """
    os.environ.update(ENV_OFF)
    late = []
    for name in BLOCKED_MODULES:
        if sys.modules.get(name, None) is not None:
            late.append(name)
        else:
            sys.modules[name] = None  # type: ignore[assignment]  # `import name` raises ImportError
    return late
