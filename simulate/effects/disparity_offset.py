"""A constant disparity offset: bias growing with z^2, what the D4xx tare calibration removes."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class DisparityOffset(DisparityShift):
    """d_meas = d + offset_px, so z_meas - z = -z^2 offset / (f B + z offset) (~ -z^2 offset / (f B)).

    A small error in the relative rotation of the two imagers about the vertical axis (or the
    principal points) shifts every disparity by the same amount; Intel's tare calibration
    estimates exactly this offset from a flat target at a known distance. The yaw is an angle, so
    `offset_px` is stated in px of the camera's 1280-wide mode and scaled by fx / fx_ref in the
    others (`PixelContext.reference_scale`): one unit gives one depth bias at every resolution.
    """

    name: ClassVar[str] = "disparity_offset"
    meaning: ClassVar[str] = ("constant disparity offset (px at 1280 wide, scaled with fx); depth bias "
                              "~ -z^2 offset / (f_1280 B)")
    source: ClassVar[str] = ("residual imager yaw after on-chip calibration, what tare fixes (Intel "
                             "'Self-calibration for D400 series')")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "offset_px": (0.0, "px at 1280 wide", "added to every disparity, in px of the 1280-wide mode "
                                                "(x fx / fx_ref in others; + = depth too near)"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        return np.asarray(self.params["offset_px"] * ctx.reference_scale)
