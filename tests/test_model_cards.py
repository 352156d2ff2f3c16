"""One card per shipped model, ``models/*/MODEL.md``: Hugging Face-style front matter (licence,
datasets, metrics, tags, scores), a two-line quick start, data, recipe, scores, limits, citation,
and the graphs' hashes; every score equal to the ``results.json`` it comes from, every hash to the
manifest; ``docs/models.md`` an index that links each card."""

from __future__ import annotations

import json
import re

import pytest

from conftest import REPO

MODELS = REPO / "models"
RESULTS = REPO / "docs" / "results"
NAMES = sorted(p.parent.name for p in MODELS.glob("*/manifest.json"))
SECTIONS = ["Quick start", "Data", "Recipe", "Scores", "Limits", "Files", "Citation"]
LICENCES = {"astyx": "cc-by-nc-sa-4.0", "sim": "apache-2.0"}
# card -> (results file, path to the method's scores): where its front matter's scores come from
SOURCES = {
    "astyx-lite": ("quality-astyx-val/results.json", ["summary", "MSDNet (onnxruntime)"]),
    "astyx-lite-nodgfd": ("quality-astyx-val/results.json", ["summary", "w/o DGFD (astyx-lite-nodgfd)"]),
    "astyx-lite-r2ldm": ("quality-astyx-val-r2ldm/results.json", ["summary", "R2LDM (onnxruntime)"]),
    "sim-lite": ("steps-sim-eval/results.json", ["rows", 2]),  # T_m 4, the shipped one
    "sim-lite-r2ldm": ("quality-sim-eval/results.json", ["summary", "R2LDM (onnxruntime)"]),
}
METRIC_KEYS = {
    "CD (m)": "cd",
    "MHD (m)": "mhd",
    "F@0.2 m": "fscore@0.2",
    "F@0.5 m": "fscore@0.5",
    "JSD": "jsd",
}


def _card(name: str) -> str:
    return (MODELS / name / "MODEL.md").read_text(encoding="utf-8")


def _front_matter(name: str) -> dict:
    yaml = pytest.importorskip("yaml")
    match = re.match(r"^---\n(.*?)\n---\n", _card(name), flags=re.DOTALL)
    assert match, f"{name}: MODEL.md opens with no front matter"
    return yaml.safe_load(match.group(1))


def _source(name: str) -> dict:
    file, path = SOURCES[name]
    node = json.loads((RESULTS / file).read_text(encoding="utf-8"))
    for key in path:
        node = node[key]
    return node


def test_every_shipped_model_has_a_card_with_a_score_source():
    assert NAMES == sorted(SOURCES) and all((MODELS / n / "MODEL.md").is_file() for n in NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_front_matter(name: str):
    meta = _front_matter(name)
    assert meta["license"] == LICENCES[name.split("-")[0]]
    assert meta["library_name"] == "msdnet" and meta["tags"] and meta["datasets"] and meta["metrics"]
    (entry,) = meta["model-index"]
    assert entry["name"] == name
    (result,) = entry["results"]
    assert result["dataset"]["split"] == "validation"
    assert {m["name"] for m in result["metrics"]} == set(METRIC_KEYS)


@pytest.mark.parametrize("name", NAMES)
def test_front_matter_scores_equal_results_json(name: str):
    scores = _source(name)
    (entry,) = _front_matter(name)["model-index"]
    for metric in entry["results"][0]["metrics"]:
        expected = round(scores[METRIC_KEYS[metric["name"]]], 3)
        assert metric["value"] == expected, (name, metric["name"], metric["value"], expected)


@pytest.mark.parametrize("name", NAMES)
def test_sections_and_a_two_line_quick_start(name: str):
    text = _card(name)
    headings = re.findall(r"^## (.+)$", text, flags=re.MULTILINE)
    assert headings == SECTIONS, headings
    quick = text.split("## Quick start", 1)[1].split("## ", 1)[0]
    (block,) = re.findall(r"```bash\n(.*?)```", quick, flags=re.DOTALL)
    first, second = block.strip().splitlines()  # two lines: install, then run
    assert first.startswith("pip install") and "msdnet-infer" in second
    assert f"--model {name} " in second or name == "sim-lite"  # sim-lite is the default model
    assert "arXiv:" in text.split("## Citation", 1)[1]


def _stale_hashes(name: str, text: str) -> list[str]:
    """The manifest's graph rows that the card's text lacks (a changed hash or size)."""
    doc = json.loads((MODELS / name / "manifest.json").read_text(encoding="utf-8"))
    rows = [f"| `{g['file']}` | {g['bytes']:,} | `{g['sha256']}` |" for g in doc["graphs"]]
    return [row for row in rows if row not in text]


@pytest.mark.parametrize("name", NAMES)
def test_card_hashes_match_the_manifest(name: str):
    assert not _stale_hashes(name, _card(name)), f"models/{name}/MODEL.md: hashes or sizes out of date"


def test_hash_check_fails_on_a_changed_hash():
    text = _card("astyx-lite")
    sha = json.loads((MODELS / "astyx-lite" / "manifest.json").read_text(encoding="utf-8"))["graphs"][0][
        "sha256"
    ]
    assert len(_stale_hashes("astyx-lite", text.replace(sha, "0" * 64))) == 1


def test_models_page_is_an_index_of_the_cards():
    text = (REPO / "docs" / "models.md").read_text(encoding="utf-8")
    for name in NAMES:
        assert f"(../models/{name}/MODEL.md)" in text, name
    assert "| `encoder.onnx`" not in text  # the hash tables live in the cards
