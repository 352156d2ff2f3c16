"""How ``msdnet-node`` ends: SIGINT / SIGTERM in any state give exit 0, the stats line and the stats JSON.

Signals are blocked in the main thread before any other thread exists, so every thread started
later (onnxruntime's and OpenVINO's pools, OpenVINO's compiler, numba, Cyclone DDS, Foxglove)
inherits the block: no signal ever lands in a library's thread (no EINTR in a compile or a
session's teardown) and no Python handler runs in the middle of native code. One thread takes
them with ``sigwait``:

- before the node serves (the model loading, ``--provider auto`` measuring the engines, the warm-up,
  joining DDS), that thread ends the process itself: the stats so far (none) and the engines known
  so far are written, then ``os._exit`` with the loading left where it is;
- while serving, it sets ``stop``: the main thread finishes the scan in hand, leaves DDS and ends
  the same way; if it has not ended within ``GRACE_S``, the signal thread ends the process.

Every end goes through :meth:`Lifecycle.end`, once (a second caller waits for the first), and
leaves by ``os._exit``: the interpreter's teardown never runs beside the engines' native threads.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, NoReturn

from msdnet.runtime.errors import EXIT_BAD_INPUT, MsdnetError

SIGNALS = {signal.SIGINT, signal.SIGTERM}
GRACE_S = 2.0  # after a signal while serving: the main thread's time to finish its scan


class Lifecycle:
    """The node's states (loading, serving, ending) and the one way out of the process."""

    def __init__(self, report: Callable[[], None]) -> None:
        self.stop = threading.Event()  # set by a signal: serving ends
        self.signal: int | None = None  # the first signal taken
        self._report = report  # prints the stats line and writes the stats JSON
        self._state = threading.Lock()  # guards _serving against the signal thread
        self._serving = False
        self._ending = threading.Lock()  # held by the thread that ends the process

    def install(self) -> None:
        """Block SIGINT / SIGTERM in this (main) thread, and so in every thread started after it;
        start the thread that takes them. Call before anything starts a thread (importing numpy
        starts its BLAS pool). A thread that existed before still has them unblocked: for it, a
        handler passes the signal on the same way, through a thread of its own (the main thread,
        where Python runs handlers, may hold a lock the ending takes)."""
        signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
        for signum in SIGNALS:
            signal.signal(signum, self._handler)
        threading.Thread(target=self._take_signals, name="msdnet-node-signals", daemon=True).start()

    def _handler(self, signum: int, _frame: Any) -> None:
        threading.Thread(target=self._on_signal, args=(signum,), daemon=True).start()

    def _take_signals(self) -> None:
        while True:
            self._on_signal(signal.sigwait(SIGNALS))

    def _on_signal(self, signum: int) -> None:
        """A signal: end now before serving, else stop serving and end after GRACE_S at the latest."""
        with self._state:
            first = not self.stop.is_set()
            if first:
                self.signal = signum
            self.stop.set()
            serving = self._serving
        if not serving:
            self.end()  # loading: nothing to finish
        if first:
            timer = threading.Timer(GRACE_S, self.end)
            timer.daemon = True
            timer.start()

    def serving(self) -> bool:
        """Enter the serving state; False when a signal came first (the process is ending)."""
        with self._state:
            if self.stop.is_set():
                return False
            self._serving = True
            return True

    def serving_now(self) -> bool:
        """Whether the node has entered the serving state."""
        with self._state:
            return self._serving

    def end(self, code: int = 0, error: MsdnetError | None = None) -> NoReturn:
        """Write the last words (``error``'s line, else the report) and leave the process with
        ``code`` (2 when the report itself fails); only the first caller does, the others wait."""
        if not self._ending.acquire(blocking=False):
            threading.Event().wait()  # another thread is ending the process
        try:
            if error is not None:
                print(f"error: {error}", file=sys.stderr)
            else:
                self._report()
        except MsdnetError as err:
            print(f"error: {err}", file=sys.stderr)
            code = EXIT_BAD_INPUT
        except Exception as err:  # noqa: BLE001 - the process ends here whatever happened
            cause = " ".join(str(err).split())[:200]
            print(f"error: msdnet-node: {type(err).__name__}: {cause}", file=sys.stderr)
            code = 1
        finally:
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(code)
