"""``--provider openvino-bf16`` / ``auto-bf16``: OpenVINO computing in bfloat16. The names parse,
a CPU without bf16 is refused in one line, picks are cached apart from f32 ones, the looser guard
still rejects a wrong graph, and on a CPU with bf16 the outputs stay close to ``cpu``'s (what it
costs in CD is measured by ``msdnet-bench steps``, not here). The peer table keeps f32 peers apart."""

from __future__ import annotations

import numpy as np
import pytest
from export_helpers import make_artifact

from msdnet.benchmarks.latency.peers import _table
from msdnet.export.verify import _voxel_keys
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.providers import provider_cache, provider_measure, session

pytest.importorskip("openvino")
HAS_BF16 = session.openvino_has_bf16()


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_artifact(tmp_path_factory.mktemp("bf16"), "student")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(provider_cache, "_MEMO", {})


def _scan(pipe: Pipeline) -> np.ndarray:
    rng = np.random.default_rng(5)
    lo, hi = np.asarray(pipe.artifact.grid.point_range[:3]), np.asarray(pipe.artifact.grid.point_range[3:])
    pts = np.zeros((250, len(pipe.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((250, 3))
    return pts


def test_names_and_precision():
    assert session.base_provider(" Auto-BF16 ") == "auto" and session.precision_of("auto-bf16") == "bf16"
    assert session.base_provider("openvino-bf16") == "openvino" and session.precision_of("openvino") == "f32"
    assert session.base_provider("cpu") == "cpu" and session.precision_of("cpu") == "f32"
    assert {"openvino-bf16", "auto-bf16"} <= set(session.available_providers())
    assert session.device_of("auto-bf16") == "cpu"


def test_cpu_without_bf16_is_one_line(monkeypatch):
    monkeypatch.setattr(session, "openvino_has_bf16", lambda: False)
    for name in ("auto-bf16", "openvino-bf16"):
        with pytest.raises(MsdnetError, match="no bfloat16 on this CPU") as err:
            session.resolve_providers(name)
        assert "\n" not in str(err.value)
    assert session.resolve_providers("auto") == ["CPUExecutionProvider"]  # f32 unaffected


def test_bf16_picks_are_keyed_apart(folder):
    man = load_artifact(folder).manifest
    f32 = provider_cache.cache_key(man, onnx_spec.ENCODER.file, 1)
    assert provider_cache.cache_key(man, onnx_spec.ENCODER.file, 1, "f32") == f32  # old caches hold
    assert provider_cache.cache_key(man, onnx_spec.ENCODER.file, 1, "bf16") != f32


def test_bf16_guard_is_looser_but_rejects_a_wrong_graph():
    ref = [np.linspace(-1, 1, 600, dtype=np.float32).reshape(2, 300)]
    near = [ref[0] * (1 + 2e-2)]  # bf16 keeps ~3 digits: a few % on a value is expected
    assert "max rel" in provider_measure.disagreement(near, ref)
    assert provider_measure.disagreement(near, ref, precision="bf16") is None
    wrong = [ref[0][:, ::-1].copy()]
    assert provider_measure.disagreement(wrong, ref, precision="bf16") is not None


def test_peer_ratio_against_f32_peers_leaves_bf16_out():
    def s(ms):
        return [ms / 1e3] * 3

    specs = {"encoder": onnx_spec.ENCODER}
    seconds = {"encoder": {"onnxruntime": s(6.0), "openvino": s(10.0), "openvino_bf16": s(5.0)}}
    t = _table(specs, seconds, {"encoder": {}}, 1, 3)
    assert t["best_peer"] == "openvino_bf16" and t["engine_over_best_peer"] == pytest.approx(1.2)
    assert t["best_f32_peer"] == "openvino" and t["engine_over_best_f32_peer"] == pytest.approx(0.6)


@pytest.mark.skipif(not HAS_BF16, reason="OpenVINO has no bfloat16 on this CPU")
def test_openvino_bf16_runs_every_graph_it_loads_close_to_cpu(folder, cache):
    cpu = Pipeline.from_dir(folder, threads=1)
    ov = Pipeline.from_dir(folder, "openvino-bf16", threads=1)
    engines = {f: s.get_providers()[0] for f, s in ov.sessions.items()}
    assert engines[onnx_spec.RGFD_ADAPTER.file] == "CPUExecutionProvider"
    assert {f for f, e in engines.items() if e == "OpenVINO-bf16"} == set(ov.sessions) - {
        onnx_spec.RGFD_ADAPTER.file
    }
    scan = _scan(cpu)
    ref, got = cpu(scan, steps=4, seed=2), ov(scan, steps=4, seed=2)
    assert ref.points.tobytes() != got.points.tobytes()  # it really computed in bf16
    assert len(ref.points) > 100
    _close(ref.points, got.points, cpu)
    auto = Pipeline.from_dir(folder, "auto-bf16", threads=1)
    assert all(p.engine in ("onnxruntime", "openvino-bf16") for p in auto.auto.picks.values())
    _close(ref.points, auto(scan, steps=4, seed=2).points, cpu)


BF16_VOXELS_TOL = 0.03  # share of occupied voxels a random-weight model may gain or lose under bf16
BF16_SHIFT_M = 0.01  # largest move of a point whose voxel both keep (voxels are 0.2 m or more)


def _close(a: np.ndarray, b: np.ndarray, pipe: Pipeline) -> None:
    ka, kb = _voxel_keys(a, pipe.artifact.grid), _voxel_keys(b, pipe.artifact.grid)
    common, ia, ib = np.intersect1d(ka, kb, return_indices=True)
    only = len(ka) + len(kb) - 2 * len(common)
    shift = float(np.linalg.norm(a[ia] - b[ib], axis=1).max())
    print(f"bf16: {only} of {len(ka)} voxels differ, largest shift {shift:.4f} m")
    assert only <= BF16_VOXELS_TOL * len(ka) and shift <= BF16_SHIFT_M, (only, shift)
