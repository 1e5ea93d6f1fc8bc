"""Valid depth on the board, real against simulated: the dropout a model lacks.

The samples of every bias and noise test are pixels *with* depth, so those tests are blind to the
pixels that lost theirs: a camera dropping 15 % of a 30 deg board, where the model drops none,
went through explain without a word. Here each standpoint's fill rate (board pixels with depth /
board pixels, the mean over its frames) is compared, real against simulated. A gap is reported
when it is both significant (4 standard errors of the frame-to-frame spread, which keeps a
session's few standpoints from needing a multiplicity correction) and material (2 points: below
that, the board's edge handling and the mask's margin move the rate). Explain does not fit dropout:
it says where, so that the model's `dropout` effect can be set.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

Z_SIGNIFICANT = 4.0
MIN_GAP = 0.02


@dataclass(frozen=True)
class FillTest:
    """One standpoint's fill rates, real and simulated, and whether they differ."""

    standpoint: str
    real: float
    sim: float
    diff: float
    se: float
    distance_m: float
    inclination_deg: float
    significant: bool

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def fill_tests(real: Mapping[str, Mapping[str, float]], sim: Mapping[str, Mapping[str, float]],
               frames_real: Mapping[str, int], frames_sim: Mapping[str, int]) -> list[FillTest]:
    """Per standpoint both sides evaluated: fill rate real - sim, its standard error from each side's
    frame-to-frame spread, and the verdict."""
    out = []
    for name, r in real.items():
        s = sim.get(name)
        if s is None:
            continue
        fr, fs = float(r.get("fill_rate", math.nan)), float(s.get("fill_rate", math.nan))
        if not (math.isfinite(fr) and math.isfinite(fs)):
            continue
        se = math.hypot(_se(r, frames_real.get(name, 0)), _se(s, frames_sim.get(name, 0)))
        diff = fr - fs
        out.append(FillTest(name, fr, fs, diff, se, float(r.get("distance_m", math.nan)),
                            float(r.get("inclination_deg", math.nan)),
                            abs(diff) > max(Z_SIGNIFICANT * se, MIN_GAP)))
    return out


def _se(fig: Mapping[str, float], frames: int) -> float:
    std = float(fig.get("fill_rate_std", math.nan))
    if frames < 2 or not math.isfinite(std):
        return 0.0
    return std / math.sqrt(frames)


def fill_message(t: FillTest) -> str:
    """The warning of one standpoint whose real depth covers the board differently."""
    what = "loses depth the simulation keeps" if t.diff < 0 else "keeps depth the simulation loses"
    return (f"the real camera {what}: {100 * t.real:.1f} % of the board has depth, the simulation's "
            f"{100 * t.sim:.1f} % (+-{200 * t.se:.1f} points; board at {t.distance_m:.2f} m, "
            f"{t.inclination_deg:.0f} deg); explain fits no dropout and no bias or noise test sees "
            "missing pixels: set the model's dropout effect (docs/simulator.md)")
