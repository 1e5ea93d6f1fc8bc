"""The warm-up rule on whole-degree readings: how late it says "settled", and never too early.

480 simulated first-order warm-ups (time constants 3-60 min, rises of 6-20 C, sensor noise 0-0.3 C,
rounded or truncated to whole degrees as a D4xx's int8, a reading every 10 s, tolerance
0.05 C/min) through the rule's bound; then two typical curves against the old 5-min least-squares
rule (minimum 60 min). The figures quoted in docs/acquisition.md come from here.

Run: .venv/bin/python benchmarks/bench_warmup_rule.py
"""

from __future__ import annotations

import numpy as np

from depthstation.acquire.warmup import rule_window_s, temperature_slope, temperature_slope_bound
from depthstation.core.protocol import Warmup


def first_settled(t: np.ndarray, y: np.ndarray, rule: Warmup, start_s: float, old: bool) -> int | None:
    """Index of the first sample where the rule (the bound, or the old 5-min slope) says settled."""
    tol, win = rule.max_slope_c_per_min, rule_window_s(rule, 1.0)
    for i in range(30, t.size):
        if t[i] < start_s:
            continue
        if old:
            s = temperature_slope(t[:i + 1], y[:i + 1], 300.0)
            if s is not None and abs(s) <= tol:
                return i
        else:
            b = temperature_slope_bound(t[:i + 1], y[:i + 1], win, 1.0)
            if b is not None and b <= tol:
                return i
    return None


def main() -> None:
    rule = Warmup(min_minutes=5.0, max_slope_c_per_min=0.05, window_minutes=5.0, max_minutes=240.0)
    tol = rule.max_slope_c_per_min
    t = np.arange(0.0, rule.max_minutes * 60.0 + 1.0, 10.0)
    ratios, lags, early, unsettled, n = [], [], 0, 0, 0
    for tau_min in np.geomspace(3.0, 60.0, 10):
        for amp in (6.0, 12.0, 20.0):
            for sigma in (0.0, 0.1, 0.2, 0.3):
                for seed in range(4):
                    rng = np.random.default_rng([int(tau_min * 100), int(amp), int(sigma * 100), seed])
                    tau = 60.0 * tau_min
                    true = 20.0 + 10.0 * rng.random() + amp * (1.0 - np.exp(-t / tau))
                    slope = amp / tau * np.exp(-t / tau) * 60.0
                    quantise = np.round if seed % 2 == 0 else np.trunc
                    y = quantise(true + sigma * rng.standard_normal(t.size))
                    n += 1
                    i = first_settled(t, y, rule, 0.0, old=False)
                    if i is None:
                        unsettled += 1
                        continue
                    early += int(slope[i] > tol)
                    ratios.append(slope[i] / tol)
                    lags.append((t[i] - t[np.argmax(slope <= tol)]) / 60.0)
    print(f"{n} warm-ups: settled too early {early}, never settled {unsettled}")
    print(f"true slope / tolerance when settled: max {max(ratios):.2f}, "
          f"95 % {np.percentile(ratios, 95):.2f}, median {np.median(ratios):.2f}")
    print(f"minutes after the true slope fell below the tolerance: median {np.median(lags):.0f}, "
          f"5-95 % {np.percentile(lags, 5):.0f}-{np.percentile(lags, 95):.0f}")
    t = np.arange(0.0, 180 * 60.0 + 1.0, 10.0)
    for tau_min, amp in ((12, 17), (20, 17), (30, 20), (40, 20)):
        tau = 60.0 * tau_min
        y = np.round(25.0 + amp * (1.0 - np.exp(-t / tau)))
        slope = amp / tau * np.exp(-t / tau) * 60.0
        old, new = (first_settled(t, y, rule, 3600.0, o) for o in (True, False))

        def at(i: int | None, slope: np.ndarray = slope) -> str:
            return "never" if i is None else f"{t[i] / 60:.0f} min (true slope {slope[i]:.4f})"
        below = t[np.argmax(slope <= tol)] / 60.0
        print(f"tau {tau_min} min, +{amp} C: true slope <= {tol} from {below:.0f} min; "
              f"old rule {at(old)}; new rule {at(new)}")


if __name__ == "__main__":
    main()
