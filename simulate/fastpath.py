"""A fused sampler for models built from disparity shifts, disparity noise, scale, quantisation and dropout.

Mathematically the same model as applying the effects one by one (shifts add in disparity; the
sum of independent zero-mean Gaussian disparity noises is one Gaussian with the summed variance;
dropout is independent of the values), but one pass over the image instead of ten: what makes a
150-frame 1280x720 standpoint take seconds. Random numbers come from numpy's Generator, so the
result does not depend on threads.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from depthstation.simulate.effects.base import (
    CorrelatedJitter,
    DisparityJitter,
    DisparityShift,
    Effect,
    FrameJitter,
    PixelContext,
)
from depthstation.simulate.effects.color_camera import ColorCamera
from depthstation.simulate.effects.depth_scale import DepthScale
from depthstation.simulate.effects.dropout import Dropout
from depthstation.simulate.effects.flying_pixels import FlyingPixels
from depthstation.simulate.effects.quantization import Quantization

FUSABLE = (DisparityShift, DisparityJitter, DepthScale, Quantization, Dropout, FlyingPixels,
           ColorCamera)  # the colour camera leaves the depth alone


@njit(cache=True, nogil=True)
def _fused(d0: Any, field: Any, fsig: Any, sigma: Any, noise: Any, fb: float, step: float, scale: float,
           unit: float, keep: Any, draw: Any, out: Any) -> None:  # pragma: no cover - compiled
    """`field` (empty: none) times `fsig` is added where there is depth (d0 > 0), else d0 = -1."""
    nan = np.float32(np.nan)
    with_field = field.shape[0] > 0
    for i in range(d0.size):
        b = d0[i]
        if with_field:
            b = b + field[i] * fsig if b > 0 else np.float32(-1.0)
        d = b + sigma[i] * noise[i]
        if not d > 0 or draw[i] >= keep[i]:
            out[i] = nan
            continue
        if step > 0:
            d = math.floor(d / step + 0.5) * step
            if d <= 0:
                out[i] = nan
                continue
        z = fb / d * scale
        if unit > 0:
            z = math.floor(z / unit + 0.5) * unit
        out[i] = z


def fusable(effects: list[Effect]) -> bool:
    """Whether every effect has a fused form (at most one quantisation, dropout and flying pixels)."""
    if not all(isinstance(e, FUSABLE) for e in effects):
        return False
    return all(sum(isinstance(e, t) for e in effects) <= 1 for t in (Quantization, Dropout, FlyingPixels))


class FusedSampler:
    """Static maps of one context (disparity with all shifts, total noise RMS, keep probability)."""

    def __init__(self, effects: list[Effect], ctx: PixelContext, z_m: NDArray[Any]) -> None:
        shape = np.shape(z_m)
        self.shape = shape
        self.ctx = ctx
        self.fb = float(ctx.focal_baseline)
        z = np.asarray(z_m, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.divide(self.fb, z)
        var: Any = 0.0  # a scalar while every noise RMS is one (a map costs a pass per effect)
        keep: Any = None
        self.scale = 1.0
        self.step = 0.0
        self.unit = 0.0
        self.flying: FlyingPixels | None = None
        self.flying_table: tuple[NDArray[np.int64], NDArray[Any]] | None = None
        # noises that are not independent per pixel: drawn per frame as a whole field (window) or
        # one number (frame-common), added to the disparity before the per-pixel pass
        self.correlated: list[tuple[CorrelatedJitter, NDArray[np.float32]]] = []
        self.common: list[NDArray[np.float32]] = []
        for e in effects:
            if isinstance(e, CorrelatedJitter):
                self.correlated.append((e, np.asarray(e.sigma_px(ctx), dtype=np.float32)))
            elif isinstance(e, FrameJitter):
                self.common.append(np.asarray(e.sigma_px(ctx), dtype=np.float32))
            elif isinstance(e, DisparityShift):
                d = d + np.broadcast_to(e.shift_px(ctx), shape)
            elif isinstance(e, DisparityJitter):
                var = var + np.asarray(e.sigma_px(ctx), dtype=np.float64) ** 2
            elif isinstance(e, DepthScale):
                self.scale *= 1.0 + e.params["scale_error"]
            elif isinstance(e, Quantization):
                self.step = e.params["disparity_step_px"]
                self.unit = e.params["depth_unit_m"]
            elif isinstance(e, Dropout):
                p = e.valid_probability(ctx)
                keep = p if keep is None else keep * p
            elif isinstance(e, FlyingPixels):
                self.flying = e
                self.flying_table = e.near_table(ctx, shape)
        n = int(np.prod(shape))
        d32 = np.empty(shape, np.float32)
        np.copyto(d32, d, casting="same_kind")
        d32[np.isnan(d32)] = -1.0
        self.d0 = d32.reshape(n)
        self.no_depth = np.flatnonzero(~(self.d0 > 0)) if self.correlated or self.common else None
        self.sigma = _full(np.sqrt(var), shape, n)
        self.keep = _full(1.0 if keep is None else keep, shape, n)

    def sample(self, rng: np.random.Generator) -> NDArray[np.float32]:
        """One measured z map (float32, NaN = no depth)."""
        noise = rng.standard_normal(self.d0.size, dtype=np.float32)
        draw = rng.random(self.d0.size, dtype=np.float32)
        out = np.empty(self.d0.size, dtype=np.float32)
        d0 = self.d0
        field, fsig = _NO_FIELD, np.float32(0.0)
        if len(self.correlated) == 1 and not self.common and self.correlated[0][1].ndim == 0:
            # the usual model (one window noise of one RMS): the field is added in the pass
            e, sig = self.correlated[0]
            field = np.ascontiguousarray(e.field(self.shape, rng, self.ctx), dtype=np.float32).reshape(-1)
            fsig = np.float32(sig)
        elif self.correlated or self.common:
            d0 = d0.copy()
            grid = d0.reshape(self.shape)
            for e, sig in self.correlated:
                grid += np.asarray(e.field(self.shape, rng, self.ctx), dtype=np.float32) * sig
            for sig in self.common:
                grid += sig * np.float32(rng.standard_normal())
            d0[self.no_depth] = -1.0   # no depth stays no depth
        _fused(d0, field, fsig, self.sigma, noise, self.fb, self.step, self.scale, self.unit, self.keep, draw,
               out)
        z = out.reshape(self.shape)
        if self.flying is not None and self.flying_table is not None:
            z = self.flying.displace(self.flying_table, z, rng)
        return z


_NO_FIELD = np.zeros(0, np.float32)


def _full(value: Any, shape: tuple[int, ...], n: int) -> NDArray[np.float32]:
    """A flat float32 map of `shape` from a scalar or a broadcastable array."""
    out = np.empty(shape, np.float32)
    out[...] = value
    return out.reshape(n)
