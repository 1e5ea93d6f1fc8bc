"""Uncorrected radial distortion difference of the imagers: disparity error c r^2."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class DistortionResidual(DisparityShift):
    """d_meas = d + coeff_px * r^2, r = normalised radius ((u-ppx)^2 + (v-ppy)^2) / fx^2.

    The rectification leaves a radial residual; its bias -z^2 c r^2 / (f B) bends a plane into
    a bowl (c > 0: the image corners come out nearer). A residual of the lens model is an angle:
    `coeff_px` is in px of the 1280-wide mode, scaled by fx / fx_ref in the others.
    """

    name: ClassVar[str] = "distortion_residual"
    meaning: ClassVar[str] = "radial rectification residual: disparity error coeff * r^2 (px at 1280 wide)"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "coeff_px": (0.0, "px at 1280 wide", "disparity error at normalised radius 1 (45 deg off axis), "
                                             "px of the 1280-wide mode (x fx / fx_ref in others)"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        du = np.asarray(ctx.u, dtype=np.float64) - ctx.ppx
        dv = np.asarray(ctx.v, dtype=np.float64) - ctx.ppy
        return np.asarray(self.params["coeff_px"] * ctx.reference_scale * (du * du + dv * dv)
                          / (ctx.fx * ctx.fx))
