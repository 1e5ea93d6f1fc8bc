"""Chaos: guided sessions through the device double with faults drawn at random per seed (the seed
is in the test id; tests/chaos_live.py draws and runs them). Each must end complete, or with a
one-line reason after which --resume completes it, with no finished standpoint lost and every
take's frame numbers adding up. A handful here (the suite's time); benchmarks/chaos_sessions.py
runs 200 and prints the figures."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from chaos_live import Chaos, run_session

SEEDS = (10, 12, 13, 26)


@pytest.mark.parametrize("seed", SEEDS, ids=[f"seed{s}" for s in SEEDS])
def test_a_chaotic_session_ends_complete_or_resumable(seed: int, tmp_path: Path) -> None:
    out = run_session(seed, tmp_path)
    assert not out.problems, f"seed {seed} ({out.chaos}): {out.problems}"
    if out.first_code != 0:
        assert out.resumed and out.reason is not None and "\n" not in out.reason
        assert "internal error" not in out.reason


def test_the_draws_cover_every_fault() -> None:
    """The 200 seeds of the benchmark draw every kind of fault (the harness itself is checked)."""
    kinds: set[str] = set()
    for seed in range(200):
        c = Chaos.draw(seed)
        kinds |= {k for k, _ in c.frame_faults.values()}
        flags = {"verdict": any(v != "ok" for v in c.verdicts), "creation_errors": c.enumerate_s > 0,
                 "disk_full": c.disk_budget is not None,
                 "unplug_in_calibration": c.calibration_unplug is not None}
        kinds |= {k for k, on in flags.items() if on}
    assert kinds == {"stall", "unplug", "unplug_resume", "drop", "slow", "verdict", "creation_errors",
                     "disk_full", "unplug_in_calibration"}
