"""Pixel locking: the subpixel interpolation pulls disparities towards integers."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class PixelLocking(DisparityShift):
    """d_meas = d - A sin(2 pi d): a parabola fit of the matching cost is biased towards integers.

    Source: Shimizu and Okutomi (2001), 'Precise sub-pixel estimation on area-based matching'.
    The depth bias oscillates along z with one period per pixel of disparity.
    """

    name: ClassVar[str] = "pixel_locking"
    meaning: ClassVar[str] = "subpixel estimate pulled towards integer disparities"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "amplitude_px": (0.0, "px", "peak disparity error of the pull towards integers"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        return np.asarray(-self.params["amplitude_px"] * np.sin(2 * np.pi * ctx.disparity_px()))
