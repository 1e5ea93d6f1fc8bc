"""Quantisation: the ASIC reports disparity in 1/32 px steps and depth in integer depth units."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class Quantization(Effect):
    """Disparity rounded to `disparity_step_px`, then z = f B / d rounded to `depth_unit_m`.

    Source: Intel D400 datasheet (subpixel resolution 1/32 px in the D4 ASIC; z16 depth with a
    depth unit of 1 mm by default). The analytic signature is the average over the fractional
    position (uniform rounding error): zero bias, variance step^2 / 12 in each domain.
    """

    name: ClassVar[str] = "quantization"
    meaning: ClassVar[str] = "disparity in 1/32 px steps and depth in 1 mm units"
    source: ClassVar[str] = ("D4 ASIC: 1/32 px subpixel disparity, z16 depth unit (Intel D400 "
                             "datasheet)")
    stage: ClassVar[int] = 40
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "disparity_step_px": (1.0 / 32.0, "px", "disparity resolution of the ASIC"),
        "depth_unit_m": (0.001, "m", "depth unit of the z16 output"),
    }

    def validate(self) -> None:
        if self.params["disparity_step_px"] < 0 or self.params["depth_unit_m"] < 0:
            raise ValueError("steps must be >= 0")

    def variance_m2(self, ctx: PixelContext) -> Array:
        z = np.asarray(ctx.z_m, dtype=np.float64)
        dz = z * z / ctx.focal_baseline * self.params["disparity_step_px"]
        u = self.params["depth_unit_m"]
        return np.asarray((dz * dz + u * u) / 12.0)

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        fb = np.float32(ctx.focal_baseline)
        step = self.params["disparity_step_px"]
        unit = self.params["depth_unit_m"]
        with np.errstate(divide="ignore", invalid="ignore"):
            if step > 0:
                d = fb / z_m
                d *= np.float32(1.0 / step)
                np.rint(d, out=d)
                d *= np.float32(step)
                d[~(d > 0)] = np.nan
                z_m = fb / d
            if unit > 0:
                z_m = z_m * np.float32(1.0 / unit)
                np.rint(z_m, out=z_m)
                z_m *= np.float32(unit)
        return z_m
