"""bench/soak.py: its summaries, and a short run of the whole soak (emulator + skinmapd)."""
from __future__ import annotations

import importlib
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def soak():
    sys.path.insert(0, str(BENCH))
    try:
        yield importlib.import_module("soak")
    finally:
        sys.path.remove(str(BENCH))


def test_growth_is_the_fitted_slope_per_hour(soak):
    t = np.arange(0.0, 600.0, 1.0)
    assert soak.growth_mb_per_hour(t, 100.0 + t * (2.0 / 3600.0)) == pytest.approx(2.0)
    assert soak.growth_mb_per_hour(t, np.full(t.size, 50.0)) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(soak.growth_mb_per_hour([1.0], [5.0]))


def test_latency_drift_compares_first_and_last_tenth(soak):
    t = np.linspace(0.0, 100.0, 1001)
    latency = np.where(t < 50.0, 5.0, 20.0)
    drift = soak.latency_drift(t, latency)
    assert drift["first"]["median_ms"] == 5.0 and drift["last"]["median_ms"] == 20.0
    assert drift["first"]["n"] == drift["last"]["n"] == 101
    with pytest.raises(ValueError, match="share"):
        soak.latency_drift(t, latency, share=0.9)


def test_sequence_gaps_count_missing_scans_across_wraparound(soak):
    assert soak.sequence_gaps(np.array([1, 2, 3])) == 0
    assert soak.sequence_gaps(np.array([1, 4, 5, 9])) == 2 + 3
    assert soak.sequence_gaps(np.array([2**32 - 2, 2**32 - 1, 0, 2])) == 1
    assert soak.sequence_gaps(np.array([7])) == 0


@pytest.mark.slow
def test_short_soak_reports_every_figure_and_clean_files(tmp_path):
    out = tmp_path / "soak.json"
    proc = subprocess.run(
        [sys.executable, str(BENCH / "soak.py"), "--seconds", "6", "--progress-every", "3",
         "--workdir", str(tmp_path / "work"), "--json", str(out)],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "t+" in proc.stdout  # progress lines
    r = json.loads(out.read_text())
    assert r["ok"] and r["problems"] == []
    assert r["messages"] > 50 and r["daemon_exit_code"] == 0
    assert 0 < r["rss_start_mb"] <= r["rss_max_mb"] and r["rss_end_mb"] <= r["rss_max_mb"]
    assert all(isinstance(r["status"][k], int)
               for k in ("frames_dropped", "scans_lost", "scans_dropped_queue", "log_dropped"))
    assert r["latency"]["first"]["n"] > 0 and r["latency"]["last"]["n"] > 0
    assert r["files"] and all(f["readable"] and f["finished"] for f in r["files"])
    assert sum(f["counts"].get("/raw", 0) for f in r["files"]) > 50
    assert r["replay"]["identical"] and r["replay"]["compared"] > 0
