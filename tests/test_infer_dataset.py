"""``msdnet-infer --dataset``: the radar of a paired dataset densified and compared with its LiDAR;
the figures in comparison.json equal the metrics computed directly, and the summary says it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from export_helpers import make_artifact

from msdnet.runtime import Pipeline, read_cloud
from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.frontends.infer.dataset import COMPARISON_FILE, OUT_COLUMNS
from msdnet.runtime.io.datasets import open_dataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.io.pictures import read_counts
from msdnet.runtime.metrics.cloud import chamfer_distance
from msdnet.runtime.metrics.crop import crop_to_grid

CD_TOL = 1e-6  # metres: same points, same metric code


@pytest.fixture(scope="module")
def vod_model(tmp_path_factory) -> Path:
    return make_artifact(tmp_path_factory.mktemp("art"), "student", "vod")


def _infer(args: list) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def test_dataset_mode_writes_clouds_and_compares(vod_model, vod_root, tmp_path):
    r = _infer(
        [vod_root, "--dataset", "vod", "--model", vod_model, "--out", tmp_path, "--frames", "2"]
        + ["--steps", "3", "--threads", "1", "--png"]
    )
    assert r.exit_code == 0, r.output
    assert "denser:" in r.output and "closer:" in r.output
    body = json.loads((tmp_path / COMPARISON_FILE).read_text())
    assert len(body["frames"]) == 2
    ds = open_dataset("vod", vod_root)
    pipe = Pipeline.from_dir(vod_model, threads=1)
    for row in body["frames"]:
        fid = row["frame"]
        frame = preprocess_frame(ds.load(fid), pipe.artifact.grid)
        res = pipe(frame.radar, steps=3)
        back = read_cloud(tmp_path / f"{fid}.npy", columns=OUT_COLUMNS)
        assert back.columns == OUT_COLUMNS
        np.testing.assert_array_equal(back.points[:, :3], res.points)
        assert (tmp_path / f"{fid}.png").stat().st_size > 10_000
        legend = read_counts(tmp_path / f"{fid}.png")  # the picture counts what the JSON counts
        assert legend == {
            "LiDAR": row["lidar_points"],
            "MSDNet output": row["dense_points"],
            "radar": row["radar_points"],
        }
        radar = crop_to_grid(frame.radar.xyz, pipe.artifact.grid)
        assert row["radar_points"] == len(radar) > 0
        assert row["lidar_points"] == len(frame.lidar) > 1000
        assert abs(row["radar_cd"] - chamfer_distance(radar, frame.lidar.xyz)) < CD_TOL
        dense = crop_to_grid(res.points, pipe.artifact.grid)
        assert row["dense_points"] == len(dense)
        if len(dense):
            assert abs(row["dense_cd"] - chamfer_distance(dense, frame.lidar.xyz)) < CD_TOL
    radar_mean = np.mean([f["radar_points"] for f in body["frames"]])
    assert f"radar {radar_mean:.0f} points" in r.output


def test_dataset_mode_keep_radar_scores_the_union(vod_model, vod_root, tmp_path):
    """--keep-radar in --dataset mode: the written cloud and the comparison are model + radar."""
    args = [vod_root, "--dataset", "vod", "--model", vod_model, "--frames", "1", "--steps", "3"]
    r = _infer([*args, "--out", tmp_path, "--threads", "1", "--keep-radar"])
    assert r.exit_code == 0, r.output
    assert "-> MSDNet+radar " in r.output
    body = json.loads((tmp_path / COMPARISON_FILE).read_text())
    assert body["keep_radar"] is True
    (row,) = body["frames"]
    ds = open_dataset("vod", vod_root)
    pipe = Pipeline.from_dir(vod_model, threads=1)
    frame = preprocess_frame(ds.load(row["frame"]), pipe.artifact.grid)
    model_only = pipe(frame.radar, steps=3)
    back = read_cloud(tmp_path / f"{row['frame']}.npy", columns=OUT_COLUMNS).points
    m, k = len(model_only.points), len(frame.radar)  # the radar is already cropped to the grid box
    assert k > 0 and back.shape == (m + k, 4)
    np.testing.assert_array_equal(back[:m, :3], model_only.points)
    np.testing.assert_array_equal(back[m:, :3], frame.radar.xyz)
    assert np.all(back[m:, 3] == 1.0)
    dense = crop_to_grid(back[:, :3], pipe.artifact.grid)
    assert row["dense_points"] == len(dense) > len(crop_to_grid(model_only.points, pipe.artifact.grid))
    assert abs(row["dense_cd"] - chamfer_distance(dense, frame.lidar.xyz)) < CD_TOL


def test_dataset_mode_refusals(vod_model, vod_root, tmp_path):
    r = _infer([vod_root, "--split", "val", "--model", vod_model, "--out", tmp_path])
    assert r.exit_code == 2 and "only apply with --dataset" in r.output
    r = _infer([vod_root, vod_root, "--dataset", "vod", "--model", vod_model, "--out", tmp_path])
    assert r.exit_code == 2 and "exactly one dataset folder" in r.output
    r = _infer([tmp_path, "--dataset", "vod", "--model", vod_model, "--out", tmp_path / "o"])
    assert r.exit_code == 2 and "Traceback" not in r.output
