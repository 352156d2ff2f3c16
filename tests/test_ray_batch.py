"""``msdnet-infer --ray`` on a local Ray instance started here (2 CPUs): the same bytes as a local
run at the same thread count, and a killed actor leaves whole files only and a summary naming
every file without a result."""

from __future__ import annotations

import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.sim.sequence import SequenceSim

ray = pytest.importorskip("ray", reason="the [ray] extra (CI installs it)")
psutil = pytest.importorskip("psutil")  # a Ray dependency

ACTOR = "MapWorker(MapBatches(_InferActor))"


@pytest.fixture(scope="module")
def local_ray():
    """A 2-CPU Ray instance owned by this test process (started once for the module), on 127.0.0.1
    with usage stats off and no cloud-metadata probe, as ``--ray`` starts one (ray_batch)."""
    from msdnet.runtime.frontends.infer.ray_batch import local_instance

    start = time.perf_counter()
    with local_instance(num_cpus=2):
        print(f"ray.init: {time.perf_counter() - start:.1f} s")  # 6-9 s on 2 busy cores
        yield


@pytest.fixture(scope="module")
def radar_dir(vod_root, tmp_path_factory) -> Path:
    """The three real VoD scans and two simulated ones, in a folder named like VoD's."""
    folder = tmp_path_factory.mktemp("in") / "radar"
    folder.mkdir()
    for scan in sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin")):
        shutil.copy(scan, folder / scan.name)
    sim = SequenceSim(11, 0, 2)
    for f in range(2):
        sim.frame(f).radar.astype("<f4").tofile(folder / f"sim{f}.bin")
    return folder


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def _counts(output: str) -> str:
    """The summary's first line without its times: files ok/failed, points in and out."""
    return next(line for line in output.splitlines() if line.startswith("files:")).split("; time")[0]


def test_ray_gives_the_bytes_of_a_local_run(local_ray, radar_dir, tmp_path):
    run = ["--steps", "3", "--threads", "1", "--seed", "2"]
    local = _infer(radar_dir, "--out", tmp_path / "local", *run)
    assert local.exit_code == 0, local.output
    rrd = tmp_path / "ray.rrd"
    r = _infer(radar_dir, "--out", tmp_path / "ray", *run, "--ray", "auto", "--rerun", rrd)
    assert r.exit_code == 0, r.output
    pytest.importorskip("rerun")
    from test_rerun import read_rrd

    assert sorted(read_rrd(rrd)["/dense"]) == [0, 1, 2, 3, 4]  # --rerun logs a Ray run from its outputs
    assert "files: 5 ok, 0 failed" in r.output
    assert _counts(r.output) == _counts(local.output)
    names = sorted(p.name for p in (tmp_path / "local").iterdir())
    assert len(names) == 5 and names == sorted(p.name for p in (tmp_path / "ray").iterdir())
    for name in names:
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes()


def _actors() -> list:
    me = psutil.Process(os.getpid())
    found = []
    for p in me.children(recursive=True):
        try:
            if ACTOR in " ".join(p.cmdline()):
                found.append(p)
        except psutil.Error:
            continue
    return found


def test_killed_actor_leaves_whole_files_and_names_the_rest(local_ray, radar_dir, tmp_path):
    copies = tmp_path / "radar"  # 18 files: six copies of each VoD scan
    copies.mkdir()
    vod = sorted(radar_dir.glob("0*.bin"))
    for i in range(6):
        for scan in vod:
            shutil.copy(scan, copies / f"c{i}_{scan.name}")
    ref = tmp_path / "ref"
    assert _infer(*vod, "--out", ref, "--threads", "1").exit_code == 0
    out = tmp_path / "out"
    stale = {p.pid for p in _actors()}  # an earlier run's idle actors are not this run's
    result: dict = {}
    job = threading.Thread(
        target=lambda: result.update(r=_infer(copies, "--out", out, "--threads", "1", "--ray", "auto"))
    )
    job.start()
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and time.monotonic() < deadline and job.is_alive():
        actors = [p for p in _actors() if p.pid not in stale]
        if actors and out.is_dir() and sum(p.suffix == ".npy" for p in out.iterdir()) >= 4:
            killed = actors[0].pid
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    job.join(180)
    assert killed is not None, "no actor to kill before the run ended"
    r = result["r"]
    assert r.exit_code == 1, r.output
    failed = [line.split("FAILED ", 1)[1] for line in r.output.splitlines() if "FAILED " in line]
    ok = int(r.output.split("files: ")[1].split(" ok")[0])
    assert failed and ok + len(failed) == 18, r.output
    assert all("no result, the Ray run stopped (" in f and "Actor" in f for f in failed), r.output
    assert not [p for p in out.iterdir() if p.name.startswith(".")], r.output  # no temporary file left
    written = sorted(out.iterdir())
    assert len(written) >= ok
    for path in written:  # every file there is whole: the bytes of the local run
        assert path.read_bytes() == (ref / f"{path.stem.split('_', 1)[1]}.npy").read_bytes()
    for f in failed:
        assert f.split(":")[0].startswith(str(copies))
