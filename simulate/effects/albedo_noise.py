"""Albedo noise: lower signal on dark surfaces, more matching noise."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityJitter, PixelContext


class AlbedoNoise(DisparityJitter):
    """Added disparity RMS = sigma_px_black * (1 - albedo) (SNR falls with the returned IR)."""

    name: ClassVar[str] = "albedo_noise"
    meaning: ClassVar[str] = "extra disparity noise on dark surfaces, proportional to 1 - albedo"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px_black": (0.0, "px", "added disparity RMS on a black surface"),
    }

    def sigma_px(self, ctx: PixelContext) -> Array:
        a = np.clip(np.asarray(ctx.albedo, dtype=np.float64), 0.0, 1.0)
        return np.asarray(self.params["sigma_px_black"] * (1.0 - a))
