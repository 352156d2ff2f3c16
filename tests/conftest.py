"""Shared fixtures: where the real research data lives (read in place, never copied), and the
``--provider auto`` caches (one for the session, a fresh one per test that asks)."""

from __future__ import annotations

import os

# onnxruntime telemetry off for every test and every process a test starts, before anything imports
# onnxruntime (msdnet.runtime sets the same; this covers tests that import onnxruntime directly).
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
os.environ.setdefault("ORT_TELEMETRY_DISABLED", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from collections.abc import Iterator
from pathlib import Path

import pytest

from msdnet.runtime.providers import provider_measure as _provider_measure

REAL_STREAM_SCANS = _provider_measure.STREAM_SCANS  # before the session fixture lowers it

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
VOD_ROOT = SHARED_DATA / "vod_example"
ASTYX_ROOT = SHARED_DATA / "astyx_hires2019"


@pytest.fixture(scope="session")
def vod_root() -> Path:
    if not VOD_ROOT.is_dir():
        pytest.skip(f"real VoD example data not found at {VOD_ROOT}")
    return VOD_ROOT


@pytest.fixture(scope="module")
def student_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny random MSDNet student exported to a folder (``export_helpers.make_artifact``)."""
    from export_helpers import make_artifact

    return make_artifact(tmp_path_factory.mktemp("art"), "student")


@pytest.fixture(scope="module")
def scan(vod_root: Path):
    """One real VoD radar scan (frame 00549) as a PointCloud."""
    from msdnet.runtime import read_cloud

    return read_cloud(vod_root / "radar" / "training" / "velodyne" / "00549.bin")


@pytest.fixture(scope="session")
def astyx_root() -> Path:
    if not ASTYX_ROOT.is_dir():
        pytest.skip(f"real Astyx data not found at {ASTYX_ROOT}")
    return ASTYX_ROOT


TEST_STREAM_SCANS = 4  # --provider auto in tests: the warm-up scan and three timed ones


@pytest.fixture(scope="session", autouse=True)
def session_auto_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``--provider auto`` (the command-line default) in every test and every process a test starts:
    one cache for the session, never the user's, so each test model is measured once; in this
    process on ``TEST_STREAM_SCANS`` scans (the ``auto_cache`` fixture restores the real stream)."""
    from msdnet.runtime.providers import provider_measure

    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg-session"))
    scans, provider_measure.STREAM_SCANS = provider_measure.STREAM_SCANS, TEST_STREAM_SCANS
    yield Path(os.environ["XDG_CACHE_HOME"])
    provider_measure.STREAM_SCANS = scans
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@pytest.fixture
def auto_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``--provider auto``'s cache file, fresh under XDG_CACHE_HOME, no picks kept in memory, and
    the real stream of scans."""
    from msdnet.runtime.providers import provider_cache, provider_measure

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(provider_cache, "_MEMO", {})
    monkeypatch.setattr(provider_measure, "STREAM_SCANS", REAL_STREAM_SCANS)
    return tmp_path / "xdg" / "msdnet" / "providers.json"
