"""``--provider auto``'s head pick: the dense head where it is faster on its engine than the
coarse-to-fine head on its engine, timed in the engine picks' stream, and cached."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from export_helpers import make_artifact

from msdnet.export.manifest import write_manifest
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.providers import provider_cache, provider_head, provider_measure

pytest.importorskip("openvino")


@pytest.fixture(scope="module")
def gated(tmp_path_factory):
    """A tiny student whose manifest has a gate, so the pipeline runs the coarse-to-fine head."""
    folder = tmp_path_factory.mktemp("head") / "gated"
    shutil.copytree(make_artifact(tmp_path_factory.mktemp("art"), "student", head_kind="gated"), folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    write_manifest(folder, {**manifest, "gate": 0.48})
    return folder


def _scan(pipe: Pipeline) -> np.ndarray:
    return provider_measure.seeded_scan(pipe, np.random.default_rng(9), 300)


def _faster(monkeypatch, head: str) -> list:
    """Make ``head`` time at half the other's; -> the samples the pick was made from."""
    real, seen = provider_measure.measure, []

    def timing(pipe, runs, threads, deadline):
        samples = real(pipe, runs, threads, deadline)
        ms = {
            label: np.full(samples.scans, 1.0 if label[0] == provider_head.FILES[head] else 2.0)
            if label[0] in provider_head.FILES.values()
            else v
            for label, v in samples.ms.items()
        }
        seen.append(samples)
        return provider_measure.Samples(ms, samples.disagree, samples.failed, samples.scans)

    monkeypatch.setattr(provider_measure, "measure", timing)
    return seen


def test_the_dense_head_runs_where_it_is_faster(gated, auto_cache, monkeypatch):
    seen = _faster(monkeypatch, provider_head.DENSE)
    pipe = Pipeline.from_dir(gated, "auto", threads=1)
    pick = pipe.auto.head
    assert pick.head == "dense" and pick.ratio == 0.5 and not pick.cached and pipe.gate is None
    assert "head: dense" in "\n".join(pipe.auto.lines()) and pipe.auto.to_json()["head"]["head"] == "dense"
    # one stream for the engines and the heads: each head timed on its picked engine
    (samples,) = seen
    for f in provider_head.FILES.values():
        assert (f, pipe.auto.picks[f].engine) in samples.ms
    assert set(pick.ms) == {"dense", "coarse-to-fine"} and pick.reason.endswith("the reference, no gate")
    # the dense head decodes every half-scale voxel; the gated one those past the gate
    again = Pipeline.from_dir(gated, "auto", threads=1)  # the same process: the pick kept
    assert again.auto.head.cached and again.gate is None
    dense, gated_run = pipe(_scan(pipe)), Pipeline.from_dir(gated, "cpu", threads=1)(_scan(pipe))
    assert dense.stats["head_voxels"] == int(np.prod(pipe._occ[0, 0].shape)) > gated_run.stats["head_voxels"]


def test_a_missing_head_pick_times_only_the_heads(gated, auto_cache, monkeypatch):
    """Engine picks cached, head pick not: only both heads on their picked engines are timed."""
    Pipeline.from_dir(gated, "auto", threads=1)
    doc = json.loads(auto_cache.read_text())
    doc["entries"] = {k: v for k, v in doc["entries"].items() if not k.split(" | ")[1].startswith("head:")}
    auto_cache.write_text(json.dumps(doc))
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    runs = []
    real = provider_measure.measure

    def spy(pipe, todo, threads, deadline):
        runs.append(set(todo))
        return real(pipe, todo, threads, deadline)

    monkeypatch.setattr(provider_measure, "measure", spy)
    pipe = Pipeline.from_dir(gated, "auto", threads=1)
    assert runs == [{(f, pipe.auto.picks[f].engine) for f in provider_head.FILES.values()}]
    assert all(p.cached for p in pipe.auto.picks.values()) and not pipe.auto.head.cached


def test_the_coarse_to_fine_head_stays_where_it_is_faster(gated, auto_cache, monkeypatch):
    _faster(monkeypatch, provider_head.COARSE_TO_FINE)
    pipe = Pipeline.from_dir(gated, "auto", threads=1)
    assert pipe.auto.head.head == "coarse-to-fine" and pipe.gate == 0.48
    assert "the dense head must be 3% faster" in pipe.auto.head.reason


def test_the_pick_is_measured_once_and_keyed_by_both_heads_engines(gated, auto_cache, monkeypatch):
    pipe = Pipeline.from_dir(gated, "auto", threads=1)  # really timed
    pick = pipe.auto.head
    assert set(pick.ms) == {"dense", "coarse-to-fine"} and min(pick.ms.values()) > 0
    assert pick.head == ("dense" if pick.ratio <= 1 - provider_measure.MARGIN else "coarse-to-fine")
    assert (pipe.gate is None) == (pick.head == "dense")
    keys = [k for k in json.loads(auto_cache.read_text())["entries"] if k.split(" | ")[1].startswith("head:")]
    engines = {f: pipe.auto.picks[f].engine for f in provider_head.FILES.values()}
    assert len(keys) == 1 and all(f"on {e}" in keys[0] for e in engines.values())

    def no_timing(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(provider_measure, "measure", no_timing)
    monkeypatch.setattr(provider_cache, "_MEMO", {})  # a new process: only the file is left
    again = Pipeline.from_dir(gated, "auto", threads=1)
    assert again.auto.head.cached and again.auto.head.head == pick.head and again.gate == pipe.gate


def test_no_contest_without_a_gate_or_without_openvino(gated, auto_cache, monkeypatch):
    plain = Pipeline.from_dir(make_artifact(gated.parent, "student"), "auto", threads=1)
    assert plain.artifact.gate is None and plain.auto.head is None
    monkeypatch.setattr(provider_cache, "openvino_version", lambda: None)
    cpu_like = Pipeline.from_dir(gated, "auto", threads=1)
    assert cpu_like.auto.head is None and cpu_like.gate == 0.48
