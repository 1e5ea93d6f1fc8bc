"""Subpixel matching noise: zero-mean Gaussian disparity noise, Intel's RMS_z = z^2 s / (f B)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityJitter, PixelContext


class DisparityNoise(DisparityJitter):
    """The stereo matcher finds the disparity to within `sigma_px` (Intel's 'subpixel RMS').

    Source: Intel, 'Tuning depth cameras for best performance' (RMS error = z^2 * subpixel /
    (f * B), subpixel about 0.08 px for the D4xx with a textured target).
    """

    name: ClassVar[str] = "disparity_noise"
    meaning: ClassVar[str] = "zero-mean Gaussian disparity noise of the subpixel matcher"
    source: ClassVar[str] = ("Intel D400 datasheet / Grunnet-Jepsen et al. 'Depth camera performance': "
                             "subpixel RMS 0.08 px, RMS_z = z^2 s / (f B)")
    stage: ClassVar[int] = 20
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px": (0.08, "px", "RMS of the disparity estimate (Intel's subpixel RMS)"),
    }

    def validate(self) -> None:
        if self.params["sigma_px"] < 0:
            raise ValueError("sigma_px must be >= 0")

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(self.params["sigma_px"])
