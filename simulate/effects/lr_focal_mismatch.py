"""Left and right focal lengths differ: a disparity error proportional to (u - cx)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class LrFocalMismatch(DisparityShift):
    """With f_R = (1 + k) f_L the right image is magnified about cx: d_meas = d + k (u - ppx).

    The depth bias ~ -z^2 k (u - ppx) / (f B) changes sign across the image, so it averages out
    over a centred board but tilts the measured plane (the 'wedge').
    """

    name: ClassVar[str] = "lr_focal_mismatch"
    meaning: ClassVar[str] = "relative focal mismatch k of the imagers; disparity error k (u - cx)"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "ratio": (0.0, "1", "relative focal length difference (f_R - f_L) / f_L"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        return np.asarray(self.params["ratio"] * (np.asarray(ctx.u, dtype=np.float64) - ctx.ppx))
