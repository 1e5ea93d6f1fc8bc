"""A depth scale error: baseline or focal length of the calibration off by a ratio; bias proportional to z."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class DepthScale(Effect):
    """z_meas = (1 + scale_error) z: the device triangulates with f_cal B_cal = (1 + e) f B."""

    name: ClassVar[str] = "depth_scale"
    meaning: ClassVar[str] = "depth scaled by (1 + scale_error): baseline or focal error"
    source: ClassVar[str] = ("residual f B error after on-chip calibration (Intel D400 datasheet: +-2 "
                             "% at 4 m on the D455; the paper's registration scale 0.98288)")
    stage: ClassVar[int] = 30
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "scale_error": (0.0, "1", "relative error of f*B used for triangulation"),
    }

    def validate(self) -> None:
        if not -0.5 < self.params["scale_error"] < 0.5:  # a relative error: 2 would be per cent
            raise ValueError(f"scale_error is relative (-0.5 to 0.5), got {self.params['scale_error']:g}")

    def bias_m(self, ctx: PixelContext) -> Array:
        z = np.asarray(ctx.z_m, dtype=np.float64)
        return np.broadcast_to(self.params["scale_error"] * z, ctx.shape()).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        z_m *= np.float32(1.0 + self.params["scale_error"])
        return z_m
