"""Subpixel matching noise: zero-mean Gaussian disparity noise, Intel's RMS_z = z^2 s / (f B)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from simulate.effects.base import (
    Array,
    Effect,
    PixelContext,
    second_order_bias_from_disparity_variance,
    shift_depth,
)


class DisparityNoise(Effect):
    """The stereo matcher finds the disparity to within `sigma_px` (Intel's 'subpixel RMS').

    Source: Intel, 'Tuning depth cameras for best performance' (RMS error = z^2 * subpixel /
    (f * B), subpixel about 0.08 px for the D4xx with a textured target).
    """

    name: ClassVar[str] = "disparity_noise"
    meaning: ClassVar[str] = "zero-mean Gaussian disparity noise of the subpixel matcher"
    stage: ClassVar[int] = 20
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px": (0.08, "px", "RMS of the disparity estimate (Intel's subpixel RMS)"),
    }

    def validate(self) -> None:
        if self.params["sigma_px"] < 0:
            raise ValueError("sigma_px must be >= 0")

    def bias_m(self, ctx: PixelContext) -> Array:
        s = self.params["sigma_px"]
        return second_order_bias_from_disparity_variance(ctx, s * s)

    def variance_m2(self, ctx: PixelContext) -> Array:
        # z = fB/(d+n): Var = z^2 (s^2 + 8 s^4) with s = sigma/d (series to 4th order)
        z = np.asarray(ctx.z_m, dtype=np.float64)
        s = self.params["sigma_px"] / ctx.disparity_px()
        return np.asarray(z * z * (s * s + 8 * s**4))

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        sigma = np.float32(self.params["sigma_px"])
        noise: Any = rng.standard_normal(z_m.shape, dtype=np.float32)
        noise *= sigma
        return shift_depth(ctx, z_m, noise)
