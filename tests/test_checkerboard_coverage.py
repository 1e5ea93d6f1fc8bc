"""Uncertainty that covers the truth: over random simulated standpoints (1-5 m, 0-60 deg, some
exactly head-on, the board anywhere in view), the truth of distance, inclination, noise and
accuracy lies within the reported U95 in at least 90 % of them (93 % at full size:
benchmarks/bench_uncertainty.py), and U95 is not inflated (median U95 within 2x the actual error
spread, 1.96 x RMS error)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_uncertainty import FIGURES, run, summarise


def test_u95_covers_the_truth_and_is_not_inflated() -> None:
    rows = run(30, 5, 640, 360, seed=3, head_on_share=0.2)
    assert sum(r["head_on"] for r in rows) >= 4
    summary = summarise(rows)
    for name in FIGURES:
        s = summary[name]
        assert s["standpoints"] >= 25, (name, s)
        assert s["coverage"] >= 0.9, (name, s)
        assert s["median_u95_over_spread"] <= 2.0, (name, s)
