"""``--provider openvino``: OpenVINO runs the heads, onnxruntime the rest; same results
as onnxruntime under the export tolerances (``export.verify``). Needs the [openvino] extra, which
.ci/run installs."""

from __future__ import annotations

import numpy as np
import pytest
from export_helpers import make_artifact

from msdnet.export.verify import E2E_DIFF_TOL, GraphCheck, compare_points
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers.openvino_session import OpenVinoSession
from msdnet.runtime.providers.session import OPENVINO_GRAPHS, available_providers, resolve_providers

pytest.importorskip("openvino")


@pytest.fixture(scope="module")
def pipes(tmp_path_factory) -> tuple[Pipeline, Pipeline]:
    folder = make_artifact(tmp_path_factory.mktemp("ov"), "student")
    return Pipeline.from_dir(folder, threads=1), Pipeline.from_dir(folder, "openvino", threads=1)


def _scan(pipe: Pipeline) -> np.ndarray:
    rng = np.random.default_rng(5)
    lo, hi = np.asarray(pipe.artifact.grid.point_range[:3]), np.asarray(pipe.artifact.grid.point_range[3:])
    pts = np.zeros((250, len(pipe.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((250, 3))
    return pts


def test_openvino_runs_the_graphs_where_it_wins(pipes):
    _, ov = pipes
    assert "openvino" in available_providers() and resolve_providers("openvino") == ["CPUExecutionProvider"]
    engines = {f: s.get_providers()[0] for f, s in ov.sessions.items()}
    assert {f for f, e in engines.items() if e == "OpenVINO"} == set(OPENVINO_GRAPHS)
    on_ort = {onnx_spec.ENCODER.file, onnx_spec.DENOISER_STEP.file, onnx_spec.RGFD_ADAPTER.file}
    assert {engines[f] for f in on_ort} == {"CPUExecutionProvider"}
    # OpenVINO could run the step graph too (the loop only ran slower), not the adapter (DeformConv)
    graphs = ov.artifact.graphs
    assert OpenVinoSession(graphs[onnx_spec.DENOISER_STEP.file], 1).get_providers() == ["OpenVINO"]
    with pytest.raises(Exception, match="DeformConv"):
        OpenVinoSession(graphs[onnx_spec.RGFD_ADAPTER.file], 1)


def test_every_graph_within_the_export_tolerances(pipes):
    cpu, ov = pipes
    scan = _scan(cpu)
    for gate in (None, 0.3):  # the dense head, then the coarse-to-fine head
        cpu.gate = ov.gate = gate
        try:
            ref, got = cpu(scan, steps=5, seed=2), ov(scan, steps=5, seed=2)
        finally:
            cpu.gate = ov.gate = None
        differ, shift = compare_points(ref.points, got.points, cpu.artifact.grid)
        assert len(ref.points) > 100 and differ <= E2E_DIFF_TOL * len(ref.points), (differ, shift)
        assert ref.stats["head_voxels"] == got.stats["head_voxels"]
    rng = np.random.default_rng(0)
    x = rng.standard_normal(cpu.bev_shape).astype(np.float32)
    row = cpu.coefficients()[0]
    feeds = {
        onnx_spec.DENOISER_STEP.file: {"x_t": x, "t": row[0:1], "abar_t": row[1:2], "abar_prev": row[2:3]},
        onnx_spec.RECON_HEAD.file: {"features": x},
        onnx_spec.RECON_HEAD_SPARSE.file: {"features": x, "gate": np.full(1, 0.3, np.float32)},
    }
    for file, feed in feeds.items():
        check = GraphCheck(file)
        sess = OpenVinoSession(cpu.artifact.graphs[file], 1)  # every graph OpenVINO loads, the step too
        for a, b in zip(sess.run(None, feed), cpu.sessions[file].run(None, feed), strict=True):
            check.add(a.astype(np.float32), b.astype(np.float32))
        assert check.ok, (file, check.max_rel, check.cosine)


def test_openvino_missing_is_one_line(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "openvino" else real(n, *a))
    with pytest.raises(MsdnetError, match=r"pip install 'msdnet\[openvino\]'"):
        resolve_providers("openvino")
