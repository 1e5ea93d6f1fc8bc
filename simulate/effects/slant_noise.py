"""Slant noise: a slanted surface is foreshortened inside the matching window; more noise."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityJitter, PixelContext


def disparity_gradient(ctx: PixelContext) -> Array:
    """|grad d| (px per px) of a plane seen at inclination theta at depth z: B tan(theta) / z.

    For a plane n.X = c the disparity is linear in the image, d = f B (n . r~) / c, so its
    gradient is B |n_xy| / c; on the optical axis c = z cos(theta) and |n_xy| = sin(theta).
    """
    inc = np.radians(np.clip(np.asarray(ctx.inclination_deg, dtype=np.float64), 0.0, 89.0))
    return np.asarray(ctx.baseline_m * np.tan(inc) / np.asarray(ctx.z_m, dtype=np.float64))


class SlantNoise(DisparityJitter):
    """Added disparity RMS = window_px * |grad d| / sqrt(12): the disparity spread inside the window."""

    name: ClassVar[str] = "slant_noise"
    meaning: ClassVar[str] = "disparity noise from the disparity gradient across the matching window"
    source: ClassVar[str] = ("fronto-parallel window on a slanted surface: disparity gradient B "
                             "tan(theta) / z across it (Bleyer et al. 2011, PatchMatch stereo's "
                             "slanted windows)")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "window_px": (0.0, "px", "effective width of the matching window"),
    }

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(self.params["window_px"] * disparity_gradient(ctx) / np.sqrt(12.0))
