"""Warm-up: stream until the device temperature settles (the thermal drift of depth dies down).

The rule is pure (`warmup_decision`): at least the protocol's minimum time, and the temperature
slope over the last window below the threshold; where the camera reports no temperature it falls
back to the minimum time; the maximum time always ends it (with a warning in the summary).
The loop (`run_warmup`) takes its clock from the caller so a simulated camera can run it
accelerated.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from depthstation.core.protocol import Warmup


@dataclass(frozen=True)
class WarmupSample:
    """One point of the warm-up curve: time since start, temperatures and the depth of a fixed region."""

    t_s: float
    temperatures_c: dict[str, float]
    depth_m: float | None = None

    @property
    def temperature_c(self) -> float | None:
        """The temperature the rule follows: the projector's if reported (it heats most), else the ASIC's,
        else the first one reported."""
        for key in ("projector", "asic"):
            if key in self.temperatures_c:
                return self.temperatures_c[key]
        return next(iter(self.temperatures_c.values()), None)


@dataclass(frozen=True)
class WarmupDecision:
    done: bool
    reason: str
    elapsed_s: float
    slope_c_per_min: float | None
    has_temperature: bool


def temperature_slope(t_s: np.ndarray[Any, Any], temp_c: np.ndarray[Any, Any],
                      window_s: float) -> float | None:
    """Least-squares slope (degrees C per minute) over the last `window_s`; None until samples
    span the whole window, or while it holds fewer than 3 samples."""
    t = np.asarray(t_s, dtype=np.float64)
    y = np.asarray(temp_c, dtype=np.float64)
    if t.size < 3:
        return None
    if t[-1] - t[0] < window_s:
        return None  # the window is not covered yet
    sel = t >= t[-1] - window_s
    if int(sel.sum()) < 3:
        return None
    slope_per_s = float(np.polyfit(t[sel], y[sel], 1)[0])
    return slope_per_s * 60.0


def warmup_decision(samples: list[WarmupSample], rule: Warmup) -> WarmupDecision:
    """Whether warm-up is over, and why (the sentence the operator reads)."""
    if not samples:
        return WarmupDecision(False, "no sample yet", 0.0, None, False)
    elapsed = samples[-1].t_s  # sample times count from the start of the warm-up
    pts = [(s.t_s, s.temperature_c) for s in samples if s.temperature_c is not None]
    has_temp = len(pts) > 0
    slope = None
    if has_temp:
        arr = np.asarray(pts, dtype=np.float64)
        slope = temperature_slope(arr[:, 0], arr[:, 1], rule.window_minutes * 60.0)
    min_s, max_s = rule.min_minutes * 60.0, rule.max_minutes * 60.0
    if elapsed >= max_s:
        why = (f"maximum time of {rule.max_minutes:g} min reached"
               + ("" if slope is None else f" (slope still {slope:+.3f} °C/min)"))
        return WarmupDecision(True, why, elapsed, slope, has_temp)
    if elapsed < min_s:
        return WarmupDecision(False, f"minimum time: {elapsed / 60:.1f} of {rule.min_minutes:g} min",
                              elapsed, slope, has_temp)
    if not has_temp:
        return WarmupDecision(True, f"minimum time of {rule.min_minutes:g} min reached "
                              "(camera reports no temperature: time rule only)", elapsed, None, False)
    if slope is None:
        return WarmupDecision(False, "collecting the temperature window", elapsed, None, True)
    if abs(slope) <= rule.max_slope_c_per_min:
        return WarmupDecision(True, f"temperature settled: slope {slope:+.3f} °C/min <= "
                              f"{rule.max_slope_c_per_min:g} over {rule.window_minutes:g} min",
                              elapsed, slope, True)
    return WarmupDecision(False, f"temperature drifting: slope {slope:+.3f} °C/min > "
                          f"{rule.max_slope_c_per_min:g}", elapsed, slope, True)


@dataclass
class WarmupResult:
    samples: list[WarmupSample] = field(default_factory=list)
    decision: WarmupDecision | None = None

    def summary(self) -> dict[str, Any]:
        """What goes into session.json: the rule's verdict and the whole curve."""
        d = self.decision
        return {
            "done": bool(d and d.done),
            "reason": None if d is None else d.reason,
            "elapsed_s": None if d is None else d.elapsed_s,
            "final_slope_c_per_min": None if d is None else d.slope_c_per_min,
            "has_temperature": bool(d and d.has_temperature),
            "curve": [{"t_s": s.t_s, "depth_m": s.depth_m,
                       **{f"{k}_c": v for k, v in s.temperatures_c.items()}} for s in self.samples],
        }


def region_depth_m(depth: np.ndarray[Any, Any] | None, units_m: float, size: float = 0.1) -> float | None:
    """Median depth (m) of a central region (a share `size` of each side): the drift we watch."""
    if depth is None:
        return None
    h, w = depth.shape
    dh, dw = max(1, int(h * size / 2)), max(1, int(w * size / 2))
    roi = depth[h // 2 - dh:h // 2 + dh, w // 2 - dw:w // 2 + dw]
    vals = roi[roi > 0]
    return None if vals.size == 0 else float(np.median(vals)) * units_m


def run_warmup(camera: Any, rule: Warmup, depth_units_m: float, *, interval_s: float = 10.0,
               clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
               on_sample: Callable[[WarmupSample, WarmupDecision], None] | None = None,
               stop: Callable[[], bool] | None = None) -> WarmupResult:
    """Sample temperatures and the centre depth every `interval_s` until the rule says done.

    The camera keeps streaming (the load that heats it); `clock`/`sleep` are injectable so a
    simulated camera tied to the same clock warms up in seconds.
    """
    result = WarmupResult()
    t0 = clock()
    while True:
        frame = camera.wait_for_frames(5.0)
        temps = {k: float(v) for k, v in camera.temperatures().items() if v is not None and np.isfinite(v)}
        sample = WarmupSample(clock() - t0, temps, region_depth_m(frame.depth, depth_units_m))
        result.samples.append(sample)
        result.decision = warmup_decision(result.samples, rule)
        if on_sample is not None:
            on_sample(sample, result.decision)
        if result.decision.done or (stop is not None and stop()):
            return result
        sleep(interval_s)
