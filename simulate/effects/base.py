"""The effect interface (contract 5): per-pixel context, analytic signature and sampler of one sensor effect.

Stereo depth is triangulated from disparity, d = f * B / z (px), so most effects live in disparity
space: they shift or blur d, and the depth follows as z = f * B / d. The helpers here convert a
disparity shift into its exact z-depth bias and a disparity variance into its first-order z
variance, so every effect states its physics once, in the space where it happens.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import SimulationError

Array = NDArray[Any]
T = TypeVar("T")

# D455 depth camera at 1280x720 (see simulate/presets.py): used only as defaults of PixelContext
# (fx_ref: also the D435's, whose depth field of view is the same 87 deg).
_D455_FX = 640.0 / np.tan(np.radians(87.0 / 2.0))


@dataclass
class PixelContext:
    """Everything an effect may depend on, one (broadcastable) entry per pixel or sample.

    z_m: true z-depth (m); inclination_deg: ray vs surface normal (0 = head-on); u, v: depth-pixel
    coordinates (pixel centres at integers); albedo: IR reflectance 0 (black) .. 1 (white);
    time_s: since stream start; temperature_c: device temperature; edge_distance_px: distance to
    the nearest depth edge (inf if none); fx, ppx, ppy, baseline_m: scalars of the depth camera.
    fx_ref: the same camera's focal length (px) in its full-width 1280 mode (`CameraPreset.
    reference_fx`): a unit's geometric errors (disparity offset, static pattern, distortion residual)
    are angles, stated in px of that mode and scaled by `reference_scale` = fx / fx_ref in any other
    (a 0.1 px offset at 1280x720 is 0.06 px at 640x480, the same depth bias). The matcher's errors
    (noise, slant, albedo, quantisation, pixel locking) are in px of the image being matched.
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
    fx_ref: float = float(_D455_FX)

    @property
    def reference_scale(self) -> float:
        """fx / fx_ref: px of this image per px of the camera's 1280-wide mode (1 at 1280x720)."""
        return float(self.fx / self.fx_ref)

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
    source: ClassVar[str] = ""   # where the physics and its magnitude come from (`simulate model` prints it)
    stage: ClassVar[int] = 50
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {}
    time_dependent: ClassVar[bool] = False   # depends on time or temperature (context per frame)
    # parameters added after models were written: a model TOML may omit them (their default is the
    # effect as it was before them)
    OPTIONAL: ClassVar[frozenset[str]] = frozenset()

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
        self._cache: dict[str, Any] = {}
        self._cache_lock = threading.Lock()
        self.validate()

    def validate(self) -> None:
        """Reject parameters without physical meaning (override where needed)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params})"

    def cached(self, ctx: PixelContext, key: str, fn: Callable[[], T]) -> T:
        """Per-context memo for static maps (a standpoint renders its geometry once, 150 frames).

        Thread-safe: renderers on several threads share a model's effects, each with its own
        context; a value is only ever returned to a caller of the context it was made for."""
        with self._cache_lock:
            if self._cache_ctx is not ctx:
                self._cache_ctx = ctx
                self._cache = {}
            memo = self._cache
            if key in memo:
                return memo[key]
        value = fn()
        with self._cache_lock:
            memo[key] = value
        return value

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


def box_correlated_field(shape: tuple[int, ...], window: float, rng: np.random.Generator) -> Array:
    """Unit-variance Gaussian field whose neighbours share the error of a `window` x `window` box.

    Each value is the mean of window^2 white draws of a field `window - 1` larger than the image
    (so the border has the same statistics as the interior), times `window`. The correlation of
    two values k_u, k_v apart is (1 - |k_u|/w)+ (1 - |k_v|/w)+ (a box matcher's footprint).
    A 1-D array is filtered along its axis; more dimensions as one image (leading axes, last axis).
    """
    w = max(1, round(float(window)))
    if len(shape) == 0:
        return np.asarray(rng.standard_normal(dtype=np.float32))
    if w == 1:
        return rng.standard_normal(shape, dtype=np.float32)
    if len(shape) == 1:
        white = rng.standard_normal(shape[0] + w - 1, dtype=np.float32)
        c = np.concatenate([[0.0], np.cumsum(white, dtype=np.float64)])
        return ((c[w:] - c[:-w]) / np.sqrt(w)).astype(np.float32)
    rows, cols = int(np.prod(shape[:-1])), int(shape[-1])
    white = rng.standard_normal((rows + w - 1, cols + w - 1), dtype=np.float32)
    out = cv2.boxFilter(white, -1, (w, w), normalize=True, borderType=cv2.BORDER_CONSTANT)
    h = w // 2
    out = out[h:h + rows, h:h + cols] * np.float32(w)
    return np.ascontiguousarray(out).reshape(shape)


def box_correlation(window: float, du: Any, dv: Any = 0.0) -> Array:
    """Correlation of `box_correlated_field` values du, dv pixels apart (separable triangles)."""
    w = max(1.0, float(round(window)))
    a = np.clip(1.0 - np.abs(np.asarray(du, dtype=np.float64)) / w, 0.0, None)
    b = np.clip(1.0 - np.abs(np.asarray(dv, dtype=np.float64)) / w, 0.0, None)
    return np.asarray(a * b)


class CorrelatedJitter(DisparityJitter):
    """Zero-mean Gaussian disparity noise of RMS `sigma_px(ctx)` shared by neighbours within `window_px`.

    Per pixel it is the same distribution as `DisparityJitter` (same signature); only the joint
    distribution of neighbours differs, which `correlation` states.
    """

    stage: ClassVar[int] = 20

    def window(self) -> float:
        return float(self.params.get("window_px", 1.0))

    def correlation(self, du: Any, dv: Any = 0.0) -> Array:
        """Correlation of the noise of two pixels du, dv apart (px)."""
        return box_correlation(self.window(), du, dv)

    def image_window(self, ctx: PixelContext | None, shape: tuple[int, ...]) -> int:
        """The window in the rendered image's pixels: `window_px` is in the stereo imager's pixels,
        which differ from the image's when depth is aligned to the colour camera (ctx.u steps)."""
        w = self.window()
        u = np.asarray(ctx.u) if ctx is not None else np.zeros(0)
        if len(shape) >= 2 and u.shape == tuple(shape) and shape[-1] > 1:
            step = float(abs(u.reshape(-1, shape[-1])[0, 1] - u.reshape(-1, shape[-1])[0, 0]))
            if step > 0:
                w = w / step
        return max(1, round(float(w)))

    def field(self, shape: tuple[int, ...], rng: np.random.Generator,
              ctx: PixelContext | None = None) -> Array:
        """One unit-variance draw of the correlated field."""
        return box_correlated_field(shape, self.image_window(ctx, shape), rng)

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        sigma = self.cached(ctx, "sigma", lambda: np.asarray(self.sigma_px(ctx), dtype=np.float32))
        noise = np.asarray(self.field(z_m.shape, rng, ctx), dtype=np.float32) * sigma
        return shift_depth(ctx, z_m, noise)


class FrameJitter(DisparityJitter):
    """Zero-mean disparity noise common to every pixel of a frame: one draw per frame times `sigma_px(ctx)`.

    Per pixel the same distribution as `DisparityJitter` (same signature); all pixels of a frame move
    together, so it does not average out over the board.
    """

    stage: ClassVar[int] = 20

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        sigma = self.cached(ctx, "sigma", lambda: np.asarray(self.sigma_px(ctx), dtype=np.float32))
        return shift_depth(ctx, z_m, sigma * np.float32(rng.standard_normal()))
