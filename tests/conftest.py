"""Shared fixtures: where the real research data lives (read in place, never copied), and a fresh
``--provider auto`` cache."""

from __future__ import annotations

import os

# onnxruntime telemetry off for every test and every process a test starts, before anything imports
# onnxruntime (msdnet.runtime sets the same; this covers tests that import onnxruntime directly).
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
os.environ.setdefault("ORT_TELEMETRY_DISABLED", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
VOD_ROOT = SHARED_DATA / "vod_example"
ASTYX_ROOT = SHARED_DATA / "astyx_hires2019"


@pytest.fixture(scope="session")
def vod_root() -> Path:
    if not VOD_ROOT.is_dir():
        pytest.skip(f"real VoD example data not found at {VOD_ROOT}")
    return VOD_ROOT


@pytest.fixture(scope="session")
def astyx_root() -> Path:
    if not ASTYX_ROOT.is_dir():
        pytest.skip(f"real Astyx data not found at {ASTYX_ROOT}")
    return ASTYX_ROOT


@pytest.fixture
def auto_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``--provider auto``'s cache file, fresh under XDG_CACHE_HOME, and no picks kept in memory."""
    from msdnet.runtime.engine import provider_auto

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(provider_auto, "_MEMO", {})
    return tmp_path / "xdg" / "msdnet" / "providers.json"
