"""Static pattern: a unit's fixed, spatially correlated disparity error that frames do not average away."""

from __future__ import annotations

from functools import lru_cache
from typing import ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext

_CELL = 0.005          # grid step in normalised image coordinates (3.4 px at the D455's 674 px)
_HALF = (1.0, 0.75)    # grid half extent (x, y): every D4xx depth mode's field of view fits


@lru_cache(maxsize=8)
def pattern_grid(seed: int, length: float) -> NDArray[np.float32]:
    """A unit-RMS Gaussian random field over the image, correlation length `length` (normalised units)."""
    rng = np.random.default_rng([seed, 0x57A71C])
    ny, nx = (round(2 * h / _CELL) + 1 for h in (_HALF[1], _HALF[0]))
    white = rng.standard_normal((ny, nx)).astype(np.float32)
    s = max(length / _CELL, 0.5)
    k = 2 * int(np.ceil(3.5 * s)) + 1
    field = np.asarray(cv2.GaussianBlur(white, (k, k), s, borderType=cv2.BORDER_REFLECT), dtype=np.float32)
    field = (field - np.float32(field.mean())) / np.float32(max(float(field.std()), 1e-12))
    return np.asarray(field, dtype=np.float32)


class StaticPattern(DisparityShift):
    """d_meas = d + sigma_px * F(x, y): F a unit-RMS smooth random field fixed to the unit.

    What stays in a still camera's depth when the per-frame noise is averaged: the emitter's dot
    pattern is fixed to the unit, so every frame matches the same dots at the same pixels and their
    sub-pixel placement errors repeat; residuals of the lens model and rectification (the
    calibration's own fit error, ~0.05-0.1 px) are fixed too. Intel's depth-quality guide calls
    it a fixed-pattern error: averaging frames removes temporal noise, not this (Grunnet-Jepsen et
    al., "Projectors for Intel RealSense depth cameras D4xx", and "Tuning depth cameras"; the
    paper's 150 frames per standpoint average the noise 12x down, and its accuracy still reads
    3-4x the per-frame noise). Modelled as a smooth Gaussian random field over the normalised image
    (x = (u - ppx)/fx, y = (v - ppy)/fx) with correlation length `length` and RMS `sigma_px`;
    `pattern_seed` is the unit (one field per seed, the same at every resolution). The field is fixed
    to the unit's optics, so it is an angle too: `sigma_px` is in px of the 1280-wide mode and scaled
    by fx / fx_ref in the others, and the depth error it makes is the same at every resolution.
    """

    name: ClassVar[str] = "static_pattern"
    meaning: ClassVar[str] = ("fixed, spatially correlated disparity error of the unit (does not average "
                              "over frames; px at 1280 wide)")
    source: ClassVar[str] = ("emitter dot pattern fixed to the unit; lens/rectification residuals; "
                             "Intel D4xx projector and tuning white papers (fixed-pattern error); "
                             "paper Section 5.1 (accuracy 3-4x the noise after 150 frames)")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px": (0.0, "px at 1280 wide", "RMS of the fixed disparity error over the image, px of the "
                                             "1280-wide mode (x fx / fx_ref in others)"),
        "length": (0.05, "1", "correlation length, normalised image units (0.05 = 34 px, D455 at 1280)"),
        "pattern_seed": (0.0, "1", "the unit: which field (an integer)"),
    }

    def validate(self) -> None:
        p = self.params
        if p["sigma_px"] < 0 or not 0.002 <= p["length"] <= 1.0 or p["pattern_seed"] < 0 \
                or p["pattern_seed"] != int(p["pattern_seed"]):
            raise ValueError("sigma_px >= 0, length in 0.002..1 (normalised image units) and pattern_seed a "
                             "whole number >= 0 required")

    def field(self, ctx: PixelContext) -> Array:
        """F at every entry of the context (unit RMS over the image)."""
        grid = pattern_grid(int(self.params["pattern_seed"]), float(self.params["length"]))
        x = (np.asarray(ctx.u, dtype=np.float64) - ctx.ppx) / ctx.fx
        y = (np.asarray(ctx.v, dtype=np.float64) - ctx.ppy) / ctx.fx
        x, y = np.broadcast_arrays(x, y)
        gx = ((x + _HALF[0]) / _CELL).astype(np.float32)
        gy = ((y + _HALF[1]) / _CELL).astype(np.float32)
        if gx.ndim == 2 and max(gx.shape) < 32767:
            return np.asarray(cv2.remap(grid, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT),
                              dtype=np.float64)
        return _bilinear(grid, gx, gy)

    def shift_px(self, ctx: PixelContext) -> Array:
        if self.params["sigma_px"] == 0:
            return np.zeros(ctx.shape())
        return np.broadcast_to(self.params["sigma_px"] * ctx.reference_scale * self.field(ctx), ctx.shape())


def _bilinear(grid: NDArray[np.float32], gx: Array, gy: Array) -> Array:
    """Bilinear reading of `grid` at fractional (column, row) positions, clamped to its edge."""
    ny, nx = grid.shape
    x = np.clip(np.asarray(gx, dtype=np.float64), 0.0, nx - 1.000001)
    y = np.clip(np.asarray(gy, dtype=np.float64), 0.0, ny - 1.000001)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    g = grid.astype(np.float64)
    top = g[y0, x0] * (1 - fx) + g[y0, x0 + 1] * fx
    bottom = g[y0 + 1, x0] * (1 - fx) + g[y0 + 1, x0 + 1] * fx
    return np.asarray(top * (1 - fy) + bottom * fy)
