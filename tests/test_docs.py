"""The front page, the docs and the model cards (``models/*/MODEL.md``): short, present-tense,
linked only inside the repository, and every headline figure equal to the ``results.json`` it comes
from, the counts of every picture too (the README's caption, the quality strips, the demo).
``tests/test_docs_pages.py`` checks the pages' narration, commands and row labels.

"cycle" is matched as a whole word (``cycle``, ``cycles``), so names such as ``cyclonedds`` or
``lifecycle`` pass; issue references are ``issue 12``, ``issues 12``, ``issue #12`` and ``#12``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from conftest import REPO

README = REPO / "README.md"
DOCS = REPO / "docs"
RESULTS = DOCS / "results"
PAGES = [README, *sorted(DOCS.glob("*.md"))]
CARDS = sorted((REPO / "models").glob("*/MODEL.md"))  # the shipped models' cards

HISTORY = [
    re.compile(r"\bcycles?\b", re.IGNORECASE),
    re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE),
    re.compile(r"(?<![\w&/])#\d+\b"),
]
ORDINALS = (
    "first second third fourth fifth sixth seventh eighth ninth tenth eleventh twelfth thirteenth "
    "fourteenth fifteenth sixteenth seventeenth eighteenth nineteenth twentieth"
).split()
ORDINAL = re.compile(r"(?:^|[-_])(?:" + "|".join(ORDINALS) + r"|\d+(?:st|nd|rd|th))(?:$|[-_])", re.IGNORECASE)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def test_page_lengths():
    assert len(_lines(README)) <= 300
    assert len(_lines(DOCS / "training.md")) <= 600
    assert len(_lines(DOCS / "experiments.md")) <= 400


@pytest.mark.parametrize("page", PAGES + CARDS, ids=lambda p: str(p.relative_to(REPO)))
def test_no_history_in_pages(page: Path):
    hits = [
        f"{page.relative_to(REPO)}:{no}: {line.strip()[:100]}"
        for no, line in enumerate(_lines(page), 1)
        if any(p.search(line) for p in HISTORY)
    ]
    assert not hits, "pages describe the present (history goes to CHANGELOG.md):\n" + "\n".join(hits)


def test_every_model_card_is_checked_for_history():
    assert len(CARDS) == 5, [str(p.relative_to(REPO)) for p in CARDS]


def test_history_patterns_are_whole_words():
    assert HISTORY[0].search("the fifth cycle") and HISTORY[0].search("Cycles")
    assert not any(p.search("cyclonedds, a bicycle lane, the node's lifecycle") for p in HISTORY)
    assert HISTORY[1].search("issue 23") and HISTORY[2].search("see #12")
    assert not any(p.search("quality.md#pictures, colour #9ecae1") for p in HISTORY)


def test_no_code_under_docs():
    assert not [str(p.relative_to(REPO)) for p in DOCS.rglob("*.py")]


def test_no_results_folder_named_by_an_ordinal():
    bad = [str(p.relative_to(REPO)) for p in RESULTS.rglob("*") if p.is_dir() and ORDINAL.search(p.name)]
    assert not bad, bad
    assert ORDINAL.search("latency-thirteenth") and ORDINAL.search("quality-astyx-val-ninth-v1")
    assert not ORDINAL.search("latency-paper-width") and not ORDINAL.search("quality-astyx-val")


def test_every_results_folder_says_how_it_was_made():
    missing = [
        p.name
        for p in sorted(RESULTS.iterdir())
        if p.is_dir() and not (p / "command.txt").is_file() and not (p / "results.md").is_file()
    ]
    assert not missing, missing


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lstrip("#").strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    out, fenced = set(), False
    for line in _lines(path):
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            out.add(_slug(line))
    return out


def _bad_links(page: Path, text: str) -> list[str]:
    """Links of a page that leave the repository (a URL, a path outside it) or do not resolve."""
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)  # code blocks hold commands, not links
    bad = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z+.-]*:", target):  # http:, https:, mailto:
            bad.append(f"{target}: leaves the repository (cite it in the text instead)")
            continue
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if dest != REPO and REPO not in dest.parents:
            bad.append(f"{target}: outside the repository")
        elif not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target}: no heading #{anchor}")
    return bad


@pytest.mark.parametrize("page", PAGES + CARDS, ids=lambda p: str(p.relative_to(REPO)))
def test_links_stay_inside_the_repository_and_resolve(page: Path):
    bad = _bad_links(page, page.read_text(encoding="utf-8"))
    assert not bad, f"{page.name}:\n" + "\n".join(bad)


def test_link_check_catches_outside_links():
    text = "[a](../shared/papers/MSDNet.md) [b](https://arxiv.org/abs/1) [c](docs/models.md) [d](nope.md)"
    bad = _bad_links(README, text)
    assert len(bad) == 3 and "outside" in bad[0] and "leaves" in bad[1] and "no such file" in bad[2]


# ---- headline figures: README cell -> results.json -------------------------------------------------
# (section heading, row's first cell, column header) -> (text template, [(results folder file, key path)])


def _q(folder: str, method: str, metric: str):
    return (f"{folder}/results.json", ["summary", method, metric])


def _lat(run: str, *path):
    return (f"latency-{run}/results.json", list(path))


VAL, R2, PUB = "quality-astyx-val", "quality-astyx-val-r2ldm", "quality-astyx-val-r2ldm-published"
RADAR = "4D radar"
MSD = "MSDNet (onnxruntime)"  # the shipped astyx-lite, with its manifest's keep rule
MSD_ONE = "astyx-lite before the range thresholds"  # the same model at one threshold, keep rule on
MSD_OWN = "astyx-lite with neither rule"  # the same model's decoded points alone, one threshold
MSD_ALL = "astyx-lite with neither rule, every radar point kept"  # ... plus every radar point
NODGFD = "w/o DGFD (astyx-lite-nodgfd)"  # the shipped astyx-lite-nodgfd, with its keep rule
QUALITY_COLUMNS = {
    "frames": ("{:.0f}", "evaluation.frames"),
    "CD (m) ↓": ("{:.3f}", "cd"),
    "MHD (m) ↓": ("{:.3f}", "mhd"),
    "F@0.2 m ↑": ("{:.3f}", "fscore@0.2"),
    "F@0.5 m ↑": ("{:.3f}", "fscore@0.5"),
    "JSD ↓": ("{:.3f}", "jsd"),
    "points / frame": ("{:,.0f}", "points"),
}
QUALITY_ROWS = {
    "4D radar": (VAL, RADAR),
    "R2LDM, improved (`astyx-lite-r2ldm`)": (R2, "R2LDM (onnxruntime)"),
    "MSDNet (`astyx-lite`)": (VAL, MSD),
    "MSDNet, one threshold everywhere": (VAL, MSD_ONE),
    "MSDNet, one threshold, no radar point kept": (VAL, MSD_OWN),
    "MSDNet, one threshold, every radar point kept": (VAL, MSD_ALL),
    "4D radar, every 4th frame": (PUB, RADAR),
    "R2LDM as published (its authors' code, narrower U-Net)": (PUB, "R2LDM as published (onnxruntime)"),
}


def _quality_figures() -> dict:
    out = {}
    for row, (folder, method) in QUALITY_ROWS.items():
        for column, (fmt, metric) in QUALITY_COLUMNS.items():
            if metric == "evaluation.frames":
                source = (f"{folder}/results.json", ["evaluation", "frames"])
            else:
                source = _q(folder, method, metric)
            out[("Quality on Astyx validation", row, column)] = (fmt, [source])
    return out


OBJECT_COLUMNS = {
    "hit@5 ↑": ("{:.3f}", ["overall", "hit@5"]),
    "object CD (m) ↓": ("{:.3f}", ["overall", "object_cd"]),
    "points / object (LiDAR 215.9)": ("{:.1f}", ["overall", "points"]),
    "radar kept ↑": ("{:.3f}", ["radar_kept", "share"]),
}
OBJECT_ROWS = {
    "4D radar": RADAR,
    "R2LDM, improved (`astyx-lite-r2ldm`)": "R2LDM (onnxruntime)",
    "MSDNet (`astyx-lite`)": MSD,
    "MSDNet, one threshold, no radar point kept": MSD_OWN,
}


def _object_figures() -> dict:
    out = {}
    for row, method in OBJECT_ROWS.items():
        for column, (fmt, path) in OBJECT_COLUMNS.items():
            source = (f"{VAL}/results.json", ["objects", "summary", method, *path])
            out[("Quality on Astyx validation", row, column)] = (fmt, [source])
    return out


STREAM = ("stream", "stages_ms", "total", "median")
OURS = ("peers", "totals", "onnxruntime", "median_ms")
RATIO = ("ratios", "engine_over_best_peer")
LATENCY_ROWS = {
    # row's "size: model, provider" cell -> (run folder, best peer's label, its key in peers.totals)
    "lite: `astyx-lite`, `auto-bf16`": ("lite/auto-bf16-3", "OpenVINO", "openvino"),
    "lite: `astyx-lite`, `auto`": ("lite/auto-3", "OpenVINO", "openvino"),
    "paper: random weights, T_m 10, `auto-bf16`": ("paper/auto-bf16", "OpenVINO bf16", "openvino_bf16"),
    "paper-width: random weights (20.1 M), T_m 4, `auto-bf16`": (
        "paper-width/auto-bf16",
        "OpenVINO bf16",
        "openvino_bf16",
    ),
}


def _latency_figures() -> dict:
    out = {}
    for row, (run, peer, key) in LATENCY_ROWS.items():
        figures = {
            "ms / frame": ("{:.1f}", [_lat(run, *STREAM)]),
            "ours, graph stages (ms)": ("{:.1f}", [_lat(run, *OURS)]),
            "best peer (ms)": (peer + " {:.1f}", [_lat(run, "peers", "totals", key, "median_ms")]),
            "ours / best peer": ("{:.3f}", [_lat(run, *RATIO)]),
        }
        for column, value in figures.items():
            out[("Latency", row, column)] = value
    return out


LIVE_FILES = {"PointCloud2": "live/live.json", "RadarScan": "live/live-radar_scan.json"}
REPEAT_PROSE = {  # the repeat run's highest rates, named in the README's prose
    "the repeat gave {:.1f} Hz (PointCloud2)": [
        ("live/repeat/live.json", ["max_rate", "max_hz_without_drops"])
    ],
    "and {:.1f} Hz (RadarScan)": [("live/repeat/live-radar_scan.json", ["max_rate", "max_hz_without_drops"])],
}


def _live_figures() -> dict:
    out = {}
    for column, file in LIVE_FILES.items():
        out[("Live node", "highest rate without a drop (Hz)", column)] = (
            "{:.1f}",
            [(file, ["max_rate", "max_hz_without_drops"])],
        )
        out[("Live node", "at 10 Hz: end-to-end p50 / p99 (ms)", column)] = (
            "{:.1f} / {:.1f}",
            [(file, ["rates", 0, "end_to_end_ms", "p50"]), (file, ["rates", 0, "end_to_end_ms", "p99"])],
        )
        out[("Live node", "40 Hz storm: memory growth after warm-up (%)", column)] = (
            "{:.2f}",
            [(file, ["storm", "rss_growth_pct"])],
        )
    return out


def _card(name: str) -> str:
    """The README's first cell of a shipped model: its name linking its card."""
    return f"[`{name}`](models/{name}/MODEL.md)"


LITE_TIME = [_lat("lite/cpu", *STREAM), _lat("lite/cpu", "threads")]
R2LDM_TIME = [
    _lat("r2ldm/improved", "r2ldm_stages_ms", "total", "median"),
    _lat("r2ldm/improved", "threads"),
    _lat("r2ldm/improved", "r2ldm_stages_ms", "total", "n"),
]
SIM_TIME = [("steps-sim-eval/results.json", ["rows", 2, "ms"]), ("steps-sim-eval/results.json", ["threads"])]

FIGURES = {
    **_quality_figures(),
    **_object_figures(),
    **_latency_figures(),
    **_live_figures(),
    ("Shipped models", _card("astyx-lite"), "CD (m) / F@0.5"): (
        "{:.3f} / {:.3f}",
        [_q(VAL, MSD, "cd"), _q(VAL, MSD, "fscore@0.5")],
    ),
    ("Shipped models", _card("astyx-lite-nodgfd"), "CD (m) / F@0.5"): (
        "{:.3f} / {:.3f}",
        [_q(VAL, NODGFD, "cd"), _q(VAL, NODGFD, "fscore@0.5")],
    ),
    ("Shipped models", _card("astyx-lite-r2ldm"), "CD (m) / F@0.5"): (
        "{:.3f} / {:.3f}",
        [_q(R2, "R2LDM (onnxruntime)", "cd"), _q(R2, "R2LDM (onnxruntime)", "fscore@0.5")],
    ),
    ("Shipped models", _card("sim-lite") + " (default)", "CD (m) / F@0.5"): (
        "{:.3f} / {:.3f}",
        [
            ("steps-sim-eval/results.json", ["rows", 2, "cd"]),
            ("steps-sim-eval/results.json", ["rows", 2, "fscore@0.5"]),
        ],
    ),
    ("Shipped models", _card("sim-lite-r2ldm"), "CD (m) / F@0.5"): (
        "{:.3f} / {:.3f}",
        [
            _q("quality-sim-eval", "R2LDM (onnxruntime)", "cd"),
            _q("quality-sim-eval", "R2LDM (onnxruntime)", "fscore@0.5"),
        ],
    ),
    # each time with the threads (and frames) of its run: the column mixes runs, so it says their basis
    ("Shipped models", _card("astyx-lite"), "ms / frame"): ("{:.1f} ({} threads)", LITE_TIME),
    ("Shipped models", _card("astyx-lite-r2ldm"), "ms / frame"): (
        "{:,.0f} ({} threads, {} frame)",
        R2LDM_TIME,
    ),
    ("Shipped models", _card("sim-lite") + " (default)", "ms / frame"): ("{:.1f} ({} thread)", SIM_TIME),
}
# figures in the README's prose: template -> sources
PROSE = {
    **REPEAT_PROSE,
    "points / object (LiDAR {:.1f})": [
        (f"{VAL}/results.json", ["objects", "summary", RADAR, "overall", "lidar_points"])
    ],
    "the {:.0f} labelled objects": [
        (f"{VAL}/results.json", ["objects", "summary", RADAR, "overall", "objects"])
    ],
    "whole frame takes {:.3f} of the same model's unoptimised graphs": [
        _lat("paper-width/auto", "ratios", "total_over_old_graphs")
    ],
    "takes {:,.0f} ms a frame, the as-published": [
        _lat("r2ldm/improved", "r2ldm_stages_ms", "total", "median")
    ],
    "R2LDM {:,.0f} ms": [_lat("r2ldm/published", "r2ldm_stages_ms", "total", "median")],
}
# checks of the table parser's input: the README's steps-sim-eval row 2 must be T_m 4, the shipped one
STEPS_ROW_T_M = 4


def _value(source: tuple[str, list]):
    file, path = source
    node = json.loads((RESULTS / file).read_text(encoding="utf-8"))
    for key in path:
        node = node[key]
    return node


def _expected(fmt: str, sources: list) -> str:
    return fmt.format(*(_value(s) for s in sources))


def _cell(text: str) -> str:
    return text.strip().replace("**", "")


def _readme_tables(text: str | None = None) -> dict:
    """{(section heading, first cell, column header): cell} for every table of the README."""
    cells, section, header = {}, "", None
    lines = _lines(README) if text is None else text.splitlines()
    for line in lines:
        if line.startswith("#"):
            section, header = line.lstrip("#").strip(), None
        elif line.startswith("|"):
            row = [_cell(c) for c in line.strip().strip("|").split("|")]
            if header is None:
                header = row
            elif not set("".join(row)) <= set("-: "):
                for column, value in zip(header[1:], row[1:], strict=True):
                    cells[(section, row[0], column)] = value
        else:
            header = None
    return cells


def test_steps_row_is_the_shipped_t_m():
    assert _value(("steps-sim-eval/results.json", ["rows", 2, "steps"])) == STEPS_ROW_T_M
    assert (
        json.loads((REPO / "models" / "sim-lite" / "manifest.json").read_text())["diffusion"]["sample_steps"]
        == 4
    )


@pytest.mark.parametrize("key", sorted(FIGURES), ids=lambda k: " | ".join(k))
def test_readme_figure_matches_results_json(key):
    cells = _readme_tables()
    assert key in cells, f"README has no cell {key}"
    fmt, sources = FIGURES[key]
    assert cells[key] == _expected(fmt, sources), (
        f"{key}: README {cells[key]!r}, results.json {_expected(fmt, sources)!r}"
    )


@pytest.mark.parametrize("template", sorted(PROSE))
def test_readme_prose_figure_matches_results_json(template):
    text = " ".join(README.read_text(encoding="utf-8").split())
    expected = template.format(*(_value(s) for s in PROSE[template]))
    assert expected in text, f"README lacks {expected!r}"


def test_every_headline_cell_is_checked():
    """Each figure column of the results tables is in FIGURES, so no figure there goes unchecked."""
    cells = _readme_tables()
    checked = set(FIGURES)
    figure_columns = {
        "Quality on Astyx validation": set(QUALITY_COLUMNS),
        "Latency": {"ms / frame", "ours, graph stages (ms)", "best peer (ms)", "ours / best peer"},
        "Live node": {"value"},
    }
    unchecked = [
        key
        for key, value in cells.items()
        if key[0] in figure_columns and key[2] in figure_columns[key[0]] and key not in checked
    ]
    assert not unchecked, unchecked
    assert {k[0] for k in cells} >= set(figure_columns), "a results table left the README"


def test_figure_check_fails_on_a_changed_figure():
    key = ("Quality on Astyx validation", "MSDNet (`astyx-lite`)", "CD (m) ↓")
    fmt, sources = FIGURES[key]
    text = README.read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| **MSDNet (`astyx-lite`)**"))
    edited = text.replace(row, row.replace(_expected(fmt, sources), "0.799", 1))
    assert _readme_tables(text)[key] == _expected(fmt, sources)
    assert _readme_tables(edited)[key] != _expected(fmt, sources)


# ---- pictures: the counts in a picture equal those of the JSON beside it ---------------------------
# Each picture keeps its legend's counts in a PNG text chunk (runtime.io.pictures.read_counts).


def _picture_counts(png: Path) -> dict[str, int]:
    from msdnet.runtime.io.pictures import read_counts

    return read_counts(png)


QUALITY_PICTURES = sorted(RESULTS.glob("*/pictures/*.png"))
# results folders whose pictures were drawn before a picture kept its counts (their panel titles
# give them); a new run of their command adds the counts and leaves this set
PICTURES_WITHOUT_COUNTS = {
    "quality-astyx-val-r2ldm",
    "quality-astyx-val-r2ldm-published",
    "quality-sim-eval",
    "quality-sim-eval-r2ldm-published",
}
DEMO_PICTURES = sorted(RESULTS.glob("demo/bev-*.png"))


@pytest.mark.parametrize("png", QUALITY_PICTURES, ids=lambda p: str(p.relative_to(RESULTS)))
def test_quality_picture_counts_equal_results_json(png: Path):
    doc = json.loads((png.parent.parent / "results.json").read_text(encoding="utf-8"))
    counts = _picture_counts(png)
    if not counts:  # drawn before pictures kept their counts: only in the folders named here
        assert png.parent.parent.name in PICTURES_WITHOUT_COUNTS, f"{png} keeps no counts"
        return
    methods = [m for m in counts if m in doc["per_frame"]]
    assert methods and set(counts) - set(methods) == {"LiDAR"}, counts
    for method in methods:
        row = next(r for r in doc["per_frame"][method] if r["frame"] == png.stem)
        assert counts[method] == row["points"], (png.name, method, counts[method], row["points"])


@pytest.mark.parametrize("png", DEMO_PICTURES, ids=lambda p: str(p.relative_to(RESULTS)))
def test_demo_picture_legend_equals_comparison_json(png: Path):
    doc = json.loads((png.parent / "comparison.json").read_text(encoding="utf-8"))
    row = next(r for r in doc["frames"] if r["frame"] == png.stem.removeprefix("bev-"))
    counts = _picture_counts(png)
    expected = {
        "LiDAR": row["lidar_points"],
        "MSDNet output": row["dense_points"],
        "radar": row["radar_points"],
    }
    assert counts == expected


def test_pictures_are_checked():
    assert len(QUALITY_PICTURES) >= 3 and DEMO_PICTURES


README_PICTURE = re.compile(r"^!\[[^\]]*\]\((docs/results/[^)]+\.png)\)$", re.MULTILINE)


def test_readme_picture_caption_equals_its_counts():
    """The README's picture is a results folder's; its caption's counts are the picture's counts."""
    text = README.read_text(encoding="utf-8")
    (path,) = README_PICTURE.findall(text)
    caption = " ".join(text.split(path, 1)[1].split("\n\n")[1].split())
    counts = _picture_counts(REPO / path)
    assert counts, path
    for label, n in counts.items():
        assert f"({n:,})" in caption or f"({n:,} points)" in caption, (label, n, caption)


def test_readme_time_basis_is_said():
    """The time column mixes runs, so each cell says its threads; the basis is the JSON's."""
    assert _value(_lat("lite/cpu", "provider")) == _value(_lat("r2ldm/improved", "provider")) == "cpu"
    assert _value(("steps-sim-eval/results.json", ["provider"])) == "cpu"
    assert "Time: a frame's median with `--provider cpu`, at the threads given." in " ".join(
        README.read_text(encoding="utf-8").split()
    )
