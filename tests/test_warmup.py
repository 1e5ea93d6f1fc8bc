"""Warm-up rule: minimum time and settled temperature slope; time fallback; maximum time."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.acquire.warmup import WarmupSample, temperature_slope, warmup_decision
from depthstation.core.protocol import Warmup

RULE = Warmup(min_minutes=10.0, max_slope_c_per_min=0.1, window_minutes=2.0, max_minutes=40.0)


def heating(t_s: float, tau_s: float = 600.0) -> float:
    """First-order heating from 25 to 45 degrees C (what a D4xx projector roughly does)."""
    return 45.0 - 20.0 * np.exp(-t_s / tau_s)


def test_slope_of_a_line() -> None:
    t = np.arange(0, 300, 10.0)
    assert temperature_slope(t, 20 + 0.01 * t, 120.0) == pytest.approx(0.6)
    assert temperature_slope(t[:5], t[:5], 120.0) is None  # window not covered yet


def test_rule_waits_for_the_slope() -> None:
    samples: list[WarmupSample] = []
    end = None
    for t in np.arange(0, 3600, 10.0):
        samples.append(WarmupSample(float(t), {"asic": heating(t) - 3, "projector": heating(t)}))
        d = warmup_decision(samples, RULE)
        if d.done:
            end = t
            break
    assert end is not None
    # analytic: slope = 20/tau * exp(-t/tau) * 60 per min falls below 0.1 at t = tau ln(2 * 60 / 0.1 / tau)
    t_expected = 600.0 * np.log(20 * 60 / 600.0 / 0.1)
    # the windowed fit lags by about half the window
    assert end == pytest.approx(t_expected + 60.0, abs=30.0)
    assert "settled" in d.reason


def test_minimum_time_holds_even_when_cold_and_flat() -> None:
    samples = [WarmupSample(float(t), {"asic": 30.0}) for t in np.arange(0, 590, 10.0)]
    assert not warmup_decision(samples, RULE).done
    samples.append(WarmupSample(600.0, {"asic": 30.0}))
    assert warmup_decision(samples, RULE).done


def test_fallback_to_time_without_temperature() -> None:
    samples = [WarmupSample(float(t), {}) for t in np.arange(0, 600, 10.0)]
    d = warmup_decision(samples, RULE)
    assert not d.done and not d.has_temperature
    samples.append(WarmupSample(600.0, {}))
    d = warmup_decision(samples, RULE)
    assert d.done and "no temperature" in d.reason


def test_maximum_time_ends_a_drifting_camera() -> None:
    samples = [WarmupSample(float(t), {"asic": 20 + 0.01 * t}) for t in np.arange(0, 2400, 10.0)]
    assert not warmup_decision(samples, RULE).done
    samples.append(WarmupSample(2400.0, {"asic": 44.0}))
    d = warmup_decision(samples, RULE)
    assert d.done and "maximum" in d.reason
