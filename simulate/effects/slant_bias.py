"""Slant bias: a foreshortened window biases the match; disparity offset growing with tan^2(inclination)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class SlantBias(DisparityShift):
    """d_meas = d + offset_px_at_45 * tan^2(theta) (empirical; the second-order window term)."""

    name: ClassVar[str] = "slant_bias"
    meaning: ClassVar[str] = "disparity offset growing with tan^2 of the inclination"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "offset_px_at_45": (0.0, "px", "disparity offset at 45 degrees (+ = too near)"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        inc = np.radians(np.clip(np.asarray(ctx.inclination_deg, dtype=np.float64), 0.0, 89.0))
        return np.asarray(self.params["offset_px_at_45"] * np.tan(inc) ** 2)
