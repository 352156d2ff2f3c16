"""Pages that stand alone: no machine narration outside the results folders, nothing imported from
``tests/``, commands that write only into results folders that exist, and one label per table row
across the README, ``docs/*.md`` and the model cards (a row is recognised by its figures)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from test_docs import (
    CARDS,
    DOCS,
    MSD,
    MSD_ALL,
    MSD_ONE,
    MSD_OWN,
    NODGFD,
    PAGES,
    RADAR,
    REPO,
    RESULTS,
    VAL,
    _cell,
    _lines,
)

NARRATION = re.compile(
    r"load average|shared with|this machine|loaded machine|tried once|this checkout|other core busy"
    r"|otherwise idle|at this load",
    re.IGNORECASE,
)
NARRATION_PENDING: dict[str, str] = {}  # page name -> why its narration is still there


def _narration_cases() -> list:
    cases = []
    for page in PAGES + CARDS:
        pending = NARRATION_PENDING.get(page.name) if page.parent == DOCS else None
        marks = [pytest.mark.xfail(strict=True, reason=pending)] if pending else []
        cases.append(pytest.param(page, marks=marks, id=str(page.relative_to(REPO))))
    return cases


@pytest.mark.parametrize("page", _narration_cases())
def test_no_machine_narration_outside_results(page: Path):
    """Measured figures name their machine once, in their results folder; pages do not narrate it."""
    hits = [
        f"{no}: {line.strip()[:100]}" for no, line in enumerate(_lines(page), 1) if NARRATION.search(line)
    ]
    assert not hits, f"{page.relative_to(REPO)}:\n" + "\n".join(hits)


def test_narration_pattern():
    assert NARRATION.search("while other jobs kept its load average at 3") and NARRATION.search(
        "On this machine"
    )
    assert not NARRATION.search("the machine and its load are in results.md; a shared thread pool")


@pytest.mark.parametrize("page", PAGES + CARDS, ids=lambda p: str(p.relative_to(REPO)))
def test_pages_import_nothing_from_tests(page: Path):
    text = page.read_text(encoding="utf-8")
    assert "sys.path" not in text and not re.search(r"\b(from|import) test_\w+", text)


OUT_ARG = re.compile(r"--out\s+(\S+)")


@pytest.mark.parametrize("page", PAGES + CARDS, ids=lambda p: str(p.relative_to(REPO)))
def test_commands_write_into_results_folders_that_exist(page: Path):
    """A command on a page writes into docs/results/NAME only where NAME is a results folder."""
    bad = []
    for out in OUT_ARG.findall(page.read_text(encoding="utf-8")):
        out = out.strip("`'\"").rstrip("`'\":,.;)")
        if out.startswith("results/"):
            bad.append(f"{out}: the repository has no results/ folder (docs/results/, or your own)")
        elif out.startswith("docs/results/"):
            name = out.split("/")[2]
            if not (RESULTS / name).is_dir():
                bad.append(f"{out}: no results folder {name}")
    assert not bad, f"{page.relative_to(REPO)}:\n" + "\n".join(bad)


# ---- one label per table row across pages ---------------------------------------------------------
# Astyx validation methods of quality-astyx-val -> the one label every page gives their row. A row is
# recognised by its figures (CD, MHD and F@0.5, or hit@5, object CD and radar kept), whatever its label.
ROW_LABELS = {
    RADAR: "4D radar",
    "R2LDM (onnxruntime)": "R2LDM, improved (`astyx-lite-r2ldm`)",
    MSD: "MSDNet (`astyx-lite`)",
    "MSDNet + radar points (onnxruntime)": "MSDNet (`astyx-lite`), `--keep-radar`",
    MSD_ONE: "MSDNet, one threshold everywhere",
    MSD_OWN: "MSDNet, one threshold, no radar point kept",
    MSD_ALL: "MSDNet, one threshold, every radar point kept",
    NODGFD: "MSDNet, DGFD off (`astyx-lite-nodgfd`)",
    "w/o DGFD before the range thresholds": "MSDNet, DGFD off, one threshold everywhere",
}


def _row_signatures() -> dict[str, list[set[str]]]:
    """method -> the sets of cells that identify its row (scene figures; object figures), those
    that two methods share left out."""
    doc = json.loads((RESULTS / VAL / "results.json").read_text(encoding="utf-8"))
    out = {}
    for method in ROW_LABELS:
        scene = doc["summary"][method]
        objects = doc["objects"]["summary"][method]
        out[method] = [
            {f"{scene['cd']:.3f}", f"{scene['mhd']:.3f}", f"{scene['fscore@0.5']:.3f}"},
            {
                f"{objects['overall']['hit@5']:.3f}",
                f"{objects['overall']['object_cd']:.3f}",
                f"{objects['radar_kept']['share']:.3f}",
            },
        ]
    every = [frozenset(sig) for sigs in out.values() for sig in sigs]
    return {m: [sig for sig in sigs if every.count(frozenset(sig)) == 1] for m, sigs in out.items()}


def _table_rows(page: Path) -> list[list[str]]:
    return [
        [_cell(c) for c in line.strip().strip("|").split("|")]
        for line in _lines(page)
        if line.startswith("|") and not set(line) <= set("|-: ")
    ]


def test_one_label_per_table_row_across_pages():
    signatures, seen, bad = _row_signatures(), set(), []
    for page in PAGES + CARDS:
        for row in _table_rows(page):
            cells = set(row[1:])
            for method, sigs in signatures.items():
                if any(sig <= cells for sig in sigs):
                    seen.add(method)
                    if row[0] != ROW_LABELS[method]:
                        bad.append(f"{page.relative_to(REPO)}: {row[0]!r} is {ROW_LABELS[method]!r}")
    assert not bad, "\n".join(bad)
    assert seen == set(ROW_LABELS), set(ROW_LABELS) - seen  # every label is in use somewhere
