"""``--provider auto`` keeps to its wall-clock budget: slow graphs are timed on fewer scans or left
for a later load, and a clearly slower engine stops being timed. Slowness is injected (sleeps in
one engine's calls), so nothing here depends on how fast the machine is, beyond generous bounds."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from export_helpers import make_artifact

from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers import provider_auto, provider_budget, provider_cache, provider_measure

pytest.importorskip("openvino")
HEAD = onnx_spec.RECON_HEAD.file
GENEROUS_S = 20.0  # a bound on a whole measurement that no loaded test machine should reach


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_artifact(tmp_path_factory.mktemp("budget"), "student")


class _Slow:
    """A session whose every call first sleeps ``delay`` seconds; the rest is the session's."""

    def __init__(self, sess: Any, delay: float) -> None:
        self._sess, self._delay = sess, delay

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sess, name)

    def run(self, *a: Any, **k: Any) -> Any:
        time.sleep(self._delay)
        return self._sess.run(*a, **k)

    def run_with_iobinding(self, *a: Any, **k: Any) -> Any:
        time.sleep(self._delay)
        return self._sess.run_with_iobinding(*a, **k)


def _slow_openvino(monkeypatch: pytest.MonkeyPatch, delay: float) -> None:
    """Every OpenVINO call of this test sleeps ``delay`` first."""
    from msdnet.runtime.providers import openvino_session

    for name in ("run", "run_with_iobinding"):
        real = getattr(openvino_session.OpenVinoSession, name)

        def slow(self: Any, *a: Any, _real: Any = real, **k: Any) -> Any:
            time.sleep(delay)
            return _real(self, *a, **k)

        monkeypatch.setattr(openvino_session.OpenVinoSession, name, slow)


def _spy(monkeypatch: pytest.MonkeyPatch) -> list:
    real, seen = provider_measure.measure, []

    def spy(*a: Any) -> provider_measure.Samples:
        seen.append(real(*a))
        return seen[-1]

    monkeypatch.setattr(provider_measure, "measure", spy)
    return seen


def test_the_budget_rules():
    assert provider_budget.scan_floor(0.01) == provider_budget.MIN_TIMED_SCANS
    assert provider_budget.scan_floor(provider_budget.SLOW_SCAN_S * 2) == provider_budget.MIN_SLOW_SCANS
    now = time.perf_counter()
    assert provider_budget.defer(True, now + 1.0, 0.5, 0.5, 0.5)  # 1.5 s of work, 1 s left
    assert not provider_budget.defer(False, now + 1.0, 0.5, 0.5, 0.5)  # the cheapest: never
    assert not provider_budget.defer(True, now + 60.0, 0.5, 0.5, 0.5)
    ms = {("g", "onnxruntime"): [1.0, 1.0, 1.0], ("g", "openvino"): [2.0, 1.6, 3.0]}
    assert provider_budget.clearly_slower(ms, {}) == {("g", "openvino")}
    assert provider_budget.clearly_slower({k: v[:2] for k, v in ms.items()}, {}) == set()  # too few scans
    ms[("g", "openvino")][1] = 1.2  # not slower on every scan
    assert provider_budget.clearly_slower(ms, {}) == set()
    fast = {("g", "onnxruntime"): [3.0, 3.0, 3.0], ("g", "openvino"): [1.0, 1.0, 1.0]}
    assert provider_budget.clearly_slower(fast, {}) == {("g", "onnxruntime")}
    # onnxruntime is the pick wherever OpenVINO's outputs disagree: never stop timing it then
    assert provider_budget.clearly_slower(fast, {("g", "openvino"): "outputs differ"}) == set()


def test_a_slow_engine_is_timed_on_one_scan_within_the_budget(folder, auto_cache, monkeypatch):
    """OpenVINO's calls take 0.15 s each, so a scan of every engine is slow: the floor drops to
    ``MIN_SLOW_SCANS``, nothing is warmed up twice, and the slower engine is not picked."""
    _slow_openvino(monkeypatch, 0.15)
    monkeypatch.setattr(provider_measure, "BUDGET_S", 0.5)
    seen = _spy(monkeypatch)
    t0 = time.perf_counter()
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=lambda s: None)
    assert time.perf_counter() - t0 < GENEROUS_S
    (samples,) = seen
    assert pipe.auto.scans == samples.scans == provider_budget.MIN_SLOW_SCANS
    on_ov = [f for f in pipe.sessions if f != onnx_spec.RGFD_ADAPTER.file]
    for f in on_ov:
        pick = pipe.auto.picks[f]
        assert pick.engine == "onnxruntime" and pick.ratio > 1 and "median over 1 scans" in pick.reason
    assert f"over {provider_budget.MIN_SLOW_SCANS} scans" in pipe.auto.summary()


def test_a_clearly_slower_engine_stops_being_timed(folder, auto_cache, monkeypatch):
    """OpenVINO takes 0.04 s more a call: cheap scans, but a long stream that does not fit the
    budget, so after ``MIN_TIMED_SCANS`` scans the clearly slower engine stops and onnxruntime
    gets the rest."""
    _slow_openvino(monkeypatch, 0.04)
    monkeypatch.setattr(provider_measure, "STREAM_SCANS", 40)  # 40 x 0.2 s or more: past the budget
    monkeypatch.setattr(provider_measure, "BUDGET_S", 6.0)
    seen = _spy(monkeypatch)
    pipe = Pipeline.from_dir(folder, "auto", threads=1, notify=lambda s: None)
    (samples,) = seen
    n = provider_budget.MIN_TIMED_SCANS
    assert samples.scans > n  # the cheap scans after the stop
    for f in (f for f in pipe.sessions if f != onnx_spec.RGFD_ADAPTER.file):
        ov, ort_ = samples.ms[(f, "openvino")], samples.ms[(f, "onnxruntime")]
        assert len(ov) == n < len(ort_) == samples.scans
        pick = pipe.auto.picks[f]
        assert pick.engine == "onnxruntime" and f"median over {n} of {samples.scans} scans" in pick.reason
        assert np.all(ov > 0) and pick.ms["openvino"] > pick.ms["onnxruntime"]


def test_a_slow_graph_is_left_for_a_later_load(folder, auto_cache, monkeypatch):
    """The dense head's calls take 0.3 s on both engines and the budget is gone: its pick waits for
    a later load (onnxruntime meanwhile, not cached, said in the one line); the other graphs are
    measured and cached, and the next load measures only the head."""
    from msdnet.runtime.providers import openvino_session

    pipe = Pipeline.from_dir(folder, "cpu", threads=1)
    own, graph = pipe.sessions[HEAD], pipe.artifact.graphs[HEAD]
    real = openvino_session.OpenVinoSession

    def slow_head(model: bytes, *a: Any, **k: Any) -> Any:
        sess = real(model, *a, **k)
        return _Slow(sess, 0.3) if model == graph else sess

    monkeypatch.setattr(openvino_session, "OpenVinoSession", slow_head)
    monkeypatch.setattr(provider_measure, "BUDGET_S", 0.0)
    pipe.sessions[HEAD] = _Slow(own, 0.3)
    threads = {f: 1 for f in pipe.sessions}
    t0 = time.perf_counter()
    report = provider_auto.choose_engines(pipe, threads)
    assert time.perf_counter() - t0 < GENEROUS_S
    assert report.deferred == (HEAD,) and report.measured_s is not None
    head = report.picks[HEAD]
    assert head.engine == "onnxruntime" and "not measured within the 0 s budget" in head.reason
    assert f"{HEAD} left on onnxruntime for a later load" in report.summary()
    measured = [f for f in pipe.sessions if f not in (HEAD, onnx_spec.RGFD_ADAPTER.file)]
    assert all(report.picks[f].ms and not report.picks[f].cached for f in measured)
    assert report.to_json()["deferred"] == [HEAD]
    # a new process, the head as fast as the rest: only the head is measured, then cached
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    monkeypatch.setattr(openvino_session, "OpenVinoSession", real)
    monkeypatch.setattr(provider_measure, "BUDGET_S", 60.0)
    pipe.sessions[HEAD] = own
    seen = _spy(monkeypatch)
    again = provider_auto.choose_engines(pipe, threads)
    (samples,) = seen
    assert {f for f, _ in samples.ms} == {HEAD} and again.deferred == ()
    assert again.picks[HEAD].ms and not again.picks[HEAD].cached
    assert all(again.picks[f].cached for f in measured)
