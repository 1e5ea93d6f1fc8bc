"""Warm-up: stream until the device temperature settles (the thermal drift of depth dies down).

The rule is pure (`warmup_decision`): at least the protocol's minimum time, and the temperature
settled over the last window; where the camera reports no temperature it falls back to the minimum
time; the maximum time always ends it (with a warning in the summary).

A D4xx reports whole degrees (int8 in the firmware, librealsense `ds-options.cpp`). Over a window
in which the temperature moves by less than a degree, a least-squares slope of such readings
measures where the steps fall, not the slope (a single step gives anything from 0.04 to 0.3 C/min
over 5 min). For whole-degree readings the rule therefore bounds the slope instead: for a warm-up
that approaches its steady state monotonically with a slope that only shrinks (a first-order
model, or several time constants of one sign), the slope now is at most the mean slope between
the two ends of the window, and the readings' means at the ends are within one step of the true
means, so

    |slope now| <= (|mean(last sixth) - mean(first sixth)| + q + 3 (se_first + se_last)) / dt

with q the reading step (1 C), se the standard errors of the two means (noise) and dt the time
between the two ends' mean times. The window is stretched to at least 2 q / max_slope (40 min
for 0.05 C/min): a flat reading proves the bound only over more than q / max_slope, and the margin
lets noisy readings (flicker between two degrees) prove it too. Readings with
fractions (the simulator) keep the least-squares slope over the protocol's window.
The loop (`run_warmup`) takes its clock from the caller so a simulated camera can run it
accelerated.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from depthstation.core.device import CameraStalled
from depthstation.core.errors import CameraDisconnected
from depthstation.core.protocol import Warmup

# whole-degree readings: the window spans at least this many reading steps per max slope
QUANTISED_WINDOW_STEPS = 2.0
END_SHARE = 1.0 / 6.0  # each end of the window averaged for the bound
NOISE_Z = 3.0  # standard errors of each end's mean added to the bound


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
    resolution_c: float = 0.0  # step of the readings: 1.0 for whole degrees, 0.0 for fractions
    window_s: float | None = None  # the window the rule used (stretched for whole degrees)
    slope_bound_c_per_min: float | None = None  # upper bound on |slope now| (whole-degree readings)
    settled: bool = False  # the temperature rule held (not the maximum time, not the time rule alone)


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


def reading_resolution_c(temp_c: np.ndarray[Any, Any]) -> float:
    """1.0 when every reading is a whole number of degrees (a D4xx's int8), else 0.0 (fractions)."""
    y = np.asarray(temp_c, dtype=np.float64)
    return 1.0 if y.size >= 3 and bool(np.all(y == np.round(y))) else 0.0


def rule_window_s(rule: Warmup, resolution_c: float) -> float:
    """The protocol's window, stretched for stepped readings to 2 steps per max slope."""
    w = rule.window_minutes * 60.0
    if resolution_c > 0:
        w = max(w, QUANTISED_WINDOW_STEPS * resolution_c / rule.max_slope_c_per_min * 60.0)
    return w


def temperature_slope_bound(t_s: np.ndarray[Any, Any], temp_c: np.ndarray[Any, Any], window_s: float,
                            resolution_c: float) -> float | None:
    """Upper bound (degrees C per minute) on |slope now| from readings stepped by `resolution_c`
    (module docstring); None until the samples span the window."""
    t = np.asarray(t_s, dtype=np.float64)
    y = np.asarray(temp_c, dtype=np.float64)
    if t.size < 6 or t[-1] - t[0] < window_s:
        return None
    sel = t >= t[-1] - window_s
    t, y = t[sel], y[sel]
    end = END_SHARE * (t[-1] - t[0])
    a, b = t <= t[0] + end, t >= t[-1] - end
    if int(a.sum()) < 2 or int(b.sum()) < 2:
        return None
    dt = float(t[b].mean() - t[a].mean())
    se = sum(float(y[m].std(ddof=1)) / np.sqrt(int(m.sum())) for m in (a, b))
    rise = abs(float(y[b].mean() - y[a].mean()))
    return float((rise + resolution_c + NOISE_Z * se) / dt * 60.0)


def warmup_decision(samples: list[WarmupSample], rule: Warmup) -> WarmupDecision:
    """Whether warm-up is over, and why (the sentence the operator reads)."""
    if not samples:
        return WarmupDecision(False, "no sample yet", 0.0, None, False)
    elapsed = samples[-1].t_s  # sample times count from the start of the warm-up
    pts = [(s.t_s, s.temperature_c) for s in samples if s.temperature_c is not None]
    has_temp = len(pts) > 0
    slope = bound = None
    q = 0.0
    window_s = rule.window_minutes * 60.0
    if has_temp:
        arr = np.asarray(pts, dtype=np.float64)
        q = reading_resolution_c(arr[:, 1])
        window_s = rule_window_s(rule, q)
        slope = temperature_slope(arr[:, 0], arr[:, 1], window_s)
        if q > 0:
            bound = temperature_slope_bound(arr[:, 0], arr[:, 1], window_s, q)

    def decide(done: bool, why: str, settled: bool = False) -> WarmupDecision:
        return WarmupDecision(done, why, elapsed, slope, has_temp, q, window_s if has_temp else None, bound,
                              settled)

    min_s, max_s = rule.min_minutes * 60.0, rule.max_minutes * 60.0
    if elapsed >= max_s:
        why = (f"maximum time of {rule.max_minutes:g} min reached"
               + ("" if slope is None else f" (slope still {slope:+.3f} °C/min)"))
        return decide(True, why)
    if elapsed < min_s:
        return decide(False, f"minimum time: {elapsed / 60:.1f} of {rule.min_minutes:g} min")
    if not has_temp:
        return decide(True, f"minimum time of {rule.min_minutes:g} min reached "
                      "(camera reports no temperature: time rule only)")
    tol = rule.max_slope_c_per_min
    if q > 0:
        if bound is None:
            return decide(False, f"collecting the temperature window ({window_s / 60:g} min for "
                          f"{q:g} °C readings)")
        if bound <= tol:
            return decide(True, f"temperature settled: |slope| <= {bound:.3f} °C/min <= {tol:g} "
                          f"(bound from {q:g} °C readings over {window_s / 60:g} min)", settled=True)
        return decide(False, f"temperature drifting: |slope| up to {bound:.3f} °C/min > {tol:g} "
                      f"({q:g} °C readings over {window_s / 60:g} min)")
    if slope is None:
        return decide(False, "collecting the temperature window")
    if abs(slope) <= tol:
        return decide(True, f"temperature settled: slope {slope:+.3f} °C/min <= "
                      f"{tol:g} over {rule.window_minutes:g} min", settled=True)
    return decide(False, f"temperature drifting: slope {slope:+.3f} °C/min > {tol:g}")


MAX_WARMUP_FAULTS = 5  # stalls and unplugs one warm-up recovers from before it gives up


@dataclass
class WarmupResult:
    samples: list[WarmupSample] = field(default_factory=list)
    decision: WarmupDecision | None = None
    faults: list[dict[str, Any]] = field(default_factory=list)  # stalls / unplugs recovered from

    def summary(self) -> dict[str, Any]:
        """What goes into session.json: the rule's verdict and the whole curve."""
        d = self.decision
        return {
            "done": bool(d and d.done),
            "settled": bool(d and d.settled),
            "reason": None if d is None else d.reason,
            "elapsed_s": None if d is None else d.elapsed_s,
            "final_slope_c_per_min": None if d is None else d.slope_c_per_min,
            "has_temperature": bool(d and d.has_temperature),
            "resolution_c": None if d is None else d.resolution_c,
            "window_s": None if d is None else d.window_s,
            "final_slope_bound_c_per_min": None if d is None else d.slope_bound_c_per_min,
            "faults": list(self.faults),
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
               stop: Callable[[], bool] | None = None,
               recover: Callable[[CameraDisconnected], None] | None = None) -> WarmupResult:
    """Sample temperatures and the centre depth every `interval_s` until the rule says done.

    The camera keeps streaming (the load that heats it); `clock`/`sleep` are injectable so a
    simulated camera tied to the same clock warms up in seconds. A stall or an unplug is handed to
    `recover` (the capture's reset-and-retry) and the warm-up goes on, its clock running (the
    temperature rule judges the curve as it is); each is recorded in `faults`. Without `recover`,
    or after MAX_WARMUP_FAULTS, it ends the warm-up.
    """
    result = WarmupResult()
    t0 = clock()
    while True:
        try:
            frame = camera.wait_for_frames(5.0)
        except CameraDisconnected as exc:
            result.faults.append({"event": "stalled" if isinstance(exc, CameraStalled) else "disconnected",
                                  "t_s": clock() - t0, "error": str(exc)})
            if recover is None or len(result.faults) > MAX_WARMUP_FAULTS:
                raise
            recover(exc)
            continue
        temps = {k: float(v) for k, v in camera.temperatures().items() if v is not None and np.isfinite(v)}
        sample = WarmupSample(clock() - t0, temps, region_depth_m(frame.depth, depth_units_m))
        result.samples.append(sample)
        result.decision = warmup_decision(result.samples, rule)
        if on_sample is not None:
            on_sample(sample, result.decision)
        if result.decision.done or (stop is not None and stop()):
            return result
        sleep(interval_s)
