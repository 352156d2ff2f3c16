"""What bad input gets, by class (docs/reliability.md): a file or message that disagrees with its
own header is refused, every input row the engine drops is counted, every output place is checked
before any work, a killed ``msdnet-data pair`` leaves nothing behind for good, an option that does
not apply is refused or noted, refresh refuses external data in one line, a manifest whose encoder
form disagrees with its graph is named, msdnet-node's parameters file is read within limits and
its options that cannot work are refused at start, an unmatched writer is named once, a benchmark
checks its arguments before measuring, and every command's bad argument or bad input file ends in
one line without a traceback. Bundled model, a few points."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import plyfile
import pytest
from click.testing import CliRunner

from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import DROP_REASONS, PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io.atomic import TEMP_PREFIX, check_writable, temp_name
from msdnet.runtime.io.files import read_cloud, write_cloud

XYZ = ("x", "y", "z")
ENV = {**os.environ, "ORT_DISABLE_TELEMETRY": "1", "RAY_USAGE_STATS_ENABLED": "0", "NO_COLOR": "1"}
UNWRITABLE = Path("/sys/msdnet-out")  # not writable, not even by root


def _cannot_write_sys() -> bool:
    try:
        os.close(os.open(UNWRITABLE, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError:
        return True
    os.unlink(UNWRITABLE)
    return False


def _cloud(n: int = 10) -> PointCloud:
    return PointCloud(np.random.default_rng(0).random((n, 3), dtype=np.float32), XYZ)


# ---------------------------------------------------------------- 1. files agree with their headers


def _ply(path: Path, text: bool, stated: int, n: int = 10) -> Path:
    rows = np.empty(n, dtype=[(c, "<f4") for c in XYZ])
    for i, c in enumerate(XYZ):
        rows[c] = _cloud(n).points[:, i]
    plyfile.PlyData([plyfile.PlyElement.describe(rows, "vertex")], text=text).write(str(path))
    path.write_bytes(
        path.read_bytes().replace(f"element vertex {n}\n".encode(), f"element vertex {stated}\n".encode())
    )
    return path


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
@pytest.mark.parametrize("stated", [6, 14], ids=["understates", "overstates"])
def test_ply_header_count_must_match_its_body(tmp_path: Path, text: bool, stated: int) -> None:
    with pytest.raises(MsdnetError, match=f"header states {stated} vertices, the data holds 10"):
        read_cloud(_ply(tmp_path / "c.ply", text, stated))
    assert len(read_cloud(_ply(tmp_path / "ok.ply", text, 10))) == 10


def test_pcd_header_and_body_must_agree(tmp_path: Path) -> None:
    good = write_cloud(tmp_path / "good.pcd", _cloud())
    body = good.read_bytes()
    cases = {
        "points_under": (body.replace(b"POINTS 10", b"POINTS 8"), "WIDTH 10 x HEIGHT 1 points but POINTS 8"),
        "width_under": (body.replace(b"WIDTH 10", b"WIDTH 8"), "WIDTH 8 x HEIGHT 1 points but POINTS 10"),
        "both_under": (
            body.replace(b"WIDTH 10", b"WIDTH 8").replace(b"POINTS 10", b"POINTS 8"),
            "header states 8 points, the data holds 10",
        ),
        "trailing_bytes": (body + b"\0" * 14, "header states 10 points, the data holds 11 and 2 more bytes"),
        "truncated": (body[:-12], "header states 10 points, the data holds 9"),
    }
    for name, (data, why) in cases.items():
        (tmp_path / f"{name}.pcd").write_bytes(data)
        with pytest.raises(MsdnetError, match=why):
            read_cloud(tmp_path / f"{name}.pcd")
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
    head += "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
    (tmp_path / "a.pcd").write_text(head + "1 2 3\n4 5 6\n")
    assert len(read_cloud(tmp_path / "a.pcd")) == 2
    (tmp_path / "a3.pcd").write_text(head + "1 2 3\n4 5 6\n7 8 9\n")
    with pytest.raises(MsdnetError, match="header states 2 points, the data holds 3"):
        read_cloud(tmp_path / "a3.pcd")


def test_npy_shape_must_match_its_bytes_and_bin_whole_rows(tmp_path: Path) -> None:
    good = write_cloud(tmp_path / "good.npy", _cloud())
    (tmp_path / "long.npy").write_bytes(good.read_bytes() + b"\0" * 24)
    with pytest.raises(MsdnetError, match="header states 10 rows, the data holds 12"):
        read_cloud(tmp_path / "long.npy")
    (tmp_path / "short.npy").write_bytes(good.read_bytes()[:-8])
    with pytest.raises(MsdnetError, match="header states 10 rows, the data holds 9 and 4 more bytes"):
        read_cloud(tmp_path / "short.npy")
    write_cloud(tmp_path / "lidar" / "s.bin", PointCloud(np.ones((3, 4), np.float32), (*XYZ, "intensity")))
    cut = tmp_path / "lidar" / "cut.bin"
    cut.write_bytes((tmp_path / "lidar" / "s.bin").read_bytes()[:-6])
    with pytest.raises(MsdnetError, match="not a whole number of 4-column float32 rows"):
        read_cloud(cut)


rosbags = pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from msdnet.runtime.io.rosbag import (  # noqa: E402
    POINTCLOUD2,
    make_pointcloud2,
    message_cloud,
    pointcloud2_to_array,
)

STORE = get_typestore(Stores.ROS2_HUMBLE)


def _msg(n: int, **header: int):
    pts = np.random.default_rng(1).random((n, 3), dtype=np.float32)
    msg = make_pointcloud2(STORE, pts, XYZ, (1, 0), "radar")
    return replace(msg, **header) if header else msg


def test_pointcloud2_saying_less_than_it_holds_is_refused() -> None:
    """The issue's message: width and row_step claim 100 points, data holds 352."""
    msg = _msg(352, width=100, row_step=100 * 12)
    with pytest.raises(ValueError, match=r"PointCloud2 header states 1200 bytes .* the data holds 4224"):
        pointcloud2_to_array(msg, msg.fields)
    raw = bytes(STORE.serialize_cdr(msg, POINTCLOUD2))
    with pytest.raises(MsdnetError, match="m0: PointCloud2 header states 1200 bytes"):
        message_cloud(STORE.deserialize_cdr, raw, XYZ, {}, "m0")
    for sibling in (
        _msg(352, width=100),  # width alone understated (height 1: row_step ignored below width)
        _msg(100, row_step=120 * 12),  # row_step overstated: data holds less than it says
        _msg(10, height=2, width=5, row_step=5 * 12 + 4),  # two padded rows need 128 bytes
    ):
        with pytest.raises(ValueError, match="PointCloud2|data has"):
            pointcloud2_to_array(sibling, sibling.fields)
    padded = _msg(10, row_step=10 * 12 + 8)  # one row with 8 bytes of padding: whole
    padded = replace(padded, data=np.concatenate([padded.data, np.zeros(8, np.uint8)]))
    assert pointcloud2_to_array(padded, padded.fields).shape == (10, 3)
    assert pointcloud2_to_array(_msg(7), _msg(7).fields).shape == (7, 3)


# ---------------------------------------------------------------- 2. dropped rows are counted


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.from_dir(BUNDLED_MODEL, threads=1)


def _scan(pipe: Pipeline, n: int = 80, seed: int = 0) -> np.ndarray:
    """(n, C) rows inside the bundled model's grid."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(pipe.artifact.grid.point_range[:3]), np.asarray(pipe.artifact.grid.point_range[3:])
    pts = np.zeros((n, len(pipe.columns)), np.float32)
    pts[:, :3] = lo + 0.1 + (hi - lo - 0.2) * rng.random((n, 3))
    pts[:, 3:] = rng.normal(0, 2, (n, len(pipe.columns) - 3))
    return pts


def test_every_dropped_row_is_counted_and_outputs_keep_their_bytes(pipe: Pipeline) -> None:
    good = _scan(pipe)
    bad = good[:9].copy()
    bad[:2, 0] = np.nan  # non-finite
    bad[2, 3] = np.inf  # non-finite in a feature column
    bad[3:7, 0] = 500.0  # outside the grid (x)
    bad[7:9, 2] = -50.0  # outside the grid (z)
    mixed = np.concatenate([bad[:5], good, bad[5:]])
    res, ref = pipe(mixed, steps=1), pipe(good, steps=1)
    assert res.stats["dropped_nonfinite"] == 3 and res.stats["dropped_outside_grid"] == 6
    assert res.stats["dropped_over_cap"] == 0 and res.stats["dropped"] == 9
    assert res.stats["points_in"] - res.stats["dropped"] == res.stats["points_in_grid"] == len(good)
    assert ref.stats["dropped"] == 0 and set(DROP_REASONS) <= set(ref.stats)
    assert res.points.tobytes() == ref.points.tobytes()  # counting changes no byte
    cloud = PointCloud(good, pipe.columns, dropped_nonfinite=4)  # a reader dropped 4 rows
    assert pipe(cloud, steps=1).stats["dropped_nonfinite"] == 4
    empty = pipe(np.zeros((0, len(pipe.columns)), np.float32), steps=1)
    assert empty.stats["dropped"] == 0


def test_rows_over_the_voxel_cap_are_counted(pipe: Pipeline) -> None:
    capped = Pipeline(replace(pipe.artifact, inputs=replace(pipe.artifact.inputs, max_voxels=5)), threads=1)
    from msdnet.runtime.engine.voxelize import voxelize

    pts = _scan(pipe)
    res = capped(pts, steps=1)
    vox = voxelize(pts, pipe.artifact.grid, 5)
    assert res.stats["voxels"] == 5 and vox.dropped_over_cap == len(pts) - int(vox.counts.sum()) > 0
    assert res.stats["dropped_over_cap"] == vox.dropped_over_cap == res.stats["dropped"]


def test_infer_counts_drops_per_file_and_in_total(pipe: Pipeline, tmp_path: Path) -> None:
    from msdnet.runtime.frontends.infer.cli import main

    pts = _scan(pipe, 40)
    pts[0, 1] = np.nan
    pts[1:4, 0] = 900.0
    write_cloud(tmp_path / "in" / "a.ply", PointCloud(pts, pipe.columns))
    write_cloud(tmp_path / "in" / "b.ply", PointCloud(_scan(pipe, 30, seed=1), pipe.columns))
    args = [str(tmp_path / "in"), "--out", str(tmp_path / "o"), "--steps", "1", "--provider", "cpu"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert "points in 69 (dropped 1 with NaN/Inf, 3 outside the grid), out" in r.output
    assert (
        f"  dropped: {tmp_path / 'in' / 'a.ply'}: 1 rows with NaN/Inf (or beyond float32), 3 outside"
        in r.output
    )
    assert "b.ply:" not in r.output


# ---------------------------------------------------------------- 3. outputs checked first


def test_check_writable_kinds(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(MsdnetError, match="is a folder; a file path is needed"):
        check_writable(tmp_path, "file")
    with pytest.raises(MsdnetError, match="exists and is not a folder"):
        check_writable(tmp_path / "f", "into")
    with pytest.raises(MsdnetError, match="cannot write: Not a directory"):
        check_writable(tmp_path / "f" / "sub" / "x.json", "file")
    assert check_writable(tmp_path / "new" / "deeper", "into") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # the folders made for the probe are removed with it
    stale = tmp_path / temp_name("x", pid=_dead_pid())
    stale.mkdir()
    check_writable(tmp_path / "out", "folder")
    assert not stale.exists()


@pytest.mark.skipif(not _cannot_write_sys(), reason="needs a place even root cannot write")
@pytest.mark.parametrize(
    "cmd",
    [
        ["msdnet-bench", "latency", "--out", "{X}"],
        ["msdnet-bench", "fuzz", "--cases", "1", "--json", "{X}/f.json"],
        ["msdnet-data", "simulate", "--frames", "1", "--out", "{X}"],
        ["msdnet-data", "show", "--dataset", "vod", "--data", "nope", "--frame", "1", "--out", "{X}.png"],
        ["msdnet-data", "pair", "nope.bag", "--radar-topic", "a", "--lidar-topic", "b", "--out", "{X}"],
        ["msdnet-export", "nope", "--out", "{X}"],
        ["msdnet-train", "teacher", "--dataset", "vod", "--data", "nope", "--out", "{X}"],
    ],
    ids=lambda c: " ".join(c[:2]),
)
def test_unwritable_output_refused_before_any_work(cmd: list[str]) -> None:
    r = subprocess.run(
        [c.replace("{X}", str(UNWRITABLE)) for c in cmd], capture_output=True, text=True, env=ENV
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith(f"error: {UNWRITABLE}") and "cannot write" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# ---------------------------------------------------------------- 4. a killed pair leaves nothing for good


def _dead_pid() -> int:
    return int(
        subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True).stdout
    )


def _pair_bag(path: Path, frames: int, lidar_points: int, nan_rows: int = 0) -> Path:
    from rosbags import rosbag2

    rng = np.random.default_rng(0)
    radar_cols = ("x", "y", "z", "rcs", "v_r", "v_r_compensated", "time")
    with rosbag2.Writer(path, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as bag:
        radar = bag.add_connection("/radar", POINTCLOUD2, typestore=STORE)
        lidar = bag.add_connection("/lidar", POINTCLOUD2, typestore=STORE)
        for k in range(frames):
            ns = 1_700_000_000 * 10**9 + k * 10**8
            scan = rng.random((50, 7), dtype=np.float32)
            scan[:nan_rows, 1] = np.nan
            bag.write(
                radar,
                ns,
                STORE.serialize_cdr(
                    make_pointcloud2(STORE, scan, radar_cols, divmod(ns, 10**9), "r"), POINTCLOUD2
                ),
            )
            sweep = rng.random((lidar_points, 4), dtype=np.float32)
            msg = make_pointcloud2(STORE, sweep, (*XYZ, "intensity"), divmod(ns + 1000, 10**9), "l")
            bag.write(lidar, ns + 1000, STORE.serialize_cdr(msg, POINTCLOUD2))
    return path


def test_killed_pair_leaves_no_temporary_folder_after_the_next_run(tmp_path: Path) -> None:
    bag = _pair_bag(tmp_path / "drive", frames=400, lidar_points=4000)
    args = ["--radar-topic", "/radar", "--lidar-topic", "/lidar", "--extrinsic", "0,0,0,0,0,0"]
    outs = tmp_path / "outs"
    outs.mkdir()
    proc = subprocess.Popen(
        ["msdnet-data", "pair", str(bag), *args, "--out", str(outs / "a")],
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        temps = [p for p in outs.iterdir() if p.name.startswith(TEMP_PREFIX)]
        if temps and any(temps[0].rglob("*.bin")):  # writing frames: kill it mid-run
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    left = [p for p in outs.iterdir() if p.name.startswith(TEMP_PREFIX)]
    assert left and f"-{proc.pid}-" in left[0].name and not (outs / "a").exists()
    small = _pair_bag(tmp_path / "small", frames=3, lidar_points=20)
    r = subprocess.run(
        ["msdnet-data", "pair", str(small), *args, "--out", str(outs / "b")],
        env=ENV,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in outs.iterdir()) == ["b"]  # the dead run's folder is gone


def test_pair_counts_the_rows_it_drops(tmp_path: Path) -> None:
    from msdnet.runtime.frontends.data.cli import main

    bag = _pair_bag(tmp_path / "drive", frames=3, lidar_points=20, nan_rows=2)
    args = [
        "pair",
        str(bag),
        "--radar-topic",
        "/radar",
        "--lidar-topic",
        "/lidar",
        "--extrinsic",
        "0,0,0,0,0,0",
    ]
    r = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "p")])
    assert r.exit_code == 0 and "note: rows with NaN/Inf dropped: 6 radar" in r.output, r.output
    assert len(read_cloud(tmp_path / "p" / "radar" / "training" / "velodyne" / "00000.bin")) == 48


# ---------------------------------------------------------------- 5. options that do not apply


def test_layout_for_self_describing_inputs_refused_or_noted(pipe: Pipeline, tmp_path: Path) -> None:
    from msdnet.runtime.frontends.infer.cli import main

    write_cloud(tmp_path / "in" / "a.pcd", PointCloud(_scan(pipe, 20), pipe.columns))
    base = ["--out", str(tmp_path / "o"), "--steps", "1", "--provider", "cpu"]
    for extra in (["--layout", "kitti-lidar"], ["--columns", "x,y,z,rcs"]):
        r = CliRunner().invoke(main, [str(tmp_path / "in" / "a.pcd"), *base, *extra])
        assert r.exit_code == 2 and f"error: {extra[0]}: names the columns of .bin files" in r.output, (
            r.output
        )
    bins = np.zeros((4, 7), np.float32)
    bins[:, :3] = _scan(pipe, 4)[:, :3]
    bins.tofile(tmp_path / "in" / "b.bin")
    r = CliRunner().invoke(main, [str(tmp_path / "in"), *base, "--layout", "vod-radar"])
    assert (
        r.exit_code == 0
        and "note: --layout applies to the 1 .bin inputs only, not to the 1 others" in r.output
    )
    for extra, why in (
        (["--split", "val"], "--split/--frames: only apply with --dataset"),
        (["--frames", "2"], "--split/--frames: only apply with --dataset"),
        (["--ray-timeout", "5"], "--ray-timeout: only applies with --ray"),
    ):
        r = CliRunner().invoke(main, [str(tmp_path / "in" / "a.pcd"), *base, *extra])
        assert r.exit_code == 2 and why in r.output, r.output
    r = CliRunner().invoke(main, [str(tmp_path / "in"), *base, "--dataset", "vod", "--layout", "xyz"])
    assert r.exit_code == 2 and "does not apply with --dataset" in r.output
    r = CliRunner().invoke(main, [str(tmp_path / "in"), *base, "--dataset", "vod", "--workers", "2"])
    assert r.exit_code == 2 and "--workers: --dataset runs in one process" in r.output


def test_export_options_without_their_partner_refused(tmp_path: Path) -> None:
    from msdnet.export.cli import main

    r = CliRunner().invoke(main, ["nope", "--out", str(tmp_path / "m"), "--dataset", "vod"])
    assert r.exit_code == 2 and "--dataset: names the layout of --data" in r.output
    r = CliRunner().invoke(main, ["nope", "--out", str(tmp_path / "m"), "--frames", "2"])
    assert r.exit_code == 2 and "--frames: only used with --verify" in r.output


# ---------------------------------------------------------------- 7. refresh and external data


def _with_external_data(src: Path, dst: Path, graph: str) -> Path:
    """A copy of model ``src`` whose ``graph`` keeps one initializer in ``../outside.bin``,
    the manifest's size and hash updated to match."""
    import hashlib

    import onnx

    shutil.copytree(src, dst)
    model = onnx.load(str(dst / graph))
    init = max(model.graph.initializer, key=lambda t: len(t.raw_data))
    (dst.parent / "outside.bin").write_bytes(init.raw_data)
    length = len(init.raw_data)
    init.ClearField("raw_data")
    init.data_location = onnx.TensorProto.EXTERNAL
    for k, v in (("location", "../outside.bin"), ("offset", "0"), ("length", str(length))):
        entry = init.external_data.add()
        entry.key, entry.value = k, v
    data = model.SerializeToString()
    (dst / graph).write_bytes(data)
    manifest = json.loads((dst / "manifest.json").read_text())
    for g in manifest["graphs"]:
        if g["file"] == graph:
            g["bytes"], g["sha256"] = len(data), hashlib.sha256(data).hexdigest()
    (dst / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return dst


def _script(name: str) -> str:
    """The installed console script ``name`` beside this interpreter."""
    return str(Path(sys.executable).with_name(name))


def test_refresh_refuses_external_data_in_one_line(tmp_path: Path) -> None:
    model = _with_external_data(BUNDLED_MODEL, tmp_path / "models" / "m", "encoder.onnx")
    r = subprocess.run(
        [_script("msdnet-export"), "refresh", str(model), "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        env=ENV,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    name = _external_initializer(model / "encoder.onnx")
    assert r.stderr.strip() == f"error: encoder.onnx: keeps tensors in external files ({name})"
    assert not (tmp_path / "r").exists()


def _external_initializer(graph: Path) -> str:
    import onnx

    return next(
        t.name
        for t in onnx.load(str(graph), load_external_data=False).graph.initializer
        if t.data_location == onnx.TensorProto.EXTERNAL
    )


# ---------------------------------------------------------------- model folders: encoder form


def test_an_encoder_form_that_disagrees_with_its_graph_names_the_field(tmp_path: Path) -> None:
    folder = tmp_path / "m"
    shutil.copytree(BUNDLED_MODEL, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps({**manifest, "encoder_form": "pairs"}))
    from msdnet.runtime.model.artifact import load_artifact

    with pytest.raises(MsdnetError, match="encoder_form 'pairs' disagrees with encoder.onnx") as err:
        load_artifact(folder)
    assert str(err.value).startswith(f"{folder / 'manifest.json'}: ") and '"encoder_form": "rulebook"' in str(
        err.value
    )


# ---------------------------------------------------------------- msdnet-node: parameters, options, writers

NODE = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli"]


def test_a_parameters_file_that_is_not_one_is_refused_in_one_line(tmp_path: Path) -> None:
    head = "msdnet_node:\n  ros__parameters:\n"
    bomb = "a: &a [x,x,x,x,x,x,x,x,x]\n" + "".join(
        f"{b}: &{b} [{','.join([f'*{a}'] * 9)}]\n" for a, b in zip("abcde", "bcdef", strict=True)
    )
    cases = {
        "latin1.yaml": (head + "    target_frame: bâse\n").encode("latin-1"),
        "gzip.yaml": __import__("gzip").compress(head.encode()),
        "bomb.yaml": (bomb + head + "    fields: *f\n").encode(),
        "range.yaml": (head + "    seed: -1\n").encode(),
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        r = subprocess.run(
            NODE + ["--params-file", str(tmp_path / name)], capture_output=True, text=True, env=ENV
        )
        assert r.returncode == 2 and r.stderr.startswith(f"error: {tmp_path / name}: "), r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and len(r.stderr) < 300, r.stderr
    assert "seed: must be >= 0" in r.stderr


def test_node_options_that_cannot_work_are_refused_at_start() -> None:
    pytest.importorskip("cyclonedds")
    for args, says in (
        (["--output-topic", "/radar/points"], "--output-topic: /radar/points is both the input topic"),
        (["--input-type", "radar_scan", "--field", "rcs=foo"], "--field: a RadarScan has no field 'foo'"),
    ):
        r = subprocess.run(NODE + ["--provider", "cpu", *args], capture_output=True, text=True, env=ENV)
        assert r.returncode == 2 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_writer_the_node_cannot_match_is_named_once() -> None:
    pytest.importorskip("cyclonedds")
    from types import SimpleNamespace

    from msdnet.runtime.frontends.live.discovery import WriterWatch

    said: list[str] = []
    watch = WriterWatch.__new__(WriterWatch)
    samples = [
        SimpleNamespace(
            sample_info=SimpleNamespace(instance_handle=h, valid_data=True),
            topic_name="rt/radar/points",
            type_name="sensor_msgs::msg::dds_::PointCloud2_",
            qos=[],
        )
        for h in (1, 2)
    ]
    watch.builtin = SimpleNamespace(take=lambda N: samples)
    watch.reader = SimpleNamespace(get_matched_publications=lambda: [])
    watch.dds_topic, watch.ros_topic = "rt/radar/points", "/radar/points"
    watch.dds_type, watch.reliable, watch.warn = "radar_msgs::msg::dds_::RadarScan_", False, said.append
    watch.seen, watch.said, watch.count = {}, set(), 0
    watch.poll()
    watch.poll()
    assert watch.count == 1 and len(said) == 1, said  # two writers of one wrong type: one line
    assert "publishes sensor_msgs/msg/PointCloud2, this node reads radar_msgs/msg/RadarScan" in said[0]


# ---------------------------------------------------------------- msdnet-bench: arguments before measuring


def test_benchmarks_check_arguments_and_outputs_before_measuring(tmp_path: Path) -> None:
    from msdnet.benchmarks.cli import main as bench

    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    r = CliRunner().invoke(bench, ["params", "tiny", "--out", str(blocker)])
    assert r.exit_code == 2 and f"{blocker}: exists and is not a folder" in r.output
    assert "preset tiny" not in r.output  # refused before the table was computed
    r = CliRunner().invoke(bench, ["encoders", "--preset", "huge", "--data", str(tmp_path)])
    assert r.exit_code == 2 and "Invalid value for '--preset'" in r.output and "KeyError" not in r.output


# ---------------------------------------------------------------- every command: one line, no traceback


def test_every_command_ends_bad_arguments_and_bad_files_in_one_line(tmp_path: Path) -> None:
    bad_model = tmp_path / "badmodel"
    bad_model.mkdir()
    (bad_model / "manifest.json").write_text("{nope")
    (tmp_path / "garbage.ply").write_bytes(os.urandom(300))
    (tmp_path / "garbage.bag").write_bytes(b"#ROSBAG V2.0\n" + os.urandom(300))
    (tmp_path / "data").mkdir()
    py = [_script("msdnet-export"), "refresh"]
    t = str(tmp_path)
    cases = {
        "infer arg": ["msdnet-infer", f"{t}/garbage.ply", "--out", f"{t}/o", "--layout", "nope"],
        "infer file": [
            "msdnet-infer",
            f"{t}/garbage.ply",
            "--out",
            f"{t}/o",
            "--provider",
            "cpu",
            "--steps",
            "1",
        ],
        "node arg": ["msdnet-node", "--domain-id", "-5"],
        "node file": ["msdnet-node", "--model", str(bad_model), "--topic", "/radar/points"],
        "data arg": ["msdnet-data", "simulate", "--out", f"{t}/s", "--frames", "many"],
        "data file": [
            "msdnet-data",
            "pair",
            f"{t}/garbage.bag",
            "--radar-topic",
            "a",
            "--lidar-topic",
            "b",
            "--out",
            f"{t}/p",
        ],
        "export arg": ["msdnet-export", str(bad_model), "--out", f"{t}/e", "--frames", "0"],
        "export file": ["msdnet-export", str(bad_model), "--out", f"{t}/e"],
        "train arg": ["msdnet-train", "nokind", "--dataset", "vod", "--data", f"{t}/data", "--out", f"{t}/t"],
        "train file": [
            "msdnet-train",
            "teacher",
            "--dataset",
            "vod",
            "--data",
            f"{t}/garbage.ply",
            "--out",
            f"{t}/t",
        ],
        "bench arg": ["msdnet-bench", "fuzz", "--cases", "abc"],
        "bench file": [
            "msdnet-bench",
            "steps",
            "--model",
            str(bad_model),
            "--dataset",
            "vod",
            "--data",
            f"{t}/data",
            "--out",
            f"{t}/b",
        ],
        "refresh arg": [*py, str(tmp_path / "no-such-model")],
        "refresh file": [*py, str(bad_model)],
    }
    procs = {
        k: subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        for k, c in cases.items()
    }
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode not in (0, None), (name, out, err)
        assert "Traceback" not in err and "Traceback" not in out, (name, err)
        lines = [line for line in err.splitlines() if line.startswith(("error:", "Error:", "  FAILED"))]
        lines += [line for line in out.splitlines() if line.startswith("  FAILED")]
        assert len(lines) == 1, (name, out, err)
