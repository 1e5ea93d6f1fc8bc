"""Missing depth: below min-z, at long range, at grazing angles, dark surfaces."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numba import njit

from depthstation.simulate.effects.base import Array, Effect, PixelContext


@njit(inline="always")
def _minus_u(x: float, x0: float, w: float) -> float:  # pragma: no cover - compiled
    t = (x - x0) / w
    if t < -60.0:
        t = -60.0
    elif t > 60.0:
        t = 60.0
    return -t


@njit(cache=True, nogil=True)
def _exponents(z: Any, inc: Any, z50: float, zw: float, g50: float, gw: float, e1: Any,
               e2: Any) -> None:  # pragma: no cover - compiled
    """-u of u = (x - x50) / width clipped to +-60, for the range (z) and grazing (inc) roll-offs."""
    for i in range(e1.shape[0]):
        e1[i] = _minus_u(float(z[i]), z50, zw)
        e2[i] = _minus_u(float(inc[i]), g50, gw)


@njit(cache=True, nogil=True)
def _keep(z: Any, alb: Any, fb: float, max_d: float, dark_p: float, e1: Any, e2: Any,
          out: Any) -> None:  # pragma: no cover - compiled
    """keep = [fB / z <= max_d] (1 - 1 / (1 + e1)) (1 - 1 / (1 + e2)) (1 - p_dark (1 - clip(albedo)))
    with e = exp(-u), multiplied in that order."""
    for i in range(out.shape[0]):
        k = 1.0 if fb / float(z[i]) <= max_d else 0.0
        k = k * (1.0 - 1.0 / (e1[i] + 1.0))
        k = k * (1.0 - 1.0 / (e2[i] + 1.0))
        a = float(alb[i])
        if a < 0.0:
            a = 0.0
        elif a > 1.0:
            a = 1.0
        out[i] = k * (1.0 - dark_p * (1.0 - a))


class Dropout(Effect):
    """Pixels lose their depth value with a probability built from independent causes.

    - min-z: the matcher searches `max_disparity_px` (126 px on the D4xx) so d > that is lost
      (min-z = f B / 126, about 0.51 m at 1280x720 for the D455; Intel datasheet);
    - range: the projected pattern and the texture fade with z^2, the matcher's confidence drops
      below its threshold: logistic in z around `range_z50_m` with width `range_width_m`;
    - grazing: the window sees a foreshortened, stretched texture: logistic in inclination around
      `grazing_deg50`;
    - dark: little IR comes back from black print: probability `dark_probability` * (1 - albedo);
    - base: a residual `base_probability` everywhere.
    The sampler draws one uniform per pixel; the signature is the keep probability.
    """

    name: ClassVar[str] = "dropout"
    meaning: ClassVar[str] = "pixels without depth: min-z, range, grazing angle, dark surfaces"
    source: ClassVar[str] = ("D4 disparity search range 126 px (min-z), projector range, grazing "
                             "angles, dark print (Intel D400 datasheet)")
    stage: ClassVar[int] = 70
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "max_disparity_px": (126.0, "px", "disparity search range of the matcher (sets min-z)"),
        "range_z50_m": (6.5, "m", "z at which half the pixels are lost to range"),
        "range_width_m": (0.4, "m", "width of the range roll-off"),
        "grazing_deg50": (80.0, "deg", "inclination at which half the pixels are lost"),
        "grazing_width_deg": (2.5, "deg", "width of the grazing roll-off"),
        "dark_probability": (0.02, "1", "loss probability on a black (albedo 0) surface"),
        "base_probability": (0.0, "1", "loss probability everywhere"),
    }

    def validate(self) -> None:
        p = self.params
        if not (0 <= p["dark_probability"] <= 1 and 0 <= p["base_probability"] <= 1):
            raise ValueError("probabilities must lie in [0, 1]")
        if p["range_width_m"] <= 0 or p["grazing_width_deg"] <= 0:
            raise ValueError("widths must be positive")
        # metres and degrees: 6500 and 400 are millimetres, which switched range dropout off unsaid
        if not (0 < p["range_z50_m"] <= 100 and p["range_width_m"] <= 20):
            raise ValueError(f"range_z50_m (0 to 100) and range_width_m (at most 20) are metres, got "
                             f"{p['range_z50_m']:g} and {p['range_width_m']:g}")
        if not (0 < p["grazing_deg50"] <= 90 and p["grazing_width_deg"] <= 45):
            raise ValueError(f"grazing_deg50 (0 to 90) and grazing_width_deg (at most 45) are degrees, got "
                             f"{p['grazing_deg50']:g} and {p['grazing_width_deg']:g}")
        if not 0 < p["max_disparity_px"] <= 1024:
            raise ValueError(f"max_disparity_px must lie in (0, 1024], got {p['max_disparity_px']:g}")

    def valid_probability(self, ctx: PixelContext) -> Array:
        # keep = [d <= max_d] * (1 - logistic(range)) * (1 - logistic(grazing)) * (1 - p_dark (1 - albedo))
        # * (1 - p_base), logistic(u) = 1 / (1 + exp(-u)), u clipped to +-60, in float64. Compiled
        # passes with numpy's vectorised exp between them: a per-pose cost of every simulated frame.
        p = self.params
        z, inc, alb = np.broadcast_arrays(*map(np.asarray, (ctx.z_m, ctx.inclination_deg, ctx.albedo)))
        # float32 or float64 maps are read as they are (float64 arithmetic either way)
        flat = [np.ascontiguousarray(x if x.dtype.kind == "f" else x.astype(np.float64)).reshape(-1)
                for x in (z, inc, alb)]
        e1, e2, keep = np.empty(flat[0].size), np.empty(flat[0].size), np.empty(flat[0].size)
        _exponents(flat[0], flat[1], p["range_z50_m"], p["range_width_m"], p["grazing_deg50"],
                   p["grazing_width_deg"], e1, e2)
        np.exp(e1, out=e1)
        np.exp(e2, out=e2)
        _keep(flat[0], flat[2], float(ctx.focal_baseline), p["max_disparity_px"], p["dark_probability"],
              e1, e2, keep)
        out = keep.reshape(z.shape)
        if p["base_probability"] != 0:
            out = out * (1 - p["base_probability"])
        shape = ctx.shape()
        return out if out.shape == shape else np.broadcast_to(out, shape).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        keep = self.cached(ctx, "keep", lambda: np.broadcast_to(
            self.valid_probability(ctx), z_m.shape).astype(np.float32))
        draw = rng.random(z_m.shape, dtype=np.float32)
        z_m[draw >= keep] = np.nan
        return z_m
