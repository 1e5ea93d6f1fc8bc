"""Albedo bias: dark print returns less IR; the match on black squares is offset in disparity."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class AlbedoBias(DisparityShift):
    """d_meas = d + offset_px_black * (1 - albedo): black squares appear at another depth than white."""

    name: ClassVar[str] = "albedo_bias"
    meaning: ClassVar[str] = "disparity offset on dark surfaces, proportional to 1 - albedo"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "offset_px_black": (0.0, "px", "disparity offset on a black surface (+ = too near)"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        a = np.clip(np.asarray(ctx.albedo, dtype=np.float64), 0.0, 1.0)
        return np.asarray(self.params["offset_px_black"] * (1.0 - a))
