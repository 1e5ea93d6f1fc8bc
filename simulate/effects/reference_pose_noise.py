"""Reference pose noise: the board pose from corners is uncertain, more at long range and steep angles."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class ReferencePoseNoise(Effect):
    """The reference plane moves along z by sigma = corner_sigma_px z^2 / (f L cos(theta)) per frame.

    Corner noise of sigma_px on a board of size L gives a distance error ~ sigma_px z^2 / (f L)
    (the board's apparent size is f L / z px), stretched by 1 / cos(theta) along the ray. One draw
    per frame moves the whole reference (the error is common to all pixels of a frame).
    """

    name: ClassVar[str] = "reference_pose_noise"
    meaning: ClassVar[str] = "per-frame error of the checkerboard reference plane along z"
    stage: ClassVar[int] = 60
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "corner_sigma_px": (0.0, "px", "RMS of the detected corner positions"),
        "board_size_m": (0.57, "m", "extent of the corner grid (6 x 0.095 m for the default board)"),
    }

    def validate(self) -> None:
        if self.params["corner_sigma_px"] < 0 or not 0.01 <= self.params["board_size_m"] <= 10:
            raise ValueError("corner_sigma_px >= 0 and board_size_m, the corner grid's extent, in 0.01..10 m "
                             f"required (got {self.params['board_size_m']:g})")

    def sigma_m(self, ctx: PixelContext) -> Array:
        z = np.asarray(ctx.z_m, dtype=np.float64)
        inc = np.radians(np.clip(np.asarray(ctx.inclination_deg, dtype=np.float64), 0.0, 85.0))
        return np.asarray(self.params["corner_sigma_px"] * z * z
                          / (ctx.fx * self.params["board_size_m"] * np.cos(inc)))

    def variance_m2(self, ctx: PixelContext) -> Array:
        return np.broadcast_to(self.sigma_m(ctx) ** 2, ctx.shape()).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        sigma = self.cached(ctx, "sigma", lambda: np.asarray(self.sigma_m(ctx), dtype=np.float32))
        z_m += sigma * np.float32(rng.standard_normal())
        return z_m
