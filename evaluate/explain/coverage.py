"""What explain's data covered: the board's valid depth, and the span of each fitted axis.

Valid depth, real against simulated: the dropout a model lacks.

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
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from depthstation.evaluate.explain.samples import Samples

if TYPE_CHECKING:
    from depthstation.evaluate.explain.discover import DiscoveredTerm

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
        n_r, n_s = frames_real.get(name, 0), frames_sim.get(name, 0)
        if min(n_r, n_s) < 2:   # no frame-to-frame spread: no standard error, no test
            continue
        se = math.hypot(_se(r, n_r), _se(s, n_s))
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
            f"{100 * t.sim:.1f} % (+-{200 * t.se:.1f} points at 95 %; board at {t.distance_m:.2f} m, "
            f"{t.inclination_deg:.0f} deg); explain fits no dropout and no bias or noise test sees "
            "missing pixels: set the model's dropout effect (docs/simulator.md)")


# A discovered field along an image axis fitted on less than this share of the image: model.toml
# applies it over the whole image, where it extrapolates (an audit's row stripe, fitted on boards
# near the centre, became +0.56 px at the image's top where the truth was 0, without a word).
MIN_IMAGE_SHARE = 0.6


def fit_domain(s: Samples) -> dict[str, list[float]]:
    """The span (0.5th to 99.5th percentile) of each axis the compared pixels covered: what every
    fitted term is known over (explain.json `fit_domain`)."""
    x, y = (s.u - s.ppx) / s.fx, (s.v - s.ppy) / s.fx
    axes = {"u_imager_px": s.u, "v_imager_px": s.v, "radius": np.hypot(x, y), "distance_m": s.z_ref_m,
            "inclination_deg": s.inclination_deg, "time_s": s.time_s, "temperature_c": s.temperature_c}
    out = {}
    for name, values in axes.items():
        finite = values[np.isfinite(values)]
        if finite.size:
            lo, hi = np.percentile(finite, [0.5, 99.5])
            out[name] = [float(lo), float(hi)]
    return out


def image_share(dom: Mapping[str, list[float]], s: Samples, axis: str) -> tuple[float, float, float] | None:
    """(low, high, share of the image) the data covered along an image axis (u, v in the stereo
    imager's px, where disparity lives; radius normalised) from `fit_domain(s)`; None for an axis
    that is not one of the image's."""
    width, height = 2 * s.ppx + 1, 2 * s.ppy + 1
    if axis == "u" and "u_imager_px" in dom:
        lo, hi = dom["u_imager_px"]
        return lo, hi, (hi - lo) / width
    if axis == "v" and "v_imager_px" in dom:
        lo, hi = dom["v_imager_px"]
        return lo, hi, (hi - lo) / height
    if axis == "radius" and "radius" in dom:
        lo, hi = dom["radius"]
        return lo, hi, hi / (math.hypot(s.ppx, s.ppy) / s.fx)
    return None


def extrapolation_messages(terms: Sequence[DiscoveredTerm], s: Samples) -> list[str]:
    """What a discovered image-axis field covered and that model.toml applies it beyond."""
    out: list[str] = []
    dom = fit_domain(s) if terms else {}   # once: percentiles over every sample
    for t in terms:
        # a tile field is a smooth 2-D field over the image: it extrapolates along u and v alike
        for axis in [a for ax in t.axes for a in (("u", "v") if ax == "tile" else (ax,))]:
            span = image_share(dom, s, axis)
            if span is None or span[2] >= MIN_IMAGE_SHARE:
                continue
            lo, hi, share = span
            where = (f"imager rows {lo:.0f}-{hi:.0f}" if axis == "v"
                     else f"imager columns {lo:.0f}-{hi:.0f}" if axis == "u"
                     else f"normalised radii up to {hi:.2f}")
            out.append(f"the discovered {t.effect} was fitted on {where} ({100 * share:.0f} % of the image "
                       f"along {axis}); model.toml applies it over the whole image, where it extrapolates. "
                       "Over a narrow band a constant and a field along the axis are hard to tell apart, so "
                       "the terms selected beside it share what it describes: capture standpoints that put "
                       "the board across the image before trusting either")
    return out
