"""``--provider auto``: per graph the faster of onnxruntime and OpenVINO, measured once and cached;
outputs within the export tolerances of ``--provider cpu``; the adapter stays on onnxruntime."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest
from click.testing import CliRunner
from export_helpers import make_artifact

from msdnet.export.verify import E2E_DIFF_TOL, GRAPH_COS_TOL, GRAPH_REL_TOL, compare_points
from msdnet.runtime.engine import provider_auto
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.io.files import write_cloud
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import load_artifact

pytest.importorskip("openvino")
ON_OV = (onnx_spec.ENCODER.file, onnx_spec.DENOISER_STEP.file, onnx_spec.RECON_HEAD.file)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_artifact(tmp_path_factory.mktemp("auto"), "student")


@pytest.fixture
def cache(auto_cache):
    return auto_cache  # conftest's: a fresh cache under XDG_CACHE_HOME, no picks kept in memory


def _scan(pipe: Pipeline) -> np.ndarray:
    rng = np.random.default_rng(5)
    lo, hi = np.asarray(pipe.artifact.grid.point_range[:3]), np.asarray(pipe.artifact.grid.point_range[3:])
    pts = np.zeros((250, len(pipe.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((250, 3))
    return pts


def _engines(pipe: Pipeline) -> dict[str, str]:
    return {f: s.get_providers()[0] for f, s in pipe.sessions.items()}


def _force(cache, folder, engine: str, threads: int = 1) -> None:
    """Write cache entries that put every graph OpenVINO loads on ``engine``."""
    art = load_artifact(folder)
    entries = {
        provider_auto.cache_key(art.manifest, f, threads): {"engine": engine, "ms": {}, "reason": "forced"}
        for f in art.graphs
        if f != onnx_spec.RGFD_ADAPTER.file
    }
    assert provider_auto.write_cache(cache, entries) == "written"


def test_tolerances_are_the_exports():
    assert (provider_auto.AGREE_REL_TOL, provider_auto.AGREE_COS_TOL) == (GRAPH_REL_TOL, GRAPH_COS_TOL)
    assert provider_auto.AGREE_E2E_TOL == E2E_DIFF_TOL


def test_measured_once_then_cached(folder, cache, monkeypatch):
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    picks = pipe.auto.picks
    assert list(picks) == list(pipe.sessions) and pipe.auto.cache_note == "written"
    adapter = picks[onnx_spec.RGFD_ADAPTER.file]
    assert adapter.engine == "onnxruntime" and "DeformConv" in adapter.reason and not adapter.ms
    for f in ON_OV:
        p = picks[f]
        assert set(p.ms) == {"onnxruntime", "openvino"} and min(p.ms.values()) > 0 and not p.cached
        assert p.ratio is not None and p.ratio > 0  # paired by scan, so not the ratio of the medians
        faster = p.ratio <= 1 - provider_auto.MARGIN
        assert p.engine == ("openvino" if faster else "onnxruntime"), p.line()
        assert _engines(pipe)[f] == ("OpenVINO" if faster else "CPUExecutionProvider")
    doc = json.loads(cache.read_text())
    assert doc["version"] == provider_auto.CACHE_VERSION and len(doc["entries"]) == len(picks)
    assert [p.name for p in cache.parent.iterdir()] == ["providers.json"]  # no temporary file left
    key = next(iter(doc["entries"]))
    assert ort.__version__ in key and provider_auto.openvino_version() in key and "threads 1" in key

    def no_timing(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(provider_auto, "time_engines", no_timing)
    monkeypatch.setattr(provider_auto, "_MEMO", {})  # a new process: only the file is left
    again = Pipeline.from_dir(folder, "auto", threads=1)
    assert {f: p.engine for f, p in again.auto.picks.items()} == {f: p.engine for f, p in picks.items()}
    assert all(p.cached for p in again.auto.picks.values()) and again.auto.cache_note == "read"
    assert _engines(again) == _engines(pipe)
    assert "DeformConv" in again.auto.picks[onnx_spec.RGFD_ADAPTER.file].line()


def test_engines_are_timed_on_a_stream_of_scans(folder, cache, monkeypatch):
    """Each timed call gets a scan neither engine saw before (a sensor's frames differ, and
    OpenVINO prepares its kernels per input shape); the pipeline's own sessions have seen none."""
    timed, own, runs = [], set(), []
    real_times, real_inputs = provider_auto.time_engines, provider_auto.stream_inputs

    def spy_times(sessions, feeds, refs):
        timed.append(feeds)
        return real_times(sessions, feeds, refs)

    def spy_inputs(pipe, threads):
        own.update(id(s) for s in pipe.sessions.values())  # the pipeline's onnxruntime sessions
        return real_inputs(pipe, threads)

    def counting(name):
        real = getattr(ort.InferenceSession, name)

        def run(self, *a, **k):
            runs.append(id(self))
            return real(self, *a, **k)

        return run

    monkeypatch.setattr(provider_auto, "time_engines", spy_times)
    monkeypatch.setattr(provider_auto, "stream_inputs", spy_inputs)
    for name in ("run", "run_with_iobinding"):
        monkeypatch.setattr(ort.InferenceSession, name, counting(name))
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    on_ov = [f for f in pipe.sessions if f != onnx_spec.RGFD_ADAPTER.file]
    assert len(timed) == len(on_ov)
    steps = pipe.coefficients(provider_auto._loop_steps(pipe)).shape[0]
    for scans in timed:
        assert len(scans) == provider_auto.STREAM_SCANS
        first = [next(iter(calls[0].values())) for calls in scans]  # each scan's first input
        assert len({a.tobytes() for a in first}) == len(scans)
        assert {len(calls) for calls in scans} <= {1, steps}  # the step graph: T_m calls a scan
    assert any(len(scans[0]) == steps > 1 for scans in timed)
    enc = next(scans for scans in timed if onnx_spec.ENCODER.inputs[0] in scans[0][0])
    shapes = {tuple(a.shape for a in calls[0].values()) for calls in enc}
    assert len(shapes) >= provider_auto.STREAM_SCANS // 2  # voxel counts differ from scan to scan
    # the pipeline's sessions ran only in the timing: warm-up on the first scan, then every other
    # scan once
    per_scan = sum(len(scans[0]) for scans in timed)
    scans_run = provider_auto.WARMUP_CALLS + provider_auto.STREAM_SCANS - 1
    assert 0 < sum(r in own for r in runs) <= per_scan * scans_run


def test_a_long_loop_is_cut_for_the_timing(folder, monkeypatch):
    pipe = Pipeline.from_dir(folder, threads=1)
    calls = pipe.coefficients().shape[0]
    assert calls >= 2
    monkeypatch.setattr(provider_auto, "STREAM_LOOP_STEPS", calls)
    assert provider_auto._loop_steps(pipe) is None  # short enough: the manifest's own
    monkeypatch.setattr(provider_auto, "STREAM_LOOP_STEPS", calls - 1)
    assert provider_auto._loop_steps(pipe) == calls - 1
    inputs = provider_auto.frame_calls(pipe, steps=provider_auto._loop_steps(pipe))
    assert len(inputs[onnx_spec.DENOISER_STEP.file]) == calls - 1


def test_seeded_scans_are_radar_like(folder):
    """Clumps inside the box and the field of view: a real frame's points lie on a few objects."""
    pipe = Pipeline.from_dir(folder, threads=1)
    grid = pipe.artifact.grid
    lo, hi = np.asarray(grid.point_range[:3], np.float32), np.asarray(grid.point_range[3:], np.float32)
    a, b = (provider_auto.seeded_scan(pipe, np.random.default_rng(k), 400) for k in (0, 1))
    assert a.shape == (400, len(pipe.columns)) and a.dtype == np.float32 and not np.array_equal(a, b)
    assert np.all((a[:, :3] >= lo) & (a[:, :3] < hi)) and not a[:, 3:].any()
    angle = np.degrees(np.abs(np.arctan2(a[:, 1], a[:, 0])))
    assert np.mean(angle <= grid.fov_deg + 5) > 0.9
    spread = np.linalg.norm(a[:, None, :3] - a[None, :, :3], axis=-1)
    np.fill_diagonal(spread, np.inf)
    uniform = lo + (hi - lo) * np.random.default_rng(2).random((400, 3))
    far = np.linalg.norm(uniform[:, None] - uniform[None], axis=-1)
    np.fill_diagonal(far, np.inf)
    assert np.median(spread.min(1)) < 0.5 * np.median(far.min(1))  # clumped


def test_another_library_version_or_thread_count_measures_again(folder, cache, monkeypatch):
    art = load_artifact(folder)
    key = provider_auto.cache_key(art.manifest, onnx_spec.ENCODER.file, 1)
    assert key != provider_auto.cache_key(art.manifest, onnx_spec.ENCODER.file, 2)
    assert key != provider_auto.cache_key(art.manifest, onnx_spec.DENOISER_STEP.file, 1)
    _force(cache, folder, "onnxruntime")
    forced = [
        p for f, p in Pipeline(art, "auto", threads=1).auto.picks.items() if f != onnx_spec.RGFD_ADAPTER.file
    ]
    assert all(p.cached and p.reason == "forced" for p in forced)
    monkeypatch.setattr(ort, "__version__", "0.0.0")
    monkeypatch.setattr(provider_auto, "_MEMO", {})
    assert provider_auto.cache_key(art.manifest, onnx_spec.ENCODER.file, 1) != key
    fresh = Pipeline(art, "auto", threads=1).auto.picks
    assert not any(p.cached for p in fresh.values()) and fresh[onnx_spec.ENCODER.file].reason != "forced"


def test_openvino_picks_stay_within_the_export_tolerances(folder, cache):
    _force(cache, folder, "openvino")
    cpu, auto = Pipeline.from_dir(folder, threads=1), Pipeline.from_dir(folder, "auto", threads=1)
    engines = _engines(auto)
    assert {f for f, e in engines.items() if e == "OpenVINO"} == set(auto.artifact.graphs) - {
        onnx_spec.RGFD_ADAPTER.file
    }
    assert engines[onnx_spec.RGFD_ADAPTER.file] == "CPUExecutionProvider"
    scan = _scan(cpu)
    for gate in (None, 0.3):  # the dense head, then the coarse-to-fine head
        cpu.gate = auto.gate = gate
        ref, got = cpu(scan, steps=5, seed=2), auto(scan, steps=5, seed=2)
        differ, shift = compare_points(ref.points, got.points, cpu.artifact.grid)
        assert len(ref.points) > 100 and differ <= E2E_DIFF_TOL * len(ref.points), (differ, shift)
        assert ref.stats["head_voxels"] == got.stats["head_voxels"]


def test_onnxruntime_picks_give_cpus_bytes(folder, cache):
    _force(cache, folder, "onnxruntime")
    cpu, auto = Pipeline.from_dir(folder, threads=1), Pipeline.from_dir(folder, "auto", threads=1)
    assert set(_engines(auto).values()) == {"CPUExecutionProvider"}
    scan = _scan(cpu)
    a, b = cpu(scan, steps=4, seed=1), auto(scan, steps=4, seed=1)
    assert a.points.tobytes() == b.points.tobytes() and a.confidence.tobytes() == b.confidence.tobytes()


def test_outputs_that_disagree_keep_onnxruntime():
    ref = [np.ones((2, 3), np.float32)]
    assert provider_auto.disagreement([ref[0] * (1 + 1e-6)], ref) is None
    assert "max rel" in provider_auto.disagreement([ref[0] * 1.01], ref)
    assert "shape" in provider_auto.disagreement([np.ones((3, 3), np.float32)], ref)
    # the coarse-to-fine head: a voxel on the gate may be gated by one engine only (<= 0.2 %)
    names = ["occupancy", "voxels"]
    vox = np.arange(1000, dtype=np.int64)
    occ = np.linspace(0, 1, 1000, dtype=np.float32)[:, None].repeat(8, 1)
    assert provider_auto.disagreement([occ[1:], vox[1:]], [occ, vox], names) is None
    assert "gated voxels" in provider_auto.disagreement([occ[3:], vox[3:]], [occ, vox], names)
    bad = occ[1:].copy()
    bad[5] += 0.1
    assert "max rel" in provider_auto.disagreement([bad, vox[1:]], [occ, vox], names)


def test_cache_location_and_bad_files(tmp_path, monkeypatch, folder):
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/dir")  # not absolute: ignored, as the XDG spec says
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert provider_auto.cache_path() == tmp_path / "home" / ".cache" / "msdnet" / "providers.json"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    path = provider_auto.cache_path()
    assert path == tmp_path / "x" / "msdnet" / "providers.json"
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    assert provider_auto.read_cache(path) == {}
    assert provider_auto.write_cache(path, {"k": {"engine": "onnxruntime"}}) == "written"
    assert provider_auto.read_cache(path) == {"k": {"engine": "onnxruntime"}}
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))  # a file where a folder must be
    monkeypatch.setattr(provider_auto, "_MEMO", {})
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    assert pipe.auto.cache_note.startswith("not written: ") and "\n" not in pipe.auto.cache_note
    assert len(pipe(_scan(pipe), steps=2).points) > 0


def test_results_name_the_cache_without_machine_folders(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    shown = provider_auto.cache_shown
    assert shown(tmp_path / "xdg" / "msdnet" / "p.json") == "$XDG_CACHE_HOME/msdnet/p.json"
    assert shown(tmp_path / "home" / ".cache" / "p.json") == "~/.cache/p.json"
    assert shown(tmp_path / "elsewhere" / "p.json") == "p.json"


def test_without_openvino_every_graph_stays(folder, cache, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "openvino" else real(n, *a))
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    assert {p.engine for p in pipe.auto.picks.values()} == {"onnxruntime"}
    assert all("not installed" in p.reason for p in pipe.auto.picks.values()) and not cache.exists()


def test_infer_verbose_prints_the_picks(folder, cache, tmp_path):
    from msdnet.runtime.frontends.infer.cli import main

    _force(cache, folder, "openvino")
    src = tmp_path / "in"
    src.mkdir()
    cpu = Pipeline.from_dir(folder, threads=1)
    write_cloud(src / "scan.pcd", PointCloud(_scan(cpu), cpu.columns))
    args = [str(src), "--model", str(folder), "--out", str(tmp_path / "out"), "--steps", "2"]
    res = CliRunner().invoke(main, [*args, "--provider", "auto", "--threads", "1", "-v"])
    assert res.exit_code == 0, res.output
    assert "provider auto: encoder.onnx: openvino (forced; cached)" in res.output
    assert "provider auto: rgfd_adapter.onnx: onnxruntime" in res.output and "DeformConv" in res.output
    assert (tmp_path / "out" / "scan.npy").is_file()


def test_latency_results_record_the_picks(folder, cache):
    from msdnet.benchmarks.latency.peer_report import auto_section

    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    text = "\n".join(auto_section({"provider_auto": {"msdnet": pipe.auto.to_json()}}))
    assert "## --provider auto" in text and text.count("| msdnet |") == len(pipe.sessions)
    assert "DeformConv" in text and "$XDG_CACHE_HOME/msdnet/providers.json" in text
    assert str(cache.parent) not in text  # results name no folder of the machine
    enc = pipe.auto.picks[onnx_spec.ENCODER.file]
    assert f"| msdnet | encoder.onnx | **{enc.engine}** | {enc.ms['onnxruntime']:.3f} |" in text
    assert auto_section({"provider_auto": {}}) == []


def test_only_cpu_pins_the_adapter_to_one_thread(folder, cache):
    """``cpu`` keeps the DeformConv graph on one thread (same bytes at any ``threads``); ``auto``
    promises no bytes and gives it the threads asked for (at paper width 157 -> 99 ms at 2)."""
    rgfd = onnx_spec.RGFD_ADAPTER.file
    assert Pipeline.from_dir(folder, threads=2).graph_threads[rgfd] == 1
    auto = Pipeline.from_dir(folder, "auto", threads=2)
    assert auto.graph_threads[rgfd] == 2 and auto.graph_threads[onnx_spec.ENCODER.file] == 2
