"""BEV pictures, realism statistics and the ``show`` / ``stats`` commands."""

from __future__ import annotations

import os

import numpy as np
import pytest
from click.testing import CliRunner
from matplotlib.image import imread

from msdnet.runtime.frontends.data.show_stats import show, stats
from msdnet.runtime.io.datasets import VodDataset
from msdnet.runtime.io.datasets.stats import REALISM_TARGETS, compute_stats, format_stats
from msdnet.runtime.io.pictures import Layer, render_bev
from msdnet.runtime.spec.grid import GRID_PRESETS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RADAR_RGB = (0xD6 / 255, 0x27 / 255, 0x28 / 255)  # the radar colour of ``show``


def _pixels(path, rgb=(1.0, 0.0, 0.0)) -> int:
    """Pixels within 0.1 of the colour ``rgb`` in each channel."""
    img = imread(path)[..., :3]  # (H, W, 3) floats in [0, 1]
    return int(np.sum(np.all(np.abs(img - np.asarray(rgb)) < 0.1, axis=-1)))


def test_render_bev_png(tmp_path):
    grey = np.random.default_rng(0).uniform([0, -10], [30, 10], size=(500, 2))
    red = np.array([[10.0, 0.0, 1.0], [20.0, 5.0, 0.0]])
    with_red = render_bev(
        tmp_path / "a.png",
        [Layer(grey, "#777777", "lidar"), Layer(red, "#ff0000", "radar", "radar")],
        GRID_PRESETS["lite"],
        "test",
    )
    without = render_bev(tmp_path / "b.png", [Layer(grey, "#777777", "lidar")], None, "")
    assert with_red.read_bytes()[:8] == PNG_MAGIC
    assert sorted(os.listdir(tmp_path)) == ["a.png", "b.png"]  # no temp files left
    assert _pixels(with_red) > 10 and _pixels(without) == 0
    with pytest.raises(ValueError, match=r"\(N, >=2\)"):
        render_bev(tmp_path / "c.png", [Layer(np.zeros(3), "k", "bad")])
    with pytest.raises(ValueError, match="style"):
        render_bev(tmp_path / "c.png", [Layer(grey, "k", "bad", "blobs")])
    assert not (tmp_path / "c.png").exists()


def test_vod_stats_in_band(vod_root):
    result = compute_stats(VodDataset(vod_root))
    assert result.frames == 3
    assert result.radar_points == pytest.approx((322 + 352 + 242) / 3)
    assert result.out_of_band() == []  # the real frames meet the targets set from them
    assert 35_000 < result.lidar_in_region < 45_000
    assert result.rcs_median == pytest.approx(-12.6, abs=0.1)
    assert 0.10 < result.moving_share < 0.20
    table = format_stats(result)
    assert "radar_points" in table and "outside" not in table
    assert set(REALISM_TARGETS) <= {line.split()[0] for line in table.splitlines()}


def test_stats_missing_columns_are_none(astyx_root):
    from msdnet.runtime.io.datasets import AstyxDataset

    result = compute_stats([AstyxDataset(astyx_root)[0]])
    assert result.rcs_median is None and result.moving_share is None
    assert result.radar_points == 831
    assert "rcs_median" not in result.out_of_band()  # absent statistics are not judged
    assert "radar_points" in result.out_of_band()  # Astyx's radar is far denser than VoD's


def test_show_command(vod_root, tmp_path):
    out = tmp_path / "pics" / "549.png"
    args = ["--dataset", "vod", "--data", str(vod_root), "--frame", "00549", "--out", str(out)]
    res = CliRunner().invoke(show, args)
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:8] == PNG_MAGIC and _pixels(out, RADAR_RGB) > 20
    assert "radar 182/322" in res.output and "ground: patchwork" in res.output


def test_show_bad_frame_one_line(vod_root, tmp_path):
    out = tmp_path / "x.png"
    args = ["--dataset", "vod", "--data", str(vod_root), "--frame", "77777", "--out", str(out)]
    res = CliRunner().invoke(show, args)
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "77777" in lines[0]
    assert not out.exists()


def test_stats_command(vod_root, tmp_path):
    res = CliRunner().invoke(stats, ["--dataset", "vod", "--data", str(vod_root), "--frames", "2"])
    assert res.exit_code == 0, res.output
    assert "2 of 3 frames" in res.output and "rcs_median" in res.output
    res = CliRunner().invoke(stats, ["--dataset", "sim", "--data", str(tmp_path / "none")])
    assert res.exit_code == 2 and "dataset folder not found" in res.output
