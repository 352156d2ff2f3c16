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
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.io.files import write_cloud
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.providers import provider_cache, provider_measure

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
        provider_cache.cache_key(art.manifest, f, threads): {"engine": engine, "ms": {}, "reason": "forced"}
        for f in art.graphs
        if f != onnx_spec.RGFD_ADAPTER.file
    }
    assert provider_cache.write_cache(cache, entries) == "written"


def test_tolerances_are_the_exports():
    assert (provider_measure.AGREE_REL_TOL, provider_measure.AGREE_COS_TOL) == (GRAPH_REL_TOL, GRAPH_COS_TOL)
    assert provider_measure.AGREE_E2E_TOL == E2E_DIFF_TOL


def test_measured_once_then_cached(folder, cache, monkeypatch):
    said: list[str] = []
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=said.append)
    picks = pipe.auto.picks
    assert said == [pipe.auto.summary()] and "measured" in said[0] and "\n" not in said[0]
    assert pipe.auto.scans == provider_measure.STREAM_SCANS - 1 and 0 < pipe.auto.measured_s
    assert list(picks) == list(pipe.sessions) and pipe.auto.cache_note == "written"
    adapter = picks[onnx_spec.RGFD_ADAPTER.file]
    assert adapter.engine == "onnxruntime" and "DeformConv" in adapter.reason and not adapter.ms
    for f in ON_OV:
        p = picks[f]
        assert set(p.ms) == {"onnxruntime", "openvino"} and min(p.ms.values()) > 0 and not p.cached
        assert p.ratio is not None and p.ratio > 0  # paired by scan, so not the ratio of the medians
        faster = p.ratio <= 1 - provider_measure.MARGIN
        assert p.engine == ("openvino" if faster else "onnxruntime"), p.line()
        assert _engines(pipe)[f] == ("OpenVINO" if faster else "CPUExecutionProvider")
    doc = json.loads(cache.read_text())
    assert doc["version"] == provider_cache.CACHE_VERSION and len(doc["entries"]) == len(picks)
    assert [p.name for p in cache.parent.iterdir()] == ["providers.json"]  # no temporary file left
    key = next(iter(doc["entries"]))
    assert ort.__version__ in key and provider_cache.openvino_version() in key and "threads 1" in key

    def no_timing(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(provider_measure, "measure", no_timing)
    monkeypatch.setattr(provider_cache, "_MEMO", {})  # a new process: only the file is left
    said: list[str] = []
    again = Pipeline.from_dir(folder, "auto", threads=1, notify=said.append)
    assert {f: p.engine for f, p in again.auto.picks.items()} == {f: p.engine for f, p in picks.items()}
    assert all(p.cached for p in again.auto.picks.values()) and again.auto.cache_note == "read"
    assert said == [] and again.auto.summary() is None and not again.auto.notes  # nothing measured
    assert _engines(again) == _engines(pipe)
    assert "DeformConv" in again.auto.picks[onnx_spec.RGFD_ADAPTER.file].line()


def test_engines_are_timed_on_a_stream_of_scans(folder, cache, monkeypatch):
    """Each timed scan is new to every timed session (a sensor's frames differ, and OpenVINO
    prepares its kernels per input shape): the scans' inputs come from other sessions, every
    engine of every graph runs each scan once, and the pipeline's own sessions run only scan 0
    (reference and warm-up) and the timed scans."""
    made, got, runs = [], [], []
    real_calls, real_measure = provider_measure.frame_calls, provider_measure.measure

    def spy_calls(pipe, seed=0, points=provider_measure.SCAN_POINTS, sessions=None, steps=None):
        out = real_calls(pipe, seed, points, sessions, steps)
        made.append((sessions, out))
        return out

    def spy_measure(pipe, todo, threads, deadline):
        own = {id(s) for s in pipe.sessions.values()}
        samples = real_measure(pipe, todo, threads, deadline)
        got.append((own, todo, samples))
        return samples

    def counting(name):
        real = getattr(ort.InferenceSession, name)

        def run(self, *a, **k):
            runs.append(id(self))
            return real(self, *a, **k)

        return run

    monkeypatch.setattr(provider_measure, "frame_calls", spy_calls)
    monkeypatch.setattr(provider_measure, "measure", spy_measure)
    for name in ("run", "run_with_iobinding"):
        monkeypatch.setattr(ort.InferenceSession, name, counting(name))
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    ((own, todo, samples),) = got
    on_ov = [f for f in pipe.sessions if f != onnx_spec.RGFD_ADAPTER.file]
    assert set(todo) == {(f, e) for f in on_ov for e in ("onnxruntime", "openvino")}
    assert samples.scans == provider_measure.STREAM_SCANS - 1 and not samples.failed
    assert all(v.shape == (samples.scans,) and v.min() > 0 for v in samples.ms.values())
    used = {id(s) for sessions, _ in made for s in sessions.values()}
    assert len(made) == provider_measure.STREAM_SCANS and not used & own
    first = [scan[onnx_spec.ENCODER.file][0]["voxel_features"] for _, scan in made]
    assert len({a.tobytes() for a in first}) == len(made)  # every scan distinct
    assert len({a.shape for a in first}) >= provider_measure.STREAM_SCANS // 2  # of different sizes
    steps = pipe.coefficients(provider_measure._loop_steps(pipe)).shape[0]
    assert len(made[0][1][onnx_spec.DENOISER_STEP.file]) == steps > 1  # the loop, call by call
    per_scan = sum(len(made[0][1][f]) for f in on_ov)  # the pipeline's onnxruntime sessions' calls
    expected = len(on_ov) + per_scan * (provider_measure.WARMUP_CALLS + samples.scans)  # + references
    assert sum(r in own for r in runs) == expected


def test_the_first_run_keeps_to_the_budget(folder, cache, monkeypatch):
    """Past ``BUDGET_S`` the stream stops once ``MIN_TIMED_SCANS`` are timed; the one line says
    how long it took."""
    monkeypatch.setattr(provider_measure, "BUDGET_S", 0.0)
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=lambda s: None)
    assert pipe.auto.scans == provider_measure.MIN_TIMED_SCANS
    line = pipe.auto.summary()
    assert f"over {provider_measure.MIN_TIMED_SCANS} scans" in line
    assert f"{pipe.auto.measured_s:.1f} s" in line
    enc = pipe.auto.picks[onnx_spec.ENCODER.file]
    assert f"median over {provider_measure.MIN_TIMED_SCANS} scans" in enc.reason


def test_a_long_loop_is_cut_for_the_timing(folder, monkeypatch):
    pipe = Pipeline.from_dir(folder, threads=1)
    calls = pipe.coefficients().shape[0]
    assert calls >= 2
    monkeypatch.setattr(provider_measure, "STREAM_LOOP_STEPS", calls)
    assert provider_measure._loop_steps(pipe) is None  # short enough: the manifest's own
    monkeypatch.setattr(provider_measure, "STREAM_LOOP_STEPS", calls - 1)
    assert provider_measure._loop_steps(pipe) == calls - 1
    inputs = provider_measure.frame_calls(pipe, steps=provider_measure._loop_steps(pipe))
    assert len(inputs[onnx_spec.DENOISER_STEP.file]) == calls - 1


def test_seeded_scans_are_radar_like(folder):
    """Clumps inside the box and the field of view: a real frame's points lie on a few objects."""
    pipe = Pipeline.from_dir(folder, threads=1)
    grid = pipe.artifact.grid
    lo, hi = np.asarray(grid.point_range[:3], np.float32), np.asarray(grid.point_range[3:], np.float32)
    a, b = (provider_measure.seeded_scan(pipe, np.random.default_rng(k), 400) for k in (0, 1))
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
    key = provider_cache.cache_key(art.manifest, onnx_spec.ENCODER.file, 1)
    assert key != provider_cache.cache_key(art.manifest, onnx_spec.ENCODER.file, 2)
    assert key != provider_cache.cache_key(art.manifest, onnx_spec.DENOISER_STEP.file, 1)
    _force(cache, folder, "onnxruntime")
    forced = [
        p for f, p in Pipeline(art, "auto", threads=1).auto.picks.items() if f != onnx_spec.RGFD_ADAPTER.file
    ]
    assert all(p.cached and p.reason == "forced" for p in forced)
    monkeypatch.setattr(ort, "__version__", "0.0.0")
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    assert provider_cache.cache_key(art.manifest, onnx_spec.ENCODER.file, 1) != key
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
    assert provider_measure.disagreement([ref[0] * (1 + 1e-6)], ref) is None
    assert "max rel" in provider_measure.disagreement([ref[0] * 1.01], ref)
    assert "shape" in provider_measure.disagreement([np.ones((3, 3), np.float32)], ref)
    # the coarse-to-fine head: a voxel on the gate may be gated by one engine only (<= 0.2 %)
    names = ["occupancy", "voxels"]
    vox = np.arange(1000, dtype=np.int64)
    occ = np.linspace(0, 1, 1000, dtype=np.float32)[:, None].repeat(8, 1)
    assert provider_measure.disagreement([occ[1:], vox[1:]], [occ, vox], names) is None
    assert "gated voxels" in provider_measure.disagreement([occ[3:], vox[3:]], [occ, vox], names)
    bad = occ[1:].copy()
    bad[5] += 0.1
    assert "max rel" in provider_measure.disagreement([bad, vox[1:]], [occ, vox], names)


def test_cache_location_and_bad_files(tmp_path, monkeypatch, folder):
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/dir")  # not absolute: ignored, as the XDG spec says
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert provider_cache.cache_path() == tmp_path / "home" / ".cache" / "msdnet" / "providers.json"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    path = provider_cache.cache_path()
    assert path == tmp_path / "x" / "msdnet" / "providers.json"
    path.parent.mkdir(parents=True)
    path.write_text("{not json")
    assert provider_cache.read_cache(path) == {}
    assert provider_cache.write_cache(path, {"k": {"engine": "onnxruntime"}}) == "written"
    assert provider_cache.read_cache(path) == {"k": {"engine": "onnxruntime"}}
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))  # a file where a folder must be
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    pipe = Pipeline.from_dir(folder, "auto", threads=1)
    assert pipe.auto.cache_note.startswith("not written: ") and "\n" not in pipe.auto.cache_note
    assert len(pipe(_scan(pipe), steps=2).points) > 0


def _entries(cache) -> dict:
    return json.loads(cache.read_text())["entries"]


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ("openvino", "a str where a record belongs"),
        (["openvino"], "a list where a record belongs"),
        ({"engine": "openvino", "ms": "12.5"}, "ms is a str"),
        ({"engine": "openvino", "ms": {"openvino": "12.5"}}, "not a time"),
        ({"engine": "openvino", "ms": {"openvino": float("nan")}}, "not a time"),
        ({"engine": "openvino", "ms": {"openvino": True}}, "not a time"),
        ({"engine": "openvino", "ms": {"tensorrt": 1.0}}, "ms names 'tensorrt'"),
        ({"engine": "tensorrt", "ms": {}}, "engine is 'tensorrt'"),
        ({"engine": "openvino-bf16", "ms": {}}, "engine is 'openvino-bf16'"),  # a bf16 pick in an f32 key
        ({"engine": "openvino", "ms": {}, "ratio": "0.5"}, "ratio is '0.5'"),
        ({"engine": "openvino", "ms": {}, "ratio": -1}, "ratio is '-1'"),
        ({"engine": "openvino", "ms": {}, "reason": 3}, "reason is a int"),
        ({"engine": "openvino", "ms": {}, "scans": "12"}, "scans is '12'"),
        ({"ms": {}}, "engine is 'None'"),
    ],
)
def test_a_cache_entry_that_does_not_validate_is_measured_again(folder, cache, bad, why):
    """Every entry is validated; one that does not validate counts as absent: that graph is
    measured again, with a note (``-v``, and in the one line), and the file gets a good entry."""
    _force(cache, folder, "onnxruntime")
    art = load_artifact(folder)
    key = provider_cache.cache_key(art.manifest, onnx_spec.ENCODER.file, 1)
    doc = json.loads(cache.read_text())
    doc["entries"][key] = bad
    cache.write_text(json.dumps(doc))
    said: list[str] = []
    pipe = Pipeline(art, "auto", threads=1, notify=said.append)
    picks = pipe.auto.picks
    assert not picks[onnx_spec.ENCODER.file].cached and picks[onnx_spec.ENCODER.file].reason != "forced"
    forced = set(picks) - {onnx_spec.ENCODER.file, onnx_spec.RGFD_ADAPTER.file}  # _force skips the adapter
    assert all(picks[f].cached for f in forced)
    (note,) = pipe.auto.notes
    assert note.startswith("cache entry for encoder.onnx does not validate") and why in note, note
    assert f"provider auto: note: {note}" in pipe.auto.lines() and note in said[0] and len(said) == 1
    assert provider_cache.entry_problem(_entries(cache)[key], "engine", ("onnxruntime", "openvino")) is None


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("{not json", "is not JSON"),
        ("", "is not JSON"),
        ("[1, 2]", "holds no entries record"),
        ('{"version": 4, "entries": []}', "holds no entries record"),
        ('{"version": 3, "entries": {}}', "is of version 3, not 4"),
        ('{"entries": {}}', "is of version None"),
        (b"\xff\xfe\x00", "cannot be read"),
    ],
)
def test_a_corrupt_or_stale_cache_file_is_measured_again_with_a_note(folder, cache, text, why):
    cache.parent.mkdir(parents=True)
    cache.write_bytes(text if isinstance(text, bytes) else text.encode())
    said: list[str] = []
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=said.append)
    assert not any(p.cached for p in pipe.auto.picks.values()) and pipe.auto.cache_note == "written"
    (note,) = pipe.auto.notes
    assert why in note and note.endswith("measured again") and len(said) == 1 and note in said[0]
    assert provider_cache.load_cache(cache) == (_entries(cache), None)  # replaced by a good file


def test_a_cache_folder_where_the_file_belongs_is_noted(folder, cache):
    cache.mkdir(parents=True)
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=lambda s: None)
    assert "cannot be read (IsADirectoryError)" in pipe.auto.notes[0]
    assert pipe.auto.cache_note.startswith("not written: ")


def test_a_bad_head_entry_is_measured_again(tmp_path_factory, cache):
    import shutil

    from msdnet.export.manifest import write_manifest
    from msdnet.runtime.providers import provider_head

    gated = tmp_path_factory.mktemp("gated") / "m"
    shutil.copytree(make_artifact(tmp_path_factory.mktemp("a"), "student", head_kind="gated"), gated)
    write_manifest(gated, {**json.loads((gated / "manifest.json").read_text()), "gate": 0.48})
    first = Pipeline.from_dir(gated, "auto", threads=1, notify=lambda s: None)
    (key,) = [k for k in _entries(cache) if k.split(" | ")[1].startswith("head:")]
    for bad in ({"head": "sideways", "ms": {}}, {"head": "dense", "ms": {"dense": "1"}}, "dense"):
        doc = json.loads(cache.read_text())
        doc["entries"][key] = bad
        cache.write_text(json.dumps(doc))
        provider_cache._MEMO.clear()
        again = Pipeline.from_dir(gated, "auto", threads=1, notify=lambda s: None)
        assert all(p.cached for p in again.auto.picks.values()) and not again.auto.head.cached
        assert again.auto.notes[0].startswith("cache entry for the head pick does not validate")
        names = provider_head.HEADS
        assert provider_cache.entry_problem(_entries(cache)[key], "head", names) is None
    assert first.auto.head is not None


def test_the_command_line_defaults_to_auto():
    from msdnet.runtime.frontends.infer.cli import main as infer
    from msdnet.runtime.frontends.live.params import PARAMS

    (opt,) = [p for p in infer.params if p.name == "provider"]
    assert opt.default == "auto"
    assert next(p for p in PARAMS if p.name == "provider").default == "auto"  # msdnet-node


def test_infer_says_once_that_it_measured(folder, tmp_path, monkeypatch):
    from msdnet.runtime.frontends.infer.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    src = tmp_path / "in"
    src.mkdir()
    cpu = Pipeline.from_dir(folder, threads=1)
    write_cloud(src / "scan.pcd", PointCloud(_scan(cpu), cpu.columns))
    args = [str(src), "--model", str(folder), "--steps", "2", "--threads", "1"]
    first = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "a")])
    assert first.exit_code == 0, first.output
    lines = [ln for ln in first.stderr.splitlines() if ln.startswith("provider auto")]
    assert len(lines) == 1 and "measured this model's engines here in" in lines[0]
    monkeypatch.setattr(provider_cache, "_MEMO", {})  # a new process: the file answers
    second = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "b")])
    assert second.exit_code == 0 and "provider auto" not in second.stderr


def test_results_name_the_cache_without_machine_folders(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    shown = provider_cache.cache_shown
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
