"""The effect interface (contract 5): per-pixel context, analytic signature and sampler of one sensor effect.

Stereo depth is triangulated from disparity, d = f * B / z (px), so most effects live in disparity
space: they shift or blur d, and the depth follows as z = f * B / d. The helpers here convert a
disparity shift into its exact z-depth bias and a disparity variance into its first-order z
variance, so every effect states its physics once, in the space where it happens.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import SimulationError

Array = NDArray[Any]

# D455 depth camera at 1280x720 (see simulate/presets.py): used only as defaults of PixelContext.
_D455_FX = 640.0 / np.tan(np.radians(87.0 / 2.0))


@dataclass
class PixelContext:
    """Everything an effect may depend on, one (broadcastable) entry per pixel or sample.

    z_m: true z-depth (m); inclination_deg: ray vs surface normal (0 = head-on); u, v: depth-pixel
    coordinates (pixel centres at integers); albedo: IR reflectance 0 (black) .. 1 (white);
    time_s: since stream start; temperature_c: device temperature; edge_distance_px: distance to
    the nearest depth edge (inf if none); fx, ppx, ppy, baseline_m: scalars of the depth camera.
    """

    z_m: Any
    inclination_deg: Any = 0.0
    u: Any = 0.0
    v: Any = 0.0
    albedo: Any = 1.0
    time_s: Any = 0.0
    temperature_c: Any = 40.0
    edge_distance_px: Any = np.inf
    fx: float = float(_D455_FX)
    ppx: float = 639.5
    ppy: float = 359.5
    baseline_m: float = 0.095

    @property
    def focal_baseline(self) -> float:
        """f * B in px * m: disparity (px) = focal_baseline / z (m)."""
        return float(self.fx * self.baseline_m)

    def disparity_px(self) -> Array:
        """True disparity of every entry (px)."""
        return self.focal_baseline / np.asarray(self.z_m, dtype=np.float64)

    def shape(self) -> tuple[int, ...]:
        """Broadcast shape of all per-pixel fields."""
        return tuple(np.broadcast_shapes(*(np.shape(getattr(self, k)) for k in _ARRAY_FIELDS)))


_ARRAY_FIELDS = ("z_m", "inclination_deg", "u", "v", "albedo", "time_s", "temperature_c",
                 "edge_distance_px")


def bias_from_disparity_shift(ctx: PixelContext, shift_px: Any) -> Array:
    """Exact z bias of a disparity shift: f B / (d + s) - z (m; + = too far). NaN where d + s <= 0."""
    d = ctx.disparity_px()
    dm = d + np.asarray(shift_px, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(dm > 0, ctx.focal_baseline / dm, np.nan) - np.asarray(ctx.z_m, dtype=np.float64)
    return np.asarray(out)


def variance_from_disparity_variance(ctx: PixelContext, var_px2: Any) -> Array:
    """First-order z variance of disparity noise: (dz/dd)^2 var_d = (z^2 / (f B))^2 var_d (m^2)."""
    z = np.asarray(ctx.z_m, dtype=np.float64)
    dzdd = z * z / ctx.focal_baseline
    return np.asarray(dzdd * dzdd * np.asarray(var_px2, dtype=np.float64))


def second_order_bias_from_disparity_variance(ctx: PixelContext, var_px2: Any) -> Array:
    """Bias of z = fB/(d+n) for zero-mean n: E[z] - z ~ z var_d / d^2 (m), the 1/d nonlinearity."""
    z = np.asarray(ctx.z_m, dtype=np.float64)
    d = ctx.disparity_px()
    return np.asarray(z * np.asarray(var_px2, dtype=np.float64) / (d * d))


def shift_depth(ctx: PixelContext, z_m: Array, shift_px: Any) -> Array:
    """Sampler helper: move the disparity of a z map by shift_px (px); NaN where d + s <= 0."""
    fb = np.float32(ctx.focal_baseline)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = fb / z_m
        d += np.asarray(shift_px, dtype=np.float32)
        d[~(d > 0)] = np.nan
        out = fb / d
    return np.asarray(out, dtype=z_m.dtype)


class Effect:
    """One physical effect of the sensor (contract 5). Subclasses set the class attributes.

    PARAMS maps each parameter to (default, unit, description); `params` holds SI values.
    `stage` orders effects in a model: disparity biases (10), disparity noise (20), depth-scale (30),
    quantisation (40), depth-space artefacts (50), reference errors (60), dropout (70).
    """

    name: ClassVar[str] = ""
    meaning: ClassVar[str] = ""
    stage: ClassVar[int] = 50
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {}

    def __init__(self, params: dict[str, Any] | None = None, **kwargs: float) -> None:
        given = dict(params or {})
        given.update(kwargs)
        unknown = sorted(set(given) - set(self.PARAMS))
        if unknown:
            known = ", ".join(self.PARAMS)
            raise SimulationError(f"effect '{self.name}': unknown parameter(s) {unknown} (known: {known})")
        self.params: dict[str, float] = {k: float(v[0]) for k, v in self.PARAMS.items()}
        for k, val in given.items():
            if isinstance(val, bool) or not isinstance(val, (int, float)):
                raise SimulationError(f"effect '{self.name}': parameter '{k}' must be a number, got {val!r}")
            self.params[k] = float(val)
        self.units: dict[str, str] = {k: v[1] for k, v in self.PARAMS.items()}
        self._cache_ctx: PixelContext | None = None
        self._cache: dict[str, Array] = {}
        self.validate()

    def validate(self) -> None:
        """Reject parameters without physical meaning (override where needed)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params})"

    def cached(self, ctx: PixelContext, key: str, fn: Callable[[], Array]) -> Array:
        """Per-context memo for static maps (a standpoint renders its geometry once, 150 frames)."""
        if self._cache_ctx is not ctx:
            self._cache_ctx = ctx
            self._cache = {}
        if key not in self._cache:
            self._cache[key] = fn()
        return self._cache[key]

    def bias_m(self, ctx: PixelContext) -> Array:
        """Expected z-depth bias (m, + = measured too far) of this effect alone."""
        return np.zeros(ctx.shape())

    def variance_m2(self, ctx: PixelContext) -> Array:
        """Added z-depth variance (m^2) of this effect alone."""
        return np.zeros(ctx.shape())

    def valid_probability(self, ctx: PixelContext) -> Array:
        """Probability that a pixel keeps a depth value under this effect (1 unless it drops pixels)."""
        return np.ones(ctx.shape())

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        """Sampler: perturb a rendered z map (NaN = no depth). May modify and return z_m."""
        raise NotImplementedError


class DisparityShift(Effect):
    """An effect that moves the disparity by a deterministic `shift_px(ctx)` (a calibration-type bias)."""

    stage: ClassVar[int] = 10

    def shift_px(self, ctx: PixelContext) -> Array:
        """Disparity error (px; + = measured disparity too large = depth too near)."""
        raise NotImplementedError

    def bias_m(self, ctx: PixelContext) -> Array:
        return np.broadcast_to(bias_from_disparity_shift(ctx, self.shift_px(ctx)), ctx.shape()).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        shift = self.cached(ctx, "shift", lambda: np.asarray(self.shift_px(ctx), dtype=np.float32))
        return shift_depth(ctx, z_m, shift)


class DisparityJitter(Effect):
    """An effect that adds zero-mean Gaussian disparity noise of RMS `sigma_px(ctx)`."""

    stage: ClassVar[int] = 20

    def sigma_px(self, ctx: PixelContext) -> Array:
        """RMS of the added disparity noise (px) per pixel."""
        raise NotImplementedError

    def bias_m(self, ctx: PixelContext) -> Array:
        s = np.asarray(self.sigma_px(ctx), dtype=np.float64)
        return np.broadcast_to(second_order_bias_from_disparity_variance(ctx, s * s), ctx.shape()).copy()

    def variance_m2(self, ctx: PixelContext) -> Array:
        s = np.asarray(self.sigma_px(ctx), dtype=np.float64) / ctx.disparity_px()
        z = np.asarray(ctx.z_m, dtype=np.float64)
        return np.broadcast_to(z * z * (s * s + 8 * s**4), ctx.shape()).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        sigma = self.cached(ctx, "sigma", lambda: np.asarray(self.sigma_px(ctx), dtype=np.float32))
        noise = rng.standard_normal(z_m.shape, dtype=np.float32)
        noise *= sigma
        return shift_depth(ctx, z_m, noise)
