"""Model folders whose encoder is in the pair form (``msdnet-export --encoder-form pairs``): refresh
and ``msdnet-bench encoders`` read them as this msdnet's export, and a manifest whose
``encoder_form`` disagrees with ``encoder.onnx`` is refused naming the field."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402
from export_helpers import make_checkpoint, one_torch_thread  # noqa: E402

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.errors import MsdnetError  # noqa: E402
from msdnet.runtime.model.artifact import load_artifact  # noqa: E402


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """A tiny Astyx-column student exported in both encoder forms."""
    from msdnet.export.cli import export_model
    from msdnet.training.recipe.checkpoint import load_checkpoint

    root = tmp_path_factory.mktemp("forms")
    model, cfg, _ = load_checkpoint(make_checkpoint(root / "ckpt", "student", "astyx"))
    out = {}
    with one_torch_thread():
        for form in ("rulebook", "pairs"):
            export_model(model, "student", cfg, root / form, "runs/x/best", encoder_form=form)
            out[form] = root / form
    return out


def _edit(src: Path, dst: Path, **fields: object) -> Path:
    shutil.copytree(src, dst)
    manifest = json.loads((dst / "manifest.json").read_text())
    for key, value in fields.items():
        if value is None:
            manifest.pop(key, None)
        else:
            manifest[key] = value
    (dst / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return dst


def test_an_encoder_form_that_disagrees_with_the_graph_names_the_field(folders, tmp_path) -> None:
    assert load_artifact(folders["pairs"]).manifest["encoder_form"] == "pairs"
    no_field = _edit(folders["pairs"], tmp_path / "a", encoder_form=None)
    with pytest.raises(
        MsdnetError, match=r"manifest.json: no encoder_form \(the rulebook form\) disagrees"
    ) as err:
        load_artifact(no_field)
    assert 'must be "encoder_form": "pairs"' in str(err.value)
    wrong = _edit(folders["rulebook"], tmp_path / "b", encoder_form="pairs")
    with pytest.raises(
        MsdnetError, match="encoder_form 'pairs' disagrees with encoder.onnx, whose inputs are the rulebook"
    ):
        load_artifact(wrong)


def test_refresh_takes_a_pairs_form_folder_and_keeps_its_form(folders, tmp_path) -> None:
    from msdnet.export.refresh import refresh_model

    r = refresh_model(folders["pairs"], tmp_path / "refreshed")
    manifest = json.loads((tmp_path / "refreshed" / "manifest.json").read_text())
    assert manifest["encoder_form"] == "pairs" and r.points > 0
    assert "voxel_counts" in Pipeline.from_dir(tmp_path / "refreshed", threads=1).artifact.specs[0].inputs


def test_encoders_bench_reads_a_pairs_form_folder(folders, astyx_root) -> None:
    from msdnet.benchmarks.cli import main

    args = ["encoders", "--model", str(folders["pairs"]), "--data", str(astyx_root), "--frames", "1"]
    r = CliRunner().invoke(main, [*args, "--repeats", "1", "--threads", "1"])
    assert r.exit_code == 0 and "not this msdnet's export" not in r.output, r.output
    assert "pairs vs rulebook max rel difference" in r.output
