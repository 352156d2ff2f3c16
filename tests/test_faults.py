"""``msdnet-infer`` under faults (issue 16): killed runs, outputs that cannot be written, dropped
rows, same bytes across --workers/--threads, early argument checks. Synthetic scans in the tiny
grid keep every test to seconds; the SIGKILL test runs the installed console script."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from export_helpers import copy_artifact, make_artifact

from msdnet.runtime import Pipeline, read_cloud
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.infer import files as file_mode
from msdnet.runtime.frontends.infer import guards, worker
from msdnet.runtime.frontends.infer.cli import OUT_COLUMNS, main
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io import files as io
from msdnet.runtime.io.atomic import clean_stale_temps, temp_name
from msdnet.runtime.io.files import write_cloud

VOD_COLUMNS = ("x", "y", "z", "rcs", "v_r_compensated")
FAST = ["--steps", "2", "--threads", "1"]
BUNDLED = BUNDLED_MODEL


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return make_artifact(tmp_path_factory.mktemp("art"), "student", "vod")


def _scan(path: Path, n: int = 200, seed: int = 0, box=(0.0, -6.4, -2.0, 12.8, 6.4, 4.0)) -> Path:
    """A random radar scan (N, 5) [x y z rcs v_r_compensated] inside ``box``, written as .ply."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(box[:3]), np.array(box[3:])
    pts = np.concatenate([lo + (hi - lo) * rng.random((n, 3)), rng.normal(0, 5, (n, 2))], axis=1)
    write_cloud(path, PointCloud(pts.astype(np.float32), VOD_COLUMNS))
    return path


def _infer(args: list) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def _temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


# ---------------------------------------------------------------- 1. killed runs


def _children(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                kids.append(int(entry.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")  # a zombie has exited


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to see a zombie")
def test_a_zombie_writers_temp_is_stale(tmp_path):
    """A killed worker whose parent died too stays a zombie until reaped; kill(pid, 0) still
    succeeds on it, which kept its temp file (CI, 2026-12-02). It writes nothing more: stale."""
    from msdnet.runtime.io.atomic import clean_stale_temps, temp_name

    child = subprocess.Popen([sys.executable, "-c", "pass"])  # never waited for: a zombie
    deadline = time.monotonic() + 30
    while _alive(child.pid) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert Path(f"/proc/{child.pid}/stat").exists() and not _alive(child.pid)
    (tmp_path / temp_name("a.npy", pid=child.pid)).write_bytes(b"half")
    (tmp_path / temp_name("b.npy")).write_bytes(b"mine")  # this live process's own
    assert clean_stale_temps(tmp_path) == 1
    assert [p.name.endswith(".b.npy.tmp") for p in tmp_path.iterdir()] == [True]
    child.wait()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to find the worker processes")
def test_sigkill_of_workers_run_leaves_no_worker_and_rerun_cleans_and_resumes(model, tmp_path):
    inputs, out = tmp_path / "in", tmp_path / "out"
    inputs.mkdir()
    for i in range(40):
        _scan(inputs / f"s{i:02d}.ply", seed=i)
    out.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True)
    stale = out / temp_name("s00.npy", pid=int(dead.stdout))  # what a killed writer leaves
    stale.write_bytes(b"half")
    exe = Path(sys.executable).with_name("msdnet-infer")
    cmd = [str(exe), str(inputs), "--model", str(model), "--out", str(out), "--workers", "2"]
    cmd += ["--steps", "40", "--threads", "1", "--provider", "cpu"]
    proc = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
    kids: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("*.npy")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        kids = _children(proc.pid)
        assert proc.poll() is None and list(out.glob("*.npy")), "the run ended before it could be killed"
        workers = [k for k in kids if "spawn_main" in Path(f"/proc/{k}/cmdline").read_text(errors="replace")]
        assert len(workers) == 2
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 10
        while any(_alive(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [k for k in kids if _alive(k)], "worker processes outlived their killed parent"
    finally:
        for k in [proc.pid, *kids, *_children(proc.pid)]:  # never leave a process behind
            if _alive(k):
                os.kill(k, signal.SIGKILL)
    done_before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npy")}
    assert len(done_before) < 40
    r = _infer([inputs, "--model", model, "--out", out, "--skip-existing", *FAST])
    assert r.exit_code == 0, r.output
    assert (
        f"files: {40 - len(done_before)} ok, 0 failed, {len(done_before)} skipped (output exists)" in r.output
    )
    assert len(list(out.glob("*.npy"))) == 40
    assert {n: (out / n).stat().st_mtime_ns for n in done_before} == done_before  # not redone
    assert _temps(out) == []  # the planted one and any the kill left are gone


def test_clean_stale_temps_keeps_live_writers(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True)
    (tmp_path / temp_name("a.npy", pid=int(dead.stdout))).write_bytes(b"x")
    (tmp_path / temp_name("art", pid=int(dead.stdout))).mkdir()  # a killed export's folder
    live = tmp_path / temp_name("b.npy")  # this process: still writing
    live.write_bytes(b"x")
    (tmp_path / ".notours.tmp").write_bytes(b"x")
    assert clean_stale_temps(tmp_path) == 2
    assert _temps(tmp_path) == sorted([live.name, ".notours.tmp"])


def test_skip_existing_needs_png_too(model, tmp_path):
    scans = [_scan(tmp_path / f"s{i}.ply", seed=i) for i in range(2)]
    out = tmp_path / "out"
    assert _infer([*scans, "--model", model, "--out", out, *FAST]).exit_code == 0
    r = _infer([*scans, "--model", model, "--out", out, "--skip-existing", "--png", *FAST])
    assert r.exit_code == 0 and "files: 2 ok, 0 failed;" in r.output  # no .png yet: redone
    r = _infer([*scans, "--model", model, "--out", out, "--skip-existing", "--png", *FAST])
    assert "files: 0 ok, 0 failed, 2 skipped (output exists)" in r.output


# ---------------------------------------------------------------- 2. outputs that cannot be written


def test_out_is_a_file_or_an_input_folder(model, tmp_path):
    scan = _scan(tmp_path / "in" / "s.ply")
    (tmp_path / "taken").write_text("x")
    for extra in ([], ["--dataset", "vod"]):
        src = scan.parent if extra else scan
        r = _infer([src, "--model", model, "--out", tmp_path / "taken", *extra])
        assert (
            r.exit_code == 2
            and r.output == f"error: {tmp_path / 'taken'}: --out exists and is not a folder\n"
        )
    for src in (scan, scan.parent):
        r = _infer([src, "--model", model, "--out", scan.parent, "--format", "ply", *FAST])
        assert r.exit_code == 2 and f"--out is the folder of input {src}; choose another --out" in r.output
    assert sorted(p.name for p in scan.parent.iterdir()) == ["s.ply"]


@pytest.mark.parametrize("mode", ["files", "dataset"])
def test_read_only_out_is_one_line_before_any_work(model, tmp_path, monkeypatch, mode):
    scan = _scan(tmp_path / "in" / "s.ply")
    extra = ["--dataset", "vod"] if mode == "dataset" else []  # checked before the dataset is read
    out = tmp_path / "ro"
    real_open = os.open

    def read_only(path, *args, **kwargs):
        if str(path).startswith(str(out)):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    r = _infer([scan.parent if extra else scan, "--model", model, "--out", out, *extra, *FAST])
    assert r.exit_code == 2 and r.output == f"error: {out}: cannot write: read-only file system\n"


@pytest.mark.parametrize("fmt", ["bin", "npy"])
def test_disk_full_names_the_output_and_says_so(model, tmp_path, monkeypatch, fmt):
    scan = _scan(tmp_path / "s.ply")
    out = tmp_path / "out"

    def full_disk(path, mode="r", *args, **kwargs):  # writes go to /dev/full (ENOSPC)
        return open("/dev/full", "wb") if "w" in mode else open(path, mode, *args, **kwargs)

    monkeypatch.setattr(io, "open", full_disk, raising=False)
    r = _infer([scan, "--model", model, "--out", out, "--format", fmt, *FAST])
    assert r.exit_code == 1
    assert f"FAILED {out / ('s.' + fmt)}: cannot write: no space left on the device (disk full)" in r.output
    assert _temps(out) == [] and not (out / f"s.{fmt}").exists()


def test_longest_legal_name_still_writes(model, tmp_path):
    stem = "r" * 251  # "<stem>.ply" and "<stem>.npy": 255 bytes, the file-system limit
    scan = _scan(tmp_path / f"{stem}.ply")
    r = _infer([scan, "--model", model, "--out", tmp_path / "out", *FAST])
    assert r.exit_code == 0, r.output
    assert len(read_cloud(tmp_path / "out" / f"{stem}.npy", columns=OUT_COLUMNS)) > 0
    assert len(temp_name(f"{stem}.npy").encode()) == 255


# ---------------------------------------------------------------- 3. dropped rows


def test_dropped_rows_counted_per_file_and_in_summary(model, tmp_path):
    pts = np.asarray(read_cloud(_scan(tmp_path / "a.ply")).points, np.float64)
    pts[[3, 7], 1] = np.nan
    pts[9, 4] = 1e300  # float64 beyond float32: would become Inf
    np.save(tmp_path / "bad.npy", pts.astype(np.float64).view([(c, "<f8") for c in VOD_COLUMNS]).ravel())
    nan = np.full((5, 5), np.nan).view([(c, "<f8") for c in VOD_COLUMNS]).ravel()
    np.save(tmp_path / "nan.npy", nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw numpy overflow warning
        assert read_cloud(tmp_path / "bad.npy").dropped_nonfinite == 3
    r = _infer([tmp_path / "bad.npy", tmp_path / "nan.npy", "--model", model, "--out", tmp_path / "o", *FAST])
    assert r.exit_code == 0, r.output
    assert "points in 197 (dropped 8 with NaN/Inf" in r.output
    assert f"  dropped: {tmp_path / 'bad.npy'}: 3 rows with NaN/Inf (or beyond float32)" in r.output
    assert f"  dropped: {tmp_path / 'nan.npy'}: 5 rows" in r.output
    assert f"empty: {tmp_path / 'nan.npy'}: all 5 rows are NaN/Inf: empty output" in r.output
    assert "empty scan" not in r.output


def test_pcd_claiming_more_points_than_it_holds(tmp_path):
    path = write_cloud(tmp_path / "c.pcd", PointCloud(np.ones((10, 3), np.float32), ("x", "y", "z")))
    path.write_bytes(path.read_bytes().replace(b"WIDTH 10", b"WIDTH 12").replace(b"POINTS 10", b"POINTS 12"))
    with pytest.raises(MsdnetError, match="header states 12 points, the data holds 10"):
        read_cloud(path)


def test_empty_output_bin_reads_back(model, tmp_path):
    scan = _scan(tmp_path / "far.ply", box=(50.0, 50.0, 50.0, 60.0, 60.0, 60.0))  # outside the grid
    r = _infer([scan, "--model", model, "--out", tmp_path / "o", "--format", "bin", *FAST])
    assert r.exit_code == 0 and "no point inside the grid" in r.output
    back = read_cloud(tmp_path / "o" / "far.bin", columns=OUT_COLUMNS)
    assert len(back) == 0 and back.columns == OUT_COLUMNS


# ---------------------------------------------------------------- 4. same seed, same bytes


@pytest.mark.skipif(not (BUNDLED / "manifest.json").is_file(), reason="bundled sim-lite model missing")
def test_same_bytes_across_workers_and_threads(tmp_path):
    """The bundled model (where DeformConv's threaded sums used to differ by ~1e-6 m between
    --threads 1 and 2): identical files for --threads 1/2 and --workers 1/2."""
    scans = [
        _scan(tmp_path / f"s{i}.ply", n=400, seed=i, box=(0.0, -16.0, -2.0, 32.0, 16.0, 4.0)) for i in (0, 1)
    ]
    runs = {
        "t1": ["--threads", "1"],
        "t2": ["--threads", "2"],
        "w2": ["--workers", "2"],
        "w2t2": ["--workers", "2", "--threads", "2"],
    }
    for name, extra in runs.items():
        r = _infer([*scans, "--model", BUNDLED, "--out", tmp_path / name, "--steps", "2", *extra])
        assert r.exit_code == 0, r.output
    for scan in scans:
        ref = (tmp_path / "t1" / f"{scan.stem}.npy").read_bytes()
        assert len(ref) > 1000
        for name in runs:
            assert (tmp_path / name / f"{scan.stem}.npy").read_bytes() == ref, name


class _InlinePool:
    """ProcessPoolExecutor stand-in: records what each worker would get, runs jobs here."""

    seen: dict = {}

    def __init__(self, workers, ctx, initializer, initargs):
        _InlinePool.seen = {"workers": workers, "initargs": initargs}
        model, provider, threads, options, _parent, key = initargs
        worker.WORKER.update(pipe=Pipeline.from_dir(model, provider, threads), options=options)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        fut: Future = Future()
        fut.set_result(fn(*args))
        return fut


def test_workers_keep_threads_and_are_clamped_to_cores(model, tmp_path, monkeypatch):
    monkeypatch.setattr(file_mode, "ProcessPoolExecutor", _InlinePool)
    scans = [_scan(tmp_path / f"s{i}.ply", seed=i) for i in range(3)]
    r = _infer([*scans, "--model", model, "--out", tmp_path / "a", "--workers", "2", "--threads", "3"])
    assert r.exit_code == 0, r.output
    cores = guards.usable_cores()
    if cores >= 2:
        assert _InlinePool.seen["workers"] == 2 and _InlinePool.seen["initargs"][2] == 3
    r = CliRunner().invoke(
        main, [*map(str, scans), "--model", str(model), "--out", str(tmp_path / "b"), "--workers", "64"]
    )
    assert r.exit_code == 0, r.output
    assert f"warning: --workers 64 is more than the {cores} CPU cores here; using {cores}" in r.stderr
    assert _InlinePool.seen["workers"] <= min(cores, 3) or cores == 1


# ---------------------------------------------------------------- 6. early argument checks


def test_negative_seed_refused_once(model, tmp_path):
    scans = [_scan(tmp_path / f"s{i}.ply", seed=i) for i in range(3)]
    r = _infer([*scans, "--model", model, "--out", tmp_path / "o", "--seed", "-1"])
    assert r.exit_code == 2 and r.output.count("--seed") == 1 and "-1 is not in the range" in r.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("block", "key", "value", "cause"),
    [
        ("diffusion", "sample_steps", 0, "diffusion block: sample_steps must be >= 1, got 0"),
        ("grid", "voxel_size", [0.0, 0.4, 0.6], "voxel_size must be three finite values > 0"),
    ],
)
def test_bad_manifest_values_blamed_on_the_manifest(model, tmp_path, block, key, value, cause):
    art = copy_artifact(model, tmp_path / "m")
    manifest = json.loads((art / "manifest.json").read_text())
    manifest[block][key] = value
    (art / "manifest.json").write_text(json.dumps(manifest))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = _infer([_scan(tmp_path / "s.ply"), "--model", art, "--out", tmp_path / "o"])
    assert r.exit_code == 2 and r.output.startswith(f"error: {art / 'manifest.json'}: ")
    assert cause in r.output and "--steps" not in r.output and len(r.output.splitlines()) == 1


def test_dataset_mode_goes_on_past_a_bad_frame_and_needs_no_pose(model, vod_root, tmp_path):
    import shutil

    root = shutil.copytree(vod_root, tmp_path / "vod")
    (root / "radar" / "training" / "velodyne" / "01047.bin").write_bytes(b"\0" * 30)  # broken frame
    for side in ("radar", "lidar"):  # single-scan densifying never reads a pose
        (root / side / "training" / "pose" / "01201.json").unlink()
    out = tmp_path / "out"
    r = _infer([root, "--dataset", "vod", "--model", model, "--out", out, *FAST])
    assert r.exit_code == 1, r.output
    assert "2 frames, median" in r.output and "1 frames failed:" in r.output
    assert "FAILED 01047: " in r.output and "whole number" in r.output
    body = json.loads((out / "comparison.json").read_text())
    assert [f["frame"] for f in body["frames"]] == ["00549", "01201"] and len(body["failed"]) == 1
    assert (out / "01201.npy").is_file() and not (out / "01047.npy").exists()
