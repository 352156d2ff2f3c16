"""Silent misreads, missing limits, late failures and leftovers on the newer surfaces (issue 24):
duplicate PointCloud2 fields, a PLY body longer than its header, a bag message over the point
cap, --rerun and bag outputs that cannot be written, broken bag metadata, killed runs' temps,
and the Python API's seed check. Bundled model, a few points, one step: seconds per test."""

from __future__ import annotations

import errno
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import plyfile
import pytest
from click.testing import CliRunner

from msdnet.runtime import Pipeline, read_cloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io.atomic import temp_name
from msdnet.runtime.io.files import MAX_POINTS, VOD_RADAR_COLUMNS

RUN = ["--steps", "1", "--threads", "1"]
TOPIC = "/radar/points"


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def _points(n: int = 60, seed: int = 0) -> np.ndarray:
    """(n, 7) VoD radar rows inside the bundled model's grid."""
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 7), np.float32)
    pts[:, 0], pts[:, 1], pts[:, 2] = rng.uniform(2, 40, n), rng.uniform(-10, 10, n), rng.uniform(-1, 2, n)
    pts[:, 3:] = rng.normal(0, 3, (n, 4))
    return pts


def _dead_pid() -> int:
    code = "import os; print(os.getpid())"
    return int(subprocess.run([sys.executable, "-c", code], capture_output=True).stdout)


def _write_ply(path: Path, pts: np.ndarray, text: bool, stated: int) -> Path:
    rows = np.empty(len(pts), dtype=[(c, "<f4") for c in ("x", "y", "z")])
    for i, c in enumerate(("x", "y", "z")):
        rows[c] = pts[:, i]
    plyfile.PlyData([plyfile.PlyElement.describe(rows, "vertex")], text=text).write(str(path))
    body = path.read_bytes()
    path.write_bytes(body.replace(f"element vertex {len(pts)}".encode(), f"element vertex {stated}".encode()))
    return path


# ---------------------------------------------------------------- readers


@pytest.mark.parametrize("text", [False, True])
def test_ply_body_longer_than_its_header_is_refused_with_both_counts(tmp_path, text):
    path = _write_ply(tmp_path / "s.ply", _points(10), text, stated=6)
    with pytest.raises(MsdnetError, match="header states 6 vertices, the data holds 10"):
        read_cloud(path)
    ok = _write_ply(tmp_path / "ok.ply", _points(10), text, stated=10)
    assert len(read_cloud(ok)) == 10


def test_pipeline_negative_seed_names_the_argument():
    pipe = Pipeline.from_dir(BUNDLED_MODEL, threads=1)
    with pytest.raises(ValueError, match=r"^seed: must be an integer >= 0 .*got -1$"):
        pipe(_points()[:, [0, 1, 2, 3, 5]], steps=1, seed=-1)


# ---------------------------------------------------------------- Rerun


def test_rerun_to_a_folder_or_a_read_only_place_refused_before_any_work(tmp_path, monkeypatch):
    scan = tmp_path / "in" / "s.npy"
    scan.parent.mkdir()
    np.save(scan, _points())
    folder = tmp_path / "rec.rrd"
    folder.mkdir()
    r = _infer(scan, "--out", tmp_path / "o", "--rerun", folder, *RUN)
    assert r.exit_code == 2 and r.output == f"error: {folder}: --rerun is a folder; name a FILE.rrd\n"
    assert not (tmp_path / "o").exists()  # nothing ran
    ro = tmp_path / "ro"
    real_open = os.open

    def read_only(path, *args, **kwargs):
        if str(path).startswith(str(ro)):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", read_only)
    r = _infer(scan, "--out", tmp_path / "o", "--rerun", ro / "run.rrd", *RUN)
    assert r.exit_code == 2 and r.output == f"error: {ro / 'run.rrd'}: cannot write: read-only file system\n"
    assert not (tmp_path / "o").exists()


def test_killed_runs_temps_removed_by_the_next_run(tmp_path):
    """A SIGKILLed writer's temp (its pid gone): recordings and pictures are removed next time."""
    pytest.importorskip("rerun", reason="the [rerun] extra (CI installs it)")
    scan = tmp_path / "in" / "s.npy"
    scan.parent.mkdir()
    np.save(scan, _points())
    dead = _dead_pid()
    out, rec = tmp_path / "o", tmp_path / "rec" / "run.rrd"
    rec.parent.mkdir()
    out.mkdir()
    stale_rrd = rec.parent / temp_name("run.rrd", pid=dead)
    stale_png = out / temp_name("s.png", pid=dead)
    stale_rrd.write_bytes(b"RRF2 half")
    stale_png.write_bytes(b"\x89PNG half")
    r = _infer(scan, "--out", out, "--rerun", rec, "--png", *RUN)
    assert r.exit_code == 0, r.output
    assert not stale_rrd.exists() and not stale_png.exists()
    assert sorted(p.name for p in rec.parent.iterdir()) == ["run.rrd"]
    assert sorted(p.name for p in out.iterdir()) == ["s.npy", "s.png"]


# ---------------------------------------------------------------- bags

rosbags = pytest.importorskip("rosbags", reason="the [ros] extra (CI installs it)")
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from msdnet.runtime.io.rosbag import POINTCLOUD2, make_pointcloud2, pointcloud2_to_array  # noqa: E402

STORE = get_typestore(Stores.ROS2_HUMBLE)


def _bag(path: Path, msgs: list, storage: str = "mcap") -> Path:
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection(TOPIC, POINTCLOUD2, typestore=STORE)
        for i, msg in enumerate(msgs):
            w.write(conn, 1_700_000_000 * 10**9 + i * 10**8, bytes(STORE.serialize_cdr(msg, POINTCLOUD2)))
    return path


def _msg(pts: np.ndarray, names=VOD_RADAR_COLUMNS) -> object:
    return make_pointcloud2(STORE, pts, names, (1_700_000_000, 0), "radar")


def test_two_fields_of_one_name_refused_naming_topic_and_field(tmp_path):
    names = ("x", "y", "z", "rcs", "rcs", "v_r_compensated", "time")
    bag = _bag(tmp_path / "dup", [_msg(_points(), names)])
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2
    assert r.output.strip().splitlines()[-1] == (
        f"error: {TOPIC}: PointCloud2 has two fields named 'rcs': which one is meant is unknown"
    )
    assert not (tmp_path / "o").exists()
    canon = ("x", "y", "z", "rcs", "RCS", "v_r_compensated", "time")  # one canonical name twice
    bag = _bag(tmp_path / "canon", [_msg(_points(), canon)])
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2 and "fields 'rcs' and 'RCS' both match model column 'rcs'" in r.output


def test_message_over_the_point_cap_refused_naming_the_message(tmp_path):
    big = _msg(_points(3))
    big.width = MAX_POINTS + 1  # claims millions of points: refused before any array is built
    bag = _bag(tmp_path / "big", [_msg(_points()), big])
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 1, r.output
    assert f"FAILED {bag}: {TOPIC} message 1 at " in r.output
    assert f"{MAX_POINTS + 1} points exceeds the cap of {MAX_POINTS} per scan" in r.output
    assert "messages: 1 ok, 1 failed" in r.output
    msg = _msg(_points(20))
    fields = list(msg.fields[:3])
    with pytest.raises(MsdnetError, match="m0: 20 points exceeds the cap of 10 per scan"):
        pointcloud2_to_array(msg, fields, "m0", max_points=10)


@pytest.mark.parametrize(
    ("text", "cause"),
    [
        ("rosbag2_bagfile_information: {storage_identifier: [", "metadata.yaml is unreadable: "),
        ("written_by: another tool\n", "metadata.yaml is not a rosbag2 one (no storage_identifier)"),
    ],
)
def test_broken_or_foreign_metadata_is_one_line_naming_the_bag(tmp_path, text, cause):
    bag = _bag(tmp_path / "b", [_msg(_points())])
    (bag / "metadata.yaml").write_text(text)
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2 and r.output.startswith(f"error: {bag}: {cause}"), r.output
    assert r.output.count("\n") == 1


def test_bag_out_read_only_refused_before_any_work(tmp_path, monkeypatch):
    bag = _bag(tmp_path / "b", [_msg(_points())])
    ro = tmp_path / "ro"
    real_open, real_mkdir = os.open, os.mkdir

    def refuse(real):
        def call(path, *args, **kwargs):
            if str(path).startswith(str(ro)):
                raise OSError(errno.EROFS, "Read-only file system", str(path))
            return real(path, *args, **kwargs)

        return call

    monkeypatch.setattr(os, "open", refuse(real_open))
    monkeypatch.setattr(os, "mkdir", refuse(real_mkdir))
    r = _infer(bag, "--topic", TOPIC, "--out", ro / "dense", *RUN)
    assert r.exit_code == 2 and r.output == f"error: {ro / 'dense'}: cannot write: read-only file system\n"


def test_sqlite3_disk_full_is_one_line_and_leaves_nothing(tmp_path, monkeypatch):
    from rosbags.rosbag2 import storage_sqlite3

    bag = _bag(tmp_path / "b", [_msg(_points()), _msg(_points(seed=1))], storage="sqlite3")
    real_write = storage_sqlite3.Sqlite3Writer.write
    calls = []

    def full(self, *args):
        calls.append(1)
        if len(calls) > 2:
            raise sqlite3.OperationalError("database or disk is full")
        return real_write(self, *args)

    monkeypatch.setattr(storage_sqlite3.Sqlite3Writer, "write", full)
    out = tmp_path / "out" / "dense"
    r = _infer(bag, "--topic", TOPIC, "--out", out, *RUN)
    assert r.exit_code == 2, r.output
    assert r.output.splitlines()[-1] == f"error: {out}: cannot write: no space left on the device (disk full)"
    assert list(out.parent.iterdir()) == []  # neither the bag nor its temporary folder


def test_killed_bag_writers_temp_folder_removed_by_the_next_run(tmp_path):
    bag = _bag(tmp_path / "b", [_msg(_points())])
    out = tmp_path / "out" / "dense"
    out.parent.mkdir()
    stale = out.parent / temp_name("dense", pid=_dead_pid())  # what a SIGKILLed bag write leaves
    (stale / "dense").mkdir(parents=True)
    (stale / "dense" / "dense_0.mcap").write_bytes(b"half a bag")
    live = out.parent / temp_name("other")  # a live writer's (this process): kept
    live.mkdir()
    r = _infer(bag, "--topic", TOPIC, "--out", out, *RUN)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(["dense", live.name])


def test_field_names_with_odd_characters_stay_on_one_line():
    """Found by msdnet-bench fuzz (msg case 1551, seed 1): a field name holding a newline."""
    from msdnet.runtime.io.rosbag import resolve_fields

    msg = _msg(_points(5), ("x\n", "y", "z", "rcs", "v_r", "v_r_compensated", "time"))
    with pytest.raises(MsdnetError) as err:
        resolve_fields(msg, ("x", "intensity"), {}, TOPIC)
    assert "\n" not in str(err.value) and "(fields: 'x\\n' y z rcs" in str(err.value)
