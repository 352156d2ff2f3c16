"""``msdnet-infer --rerun FILE.rrd``: the recording, read back with rerun-sdk's RrdReader, holds per
frame on the ``frame`` timeline the radar, the dense cloud coloured by its confidence, and in
dataset mode the LiDAR, equal to what the run wrote."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io.datasets import open_dataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.io.files import DENSE_COLUMNS, read_cloud
from msdnet.runtime.model.artifact import load_artifact

pytest.importorskip("rerun", reason="the [rerun] extra (CI installs it)")
from rerun.chunk import RrdReader  # noqa: E402

from msdnet.runtime.io.rerun_log import RADAR_RGB, confidence_colors  # noqa: E402

RUN = ["--steps", "3", "--threads", "1"]


def read_rrd(path: Path) -> dict[str, dict[int, dict[str, object]]]:
    """{entity: {frame: {column: value}}} of every chunk on the ``frame`` timeline."""
    out: dict[str, dict[int, dict[str, object]]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        table = chunk.to_record_batch().to_pydict()
        if "frame" not in table:
            continue
        for i, frame in enumerate(table["frame"]):
            out.setdefault(chunk.entity_path, {}).setdefault(frame, {}).update(
                {k: v[i] for k, v in table.items() if k not in ("frame", "log_time", "rerun.controls.RowId")}
            )
    return out


def _rgb(packed: list[int]) -> np.ndarray:
    """Rerun's packed 0xRRGGBBAA colours -> (M, 3) uint8."""
    c = np.asarray(packed, np.uint32)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], axis=1).astype(np.uint8)


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def test_file_mode_recording(vod_root, tmp_path):
    scans = sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin"))
    rrd = tmp_path / "rec" / "run.rrd"
    r = _infer(*scans, "--out", tmp_path / "out", "--rerun", rrd, *RUN)
    assert r.exit_code == 0, r.output
    got = read_rrd(rrd)
    assert sorted(got["/dense"]) == sorted(got["/radar"]) == [0, 1, 2]
    for i, scan in enumerate(scans):
        dense = read_cloud(tmp_path / "out" / f"{scan.stem}.npy", columns=DENSE_COLUMNS).points
        row = got["/dense"][i]
        np.testing.assert_array_equal(np.asarray(row["Points3D:positions"], np.float32), dense[:, :3])
        np.testing.assert_array_equal(np.asarray(row["confidence"], np.float32), dense[:, 3])
        np.testing.assert_array_equal(_rgb(row["Points3D:colors"]), confidence_colors(dense[:, 3]))
        radar = got["/radar"][i]
        np.testing.assert_array_equal(np.asarray(radar["Points3D:positions"]), read_cloud(scan).xyz)
        assert _rgb(radar["Points3D:colors"]).tolist() == [list(RADAR_RGB)]
        assert got["/source"][i]["TextLog:text"] == [str(scan)]
    assert len({len(got["/dense"][i]["Points3D:positions"]) for i in range(3)}) > 1  # real frames differ
    assert [p.name for p in rrd.parent.iterdir()] == ["run.rrd"]  # no temporary file left


def test_dataset_mode_logs_the_lidar(vod_root, tmp_path):
    rrd = tmp_path / "vod.rrd"
    r = _infer(vod_root, "--dataset", "vod", "--out", tmp_path / "out", "--rerun", rrd, *RUN)
    assert r.exit_code == 0, r.output
    got = read_rrd(rrd)
    ds = open_dataset("vod", vod_root)
    grid = load_artifact(BUNDLED_MODEL).grid
    assert sorted(got["/lidar"]) == list(range(len(ds.frame_ids))) == sorted(got["/dense"])
    for i, fid in enumerate(ds.frame_ids):
        frame = preprocess_frame(ds.load(fid), grid)
        lidar = np.asarray(got["/lidar"][i]["Points3D:positions"], np.float32)
        assert len(lidar) > 1000
        np.testing.assert_array_equal(lidar, frame.lidar.xyz)
        np.testing.assert_array_equal(np.asarray(got["/radar"][i]["Points3D:positions"]), frame.radar.xyz)
        dense = read_cloud(tmp_path / "out" / f"{fid}.npy", columns=DENSE_COLUMNS).points
        np.testing.assert_array_equal(
            np.asarray(got["/dense"][i]["Points3D:positions"], np.float32), dense[:, :3]
        )


def test_bag_mode_recording_has_the_stamps(vod_root, tmp_path):
    pytest.importorskip("rosbags", reason="the [ros] extra (CI installs it)")
    from test_rosbag import STAMP0, TOPIC, _scan, write_bag

    scans = sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin"))
    bag = write_bag(tmp_path / "in", "mcap", [_scan(s) for s in scans])
    rrd = tmp_path / "bag.rrd"
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "out", "--rerun", rrd, *RUN)
    assert r.exit_code == 0, r.output
    chunks = [c for c in RrdReader(rrd).stream().to_chunks() if c.entity_path == "/dense"]
    stamps = [t.value for c in chunks for t in c.to_record_batch().to_pydict()["stamp"]]
    assert stamps == [STAMP0 * 10**9 + i * 100_000_000 + 7 for i in range(len(scans))]
    assert sorted(read_rrd(rrd)["/radar"]) == list(range(len(scans)))
