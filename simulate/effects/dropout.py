"""Missing depth: below min-z, at long range, at grazing angles, dark surfaces."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


def _one_minus_logistic(x: Any, x0: float, width: float) -> Array:
    """1 - 1 / (1 + exp(-u)) of u = (x - x0) / width clipped to +-60, in one float64 array."""
    x = np.asarray(x, dtype=np.float64)
    t = np.subtract(x, x0, out=np.empty(x.shape))
    np.divide(t, width, out=t)
    np.clip(t, -60, 60, out=t)
    np.negative(t, out=t)
    np.exp(t, out=t)
    t += 1.0
    np.divide(1.0, t, out=t)
    np.subtract(1.0, t, out=t)
    return t


def _times(a: Array, b: Array) -> Array:
    """a * b, into a where the product has a's shape (a is a fresh float64 array)."""
    if a.ndim and a.shape == np.broadcast_shapes(a.shape, np.shape(b)):
        return np.multiply(a, b, out=a)
    return np.asarray(a * b)


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

    def valid_probability(self, ctx: PixelContext) -> Array:
        # the same products as keep = keep * (1 - logistic(...)) ..., in place (a per-pose cost of
        # every simulated frame of a walk)
        p = self.params
        z = np.asarray(ctx.z_m, dtype=np.float64)
        inc = np.asarray(ctx.inclination_deg, dtype=np.float64)
        alb = np.asarray(ctx.albedo, dtype=np.float64)
        keep = np.asarray((ctx.disparity_px() <= p["max_disparity_px"]).astype(np.float64))
        keep = _times(keep, _one_minus_logistic(z, p["range_z50_m"], p["range_width_m"]))
        keep = _times(keep, _one_minus_logistic(inc, p["grazing_deg50"], p["grazing_width_deg"]))
        dark = np.clip(alb, 0, 1, out=np.empty(alb.shape))
        np.subtract(1, dark, out=dark)
        np.multiply(p["dark_probability"], dark, out=dark)
        np.subtract(1, dark, out=dark)
        keep = _times(keep, dark)
        if p["base_probability"] != 0:
            keep = keep * (1 - p["base_probability"])
        shape = ctx.shape()
        return keep if keep.shape == shape else np.broadcast_to(keep, shape).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        keep = self.cached(ctx, "keep", lambda: np.broadcast_to(
            self.valid_probability(ctx), z_m.shape).astype(np.float32))
        draw = rng.random(z_m.shape, dtype=np.float32)
        z_m[draw >= keep] = np.nan
        return z_m
