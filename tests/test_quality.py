"""Quality evaluation building blocks: cropping, summaries, torch vs onnxruntime, reports."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from export_helpers import (
    copy_artifact,
    make_artifact,
    make_exported_checkpoint,
    one_torch_thread,
)

from msdnet.benchmarks.downstream.suite import read_sequences, select_sequences
from msdnet.benchmarks.eval_methods import (
    Method,
    PipelineMethod,
    RawRadar,
    RunSettings,
    TorchMethod,
    build_methods,
    common_grid,
    parse_ablation,
)
from msdnet.benchmarks.quality.report import picture_strip, write_json
from msdnet.benchmarks.quality.suite import (
    agreement,
    evaluate_quality,
    margins,
    pick_frames,
    summarize,
)
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets import open_dataset
from msdnet.runtime.io.datasets.preprocess import crop_mask, preprocess_frame
from msdnet.runtime.metrics.cloud import FrameScores, score_frame
from msdnet.runtime.metrics.crop import crop_to_grid, xy_range
from msdnet.runtime.spec.grid import GRID_PRESETS

TINY = GRID_PRESETS["tiny"]
SETTINGS = RunSettings(threads=1)


@pytest.fixture(scope="module")
def astyx_pair(tmp_path_factory) -> tuple[Path, Path]:
    """(checkpoint, artifact exported from that checkpoint): a tiny random student, Astyx columns."""
    return make_exported_checkpoint(tmp_path_factory.mktemp("pair"), "astyx")


class _Fake(Method):
    """A method with fixed attributes, for the pure bookkeeping functions."""

    def __init__(self, name: str, role: str, kind: str, backend: str, grid=None) -> None:
        self.name, self.key, self.role, self.kind = name, name.lower(), role, kind
        self.backend, self.source, self.grid = backend, f"/models/{name}", grid


def _scores(cd: float, n: int = 10, f: float = 0.5) -> FrameScores:
    return FrameScores(cd, cd * cd, 2 * cd, {t: f for t in (0.05, 0.1, 0.2, 0.5)}, 0.3, 1e-4, n)


def test_crop_to_grid_is_the_reference_crop():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-5, -20, -4], [40, 20, 8], size=(5000, 3)).astype(np.float32)
    out = crop_to_grid(pts, TINY)
    np.testing.assert_array_equal(out, pts[crop_mask(pts, TINY, fov=True)])
    az = np.degrees(np.arctan2(out[:, 1], out[:, 0]))
    assert len(out) > 100 and np.all(np.abs(az) <= TINY.fov_deg) and out[:, 0].max() < 12.8


def test_pick_frames_spreads_in_order():
    ids = [f"{i:03d}" for i in range(10)]
    assert pick_frames(ids, None) == ids and pick_frames(ids, 50) == ids
    assert pick_frames(ids, 3) == ["000", "004", "009"]


def test_summarize_skips_undefined_metrics_but_counts_empty_frames():
    empty = FrameScores(*(float("nan"),) * 3, {t: 0.0 for t in (0.05, 0.1, 0.2, 0.5)}, math.nan, math.nan, 0)
    s = summarize([_scores(1.0), _scores(3.0), empty])
    assert s["cd"] == pytest.approx(2.0) and s["mhd"] == pytest.approx(4.0)
    assert s["fscore@0.2"] == pytest.approx(1.0 / 3.0)  # F-score is defined (0) for an empty cloud
    assert s["points"] == pytest.approx(20 / 3) and s["frames"] == 3 and s["empty_frames"] == 1


def test_agreement_and_margins():
    methods = [
        _Fake("R2", "r2ldm", "r2ldm", "onnxruntime"),
        _Fake("MS-onnx", "msdnet", "student", "onnxruntime"),
        _Fake("MS-torch", "msdnet", "student", "torch"),
    ]
    base = summarize([_scores(2.0, f=0.2)])
    summary = {
        "R2": base,
        "MS-onnx": summarize([_scores(1.0, f=0.4)]),
        "MS-torch": summarize([_scores(1.05, f=0.4)]),
    }
    (row,) = agreement(summary, methods)
    assert row["torch"] == "MS-torch" and not row["ok"]
    assert row["max_relative_difference"] == pytest.approx(1 - 1.0 / 1.05**2)  # cd_squared moves most
    summary["MS-torch"] = summarize([_scores(1.0 + 1e-4, f=0.4)])
    assert agreement(summary, methods)[0]["ok"]
    mg = margins(summary, methods)
    assert mg["msdnet"] == "MS-onnx" and mg["r2ldm"] == "R2"  # onnxruntime is the primary MSDNet
    assert mg["metrics"]["cd"]["percent"] == pytest.approx(-50.0) and mg["metrics"]["cd"]["met"]
    assert (
        mg["metrics"]["fscore@0.2"]["percent"] == pytest.approx(100.0) and mg["metrics"]["fscore@0.2"]["met"]
    )
    assert mg["metrics"]["jsd"]["met"] is None  # no bar for JSD
    assert margins(summary, methods[1:]) is None


def test_common_grid_and_names():
    lite = GRID_PRESETS["lite"]
    assert common_grid([RawRadar()], None) == lite and common_grid([RawRadar()], "tiny") == TINY
    assert common_grid([RawRadar(), _Fake("a", "msdnet", "student", "torch", TINY)]) == TINY
    with pytest.raises(MsdnetError, match="voxel grid differs"):
        common_grid(
            [_Fake("a", "msdnet", "student", "torch", TINY), _Fake("b", "r2ldm", "r2ldm", "torch", lite)]
        )
    with pytest.raises(MsdnetError, match="differs from the models"):
        common_grid([_Fake("a", "msdnet", "student", "torch", TINY)], "lite")
    assert parse_ablation(" w/o RGFD = runs/x ") == ("w/o RGFD", Path("runs/x"))
    for bad in ("no-equals", "=dir", "name="):
        with pytest.raises(MsdnetError, match="NAME=DIR"):
            parse_ablation(bad)


def test_build_methods_orders_and_disambiguates(tmp_path):
    student = make_artifact(tmp_path, "student", "astyx")
    r2ldm = make_artifact(tmp_path, "r2ldm", "astyx")
    other = copy_artifact(student, tmp_path / "other")
    methods = build_methods([student, r2ldm, other], [], [f"w/o DGFD={student}"], SETTINGS)
    names = [m.name for m in methods]
    assert names == [
        "4D radar",
        "R2LDM (onnxruntime)",
        f"MSDNet (onnxruntime, {student.name})",
        "MSDNet (onnxruntime, other)",
        "w/o DGFD",
    ]
    assert len({m.key for m in methods}) == len(methods)
    with pytest.raises(MsdnetError, match="two methods are named"):
        build_methods([student, student], [], [], SETTINGS)
    with pytest.raises(MsdnetError, match="no manifest.json"):
        build_methods([tmp_path], [], [], SETTINGS)


def test_raw_radar_scores_and_saved_clouds(astyx_root, tmp_path):
    ds = open_dataset("astyx", astyx_root, "val")
    fid = ds.frame_ids[0]
    run = evaluate_quality(ds, [fid], [RawRadar()], TINY, save=tmp_path, progress=False)
    frame = preprocess_frame(ds.get(fid), TINY)
    radar = crop_to_grid(frame.radar.xyz, TINY)
    expected = score_frame(radar, frame.lidar.xyz, xy_range(TINY))
    got = run.scores["4D radar"][0]
    assert got.num_points == len(radar) > 0 and got.cd == pytest.approx(expected.cd)
    assert got.fscore == pytest.approx(expected.fscore) and got.mmd == pytest.approx(expected.mmd)
    np.testing.assert_array_equal(np.load(tmp_path / "radar" / f"{fid}.npy"), radar)
    assert np.load(tmp_path / "lidar" / f"{fid}.npy").shape == (len(frame.lidar), 3)


def test_torch_and_onnx_metrics_agree_on_real_frames(astyx_root, astyx_pair):
    ckpt, onnx = astyx_pair
    ds = open_dataset("astyx", astyx_root, "val")
    ids = pick_frames(ds.frame_ids, 3)
    with one_torch_thread():
        methods = [PipelineMethod(onnx, SETTINGS), TorchMethod(ckpt, SETTINGS)]
        run = evaluate_quality(ds, ids, methods, TINY, progress=False)
    summary = {name: summarize(s) for name, s in run.scores.items()}
    (row,) = agreement(summary, methods)
    assert row["ok"], row
    assert summary["MSDNet (onnxruntime)"]["points"] > 500  # the prior makes the tiny model output points


def test_vod_frames_through_the_pipeline(vod_root, tmp_path):
    ds = open_dataset("vod", vod_root)
    methods = [RawRadar(), PipelineMethod(make_artifact(tmp_path, "student", "vod"), SETTINGS)]
    run = evaluate_quality(ds, ds.frame_ids, methods, TINY, picture_ids=(ds.frame_ids[0],), progress=False)
    s = {n: summarize(v) for n, v in run.scores.items()}
    assert s["4D radar"]["frames"] == 3 and math.isfinite(s["4D radar"]["cd"])
    assert s["MSDNet (onnxruntime)"]["points"] > 10 * s["4D radar"]["points"]
    assert set(run.pictures[ds.frame_ids[0]]) == {"4D radar", "MSDNet (onnxruntime)", "LiDAR"}


def test_picture_strip_and_strict_json(tmp_path):
    pts = np.random.default_rng(0).uniform([0, -6, -1], [12, 6, 3], size=(300, 3))
    png = picture_strip(
        tmp_path / "p.png", [("a", pts, "red"), ("b", pts[:10], "blue"), ("c", pts, "0.2")], TINY
    )
    from matplotlib.image import imread

    h, w = imread(png).shape[:2]
    assert w == 1200 and h == 460
    path = write_json(tmp_path / "r.json", {"x": math.nan, "y": np.float32(1.5), "z": (1, np.int64(2))})
    doc = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"non-strict JSON {c}"))
    assert doc == {"x": None, "y": 1.5, "z": [1, 2]}


def test_sequences_file_checks(tmp_path):
    with pytest.raises(MsdnetError, match="sequences.json"):
        read_sequences(tmp_path)
    (tmp_path / "sequences.json").write_text('{"sequences": [{"frame_ids": ["00000", 3]}]}')
    with pytest.raises(MsdnetError, match="frame_ids"):
        read_sequences(tmp_path)
    (tmp_path / "sequences.json").write_text(
        '{"sequences": [{"frame_ids": ["1", "2", "3"], "has_loop": true}]}'
    )
    (seq,) = read_sequences(tmp_path)
    assert seq.frame_ids == ("1", "2", "3") and seq.has_loop
    assert select_sequences([seq], None, 2)[0].frame_ids == ("1", "2")
    with pytest.raises(MsdnetError, match="no sequence 1"):
        select_sequences([seq], (1,), None)


def test_checkpoint_beside_its_export_uses_the_export_threshold(tmp_path):
    from msdnet.benchmarks.eval_methods import RunSettings, build_methods

    ckpt, art = make_exported_checkpoint(tmp_path, "vod", threshold=0.3)
    methods = build_methods([art], [ckpt], [], RunSettings(threads=1))
    assert {m.backend: m.threshold for m in methods if m.kind == "student"}["torch"] == 0.3
    methods = build_methods([art], [ckpt], [], RunSettings(threshold=0.4, threads=1))
    assert {m.threshold for m in methods if m.kind == "student"} == {0.4}
    alone = build_methods([], [ckpt], [], RunSettings(threads=1))
    assert alone[-1].threshold == 0.5  # the checkpoint's own config


def test_teacher_row_reads_the_lidar_and_keep_radar_row_adds_the_radar(astyx_root, tmp_path):
    """A teacher checkpoint is scored on the frame's LiDAR (the student's ceiling), at the MSDNet
    export's threshold; --keep-radar adds "MSDNet + radar points", the union with the input."""
    from export_helpers import make_checkpoint

    from msdnet.benchmarks.eval_methods import RunSettings, build_methods
    from msdnet.runtime.io.datasets import open_dataset

    art = make_artifact(tmp_path, "student", "astyx")
    teacher = make_checkpoint(tmp_path / "teacher", "teacher", "astyx")
    methods = build_methods([art], [teacher], [], RunSettings(threads=1), keep_radar=True)
    by_role = {m.role: m for m in methods}
    assert [m.role for m in methods] == ["radar", "msdnet", "ablation", "teacher"]
    assert by_role["teacher"].input == "lidar" and by_role["teacher"].name == "Teacher (LiDAR in) (torch)"
    assert by_role["teacher"].threshold == by_role["msdnet"].pipe.artifact.threshold
    grid = by_role["msdnet"].grid
    run = evaluate_quality(open_dataset("astyx", astyx_root), ["000000"], methods, grid, progress=False)
    plain, joined = (run.scores[m.name][0].num_points for m in methods[1:3])
    radar_in_grid = run.scores["4D radar"][0].num_points
    assert joined == plain + radar_in_grid
    assert run.scores[by_role["teacher"].name][0].num_points > 0  # it decoded from the LiDAR
