"""``--provider cpu-shared``: every graph on one process-wide onnxruntime thread pool. The pool is
the process's, so each check runs in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from export_helpers import make_artifact

from msdnet.runtime.providers.session import SHARED, available_providers, device_of, resolve_providers

SCRIPT = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.errors import MsdnetError
    folder = sys.argv[1]
    threads = lambda: len(os.listdir("/proc/self/task"))
    ref = Pipeline.from_dir(folder, "cpu", threads=1)
    before = threads()
    shared = Pipeline.from_dir(folder, "cpu-shared", threads=3)
    again = Pipeline.from_dir(folder, "cpu-shared", threads=3)  # the same pool
    added = threads() - before
    rng = np.random.default_rng(5)
    lo = np.asarray(ref.artifact.grid.point_range[:3]); hi = np.asarray(ref.artifact.grid.point_range[3:])
    pts = np.zeros((250, len(ref.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((250, 3))
    a, b, c = ref(pts, seed=0), shared(pts, seed=0), again(pts, seed=0)
    same = a.points.shape == b.points.shape and np.allclose(a.points, b.points, atol=1e-4)
    try:
        Pipeline.from_dir(folder, "cpu-shared", threads=2)
        refused = "no"
    except MsdnetError as err:
        refused = str(err)
    print(added, len(ref.sessions), same, np.array_equal(b.points, c.points), refused)
    """
)


def test_cpu_shared_is_the_cpu_provider_on_one_pool(tmp_path):
    assert SHARED in available_providers() and resolve_providers(SHARED) == ["CPUExecutionProvider"]
    assert device_of(SHARED) == "cpu"
    folder = make_artifact(tmp_path, "student")
    run = subprocess.run([sys.executable, "-c", SCRIPT, str(folder)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    added, sessions, same, repeat, refused = run.stdout.split(maxsplit=4)
    # one pool of 3 threads (2 workers and the caller) for the sessions of both pipelines, where
    # per-session pools would add 2 workers for each of them
    assert int(added) == 2 and int(sessions) >= 4
    assert same == "True" and repeat == "True"  # the cpu provider's points, within the tolerance
    assert refused.strip() == "threads: cpu-shared: this process's shared pool has 3 threads, not 2"
