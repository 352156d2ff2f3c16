"""The committed training checkpoints (``checkpoints/<model>/<stage>``): weights and
``checkpoint.json`` only, no path of a machine, hashes that hold, and ``msdnet-export`` from the
smallest shipped model's checkpoint reproduces its shipped graphs."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import onnx
import pytest
from click.testing import CliRunner
from onnx import numpy_helper

from msdnet.export.cli import main as export_main
from msdnet.training.recipe.checkpoint import read_meta

ROOT = Path(__file__).resolve().parents[1]
STAGES = sorted(p for p in (ROOT / "checkpoints").glob("*/*") if p.is_dir())
INDEX = ROOT / "checkpoints" / "README.md"
# Constants the exporter folds (the time embedding's frequencies, exp in float32, and the adapter's
# embedding of its start step, sin / cos of m times them) may differ in the last bits between CPUs'
# vectorised exp (m = 100 scales a frequency's ulp); weights may not differ at all.
CONSTANT_ATOL = 1e-5  # the folded values are sines, cosines and frequencies in [-1, 1]


def _strings(obj) -> list[str]:
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in _strings(v)]
    if isinstance(obj, list):
        return [s for v in obj for s in _strings(v)]
    return [obj] if isinstance(obj, str) else []


def test_there_are_committed_checkpoints():
    assert STAGES, "checkpoints/ holds no stage"


@pytest.mark.parametrize("stage", STAGES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_stage_is_weights_and_json_with_no_machine_path(stage):
    assert sorted(p.name for p in stage.iterdir()) == ["checkpoint.json", "model.safetensors"]
    _, meta = read_meta(stage)  # checks the format and the weights' sha256
    assert meta["training"] == {} and list(meta["files"]) == ["model.safetensors"]
    assert not [s for s in _strings(meta) if os.path.isabs(s)]


def _same_graph(ours: Path, shipped: Path) -> None:
    a, b = onnx.load(str(ours)), onnx.load(str(shipped))
    inits_a = {i.name: numpy_helper.to_array(i) for i in a.graph.initializer}
    inits_b = {i.name: numpy_helper.to_array(i) for i in b.graph.initializer}
    assert inits_a.keys() == inits_b.keys(), ours.name
    for name, value in inits_a.items():
        assert value.dtype == inits_b[name].dtype and value.tobytes() == inits_b[name].tobytes(), name
    assert [i.name for i in a.graph.input] == [i.name for i in b.graph.input]
    assert [o.name for o in a.graph.output] == [o.name for o in b.graph.output]
    assert len(a.graph.node) == len(b.graph.node), ours.name
    for x, y in zip(a.graph.node, b.graph.node, strict=True):
        assert (x.op_type, x.name, list(x.input), list(x.output)) == (
            y.op_type,
            y.name,
            list(y.input),
            list(y.output),
        )
        for p, q in zip(x.attribute, y.attribute, strict=True):
            assert p.name == q.name
            if p.type == onnx.AttributeProto.TENSOR:
                u, v = numpy_helper.to_array(p.t), numpy_helper.to_array(q.t)
                assert u.dtype == v.dtype and u.shape == v.shape, x.name
                if u.dtype == np.float32:
                    np.testing.assert_allclose(u, v, rtol=0, atol=CONSTANT_ATOL, err_msg=x.name)
                else:
                    assert u.tobytes() == v.tobytes(), x.name
            else:
                assert p == q, (x.name, p.name)


def test_export_from_the_smallest_models_checkpoint_reproduces_its_graphs(tmp_path):
    """sim-lite, the smallest shipped MSDNet model: every weight byte for byte, every node the same."""
    shipped = ROOT / "models" / "sim-lite"
    r = CliRunner().invoke(
        export_main, [str(ROOT / "checkpoints" / "sim-lite" / "student"), "--out", str(tmp_path / "x")]
    )
    assert r.exit_code == 0, r.output
    graphs = [g["file"] for g in json.loads((shipped / "manifest.json").read_text())["graphs"]]
    assert len(graphs) >= 4
    for name in graphs:
        _same_graph(tmp_path / "x" / name, shipped / name)


@pytest.mark.parametrize("stage", STAGES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_stage_is_in_the_index_with_its_hash(stage):
    digest = read_meta(stage)[1]["files"]["model.safetensors"]
    rows = [
        r
        for r in INDEX.read_text(encoding="utf-8").splitlines()
        if r.startswith(f"| `{stage.parent.name}/{stage.name}` |")
    ]
    assert len(rows) == 1 and rows[0].endswith(f"| `{digest}` |"), (stage, rows)


@pytest.mark.parametrize("card", sorted((ROOT / "models").glob("*/MODEL.md")), ids=lambda p: p.parent.name)
def test_a_cards_checkpoint_rows_hold(card):
    """Each row ``| stage | `checkpoints/M/S` | `sha256` |`` of a card names a committed stage."""
    rows = re.findall(
        r"^\| (\S+) \| `checkpoints/([^`]+)` \| `([0-9a-f]{64})` \|$", card.read_text(encoding="utf-8"), re.M
    )
    for _, folder, digest in rows:
        assert read_meta(ROOT / "checkpoints" / folder)[1]["files"]["model.safetensors"] == digest, folder
    assert rows or card.parent.name != "sim-lite"  # sim-lite ships from a committed stage
