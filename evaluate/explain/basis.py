"""Signatures of the catalogue effects: what each one does to the z-depth error, per unit parameter.

A bias candidate gives, for every sample, the expected z-depth bias (m) per unit of each of its
parameters; a variance candidate gives the added z variance (m^2) per unit of its variance
parameter. Both are linear in what is fitted, so attribution is a (weighted) least-squares problem.
The forms follow DESIGN §4 and are written in the disparity domain where the physics lives:
a disparity error dd (px) turns into a z error of -z^2/(f B) dd.

Where the simulator's effect modules exist (`simulate.effects`), `module_basis` evaluates their
own `bias_m`/`variance_m2` with unit parameters instead, so the fitted numbers are in the units of
the model TOML; the forms here are the fallback and the documentation of what is fitted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from depthstation.evaluate.explain.samples import FloatArray, Samples
from depthstation.simulate.effects import EFFECTS, PixelContext
from depthstation.simulate.effects.base import box_correlation
from depthstation.simulate.effects.generic import TermSpec

Columns = Callable[[Samples], FloatArray]


@dataclass(frozen=True)
class Candidate:
    """One catalogue effect as a fit basis: `columns(samples)` is (n, len(params))."""

    name: str
    kind: str                     # "bias" (fitted on mean errors) or "variance" (on temporal variances)
    params: tuple[str, ...]
    units: tuple[str, ...]
    meaning: str
    columns: Columns
    squared: bool = False         # variance candidates: the fitted coefficient is params[0]**2
    excludes: tuple[str, ...] = ()  # candidates whose signature this one contains (never both)
    convert: Callable[[FloatArray, Samples], dict[str, float]] | None = None
    # variance candidates: correlation of two pixels (du, dv) stereo px apart (None = white noise)
    correlation: Callable[[float, float], float] | None = None
    table: str = "tiles"          # "tiles" (bias or within-frame variance) or "frame" (frame-common)
    spec: TermSpec | None = None  # a generic term of the discovery library (None: catalogue effect)
    fixed: dict[str, float] = field(default_factory=dict)   # parameters written but not fitted
    interpretation: tuple[str, ...] = ()

    @property
    def generic(self) -> bool:
        return self.spec is not None

    @property
    def complexity(self) -> tuple[int, int]:
        """Fitted coefficients, then axes: the simpler of two near-tied terms is preferred."""
        return len(self.params), len(self.spec.axes) if self.spec is not None else 1

    def to_params(self, coef: FloatArray, samples: Samples | None = None) -> dict[str, float]:
        """Fitted coefficients to named parameter values (sqrt for variance amplitudes)."""
        if self.convert is not None and samples is not None:
            return self.convert(coef, samples)
        if self.squared:
            return {self.params[0]: float(np.sign(coef[0]) * np.sqrt(abs(coef[0])))}
        return {p: float(c) for p, c in zip(self.params, coef, strict=True)}


def _k(s: Samples) -> FloatArray:
    return s.k_m_per_px


def _col(a: FloatArray) -> FloatArray:
    return np.asarray(a, dtype=np.float64).reshape(-1, 1)


def _disparity_offset(s: Samples) -> FloatArray:
    # measured disparity = true + offset: a positive offset brings the surface nearer
    return _col(-_k(s))


def _depth_scale(s: Samples) -> FloatArray:
    # z_meas = (1 + scale_error) z
    return _col(s.z_ref_m)


def _lr_focal(s: Samples) -> FloatArray:
    # right focal = (1 + m) left focal: disparity error -m (u - cx), z error +z^2/(fB) m (u - cx)
    return _col(_k(s) * (s.u - s.ppx))


def _distortion(s: Samples) -> FloatArray:
    # disparity error -k (r/f)^2 px with r the radius from the principal point
    r2 = ((s.u - s.ppx) ** 2 + (s.v - s.ppy) ** 2) / s.fx ** 2
    return _col(_k(s) * r2)


def _pixel_locking(s: Samples) -> FloatArray:
    phase = 2 * np.pi * s.disparity_px
    return np.stack([-_k(s) * np.sin(phase), -_k(s) * np.cos(phase)], axis=1)


def _thermal(s: Samples) -> FloatArray:
    # disparity drift c (T - T0) px: linear in (c, c (T_med - T0)) with T_med the session median,
    # so the temperature of zero drift T0 is fitted too (it is the calibration temperature)
    t = s.temperature_c
    if not np.isfinite(t).any():
        return np.zeros((len(s), 2))
    ref = float(np.nanmedian(t))
    dt = np.where(np.isfinite(t), t - ref, 0.0)
    return np.stack([-_k(s) * dt, -_k(s)], axis=1)


def _thermal_params(coef: FloatArray, s: Samples) -> dict[str, float]:
    c, off = float(coef[0]), float(coef[1])
    ref = float(np.nanmedian(s.temperature_c))
    t0 = ref - off / c if c != 0 else float("nan")
    return {"px_per_c": c, "reference_c": t0}


def _slant_bias(s: Samples) -> FloatArray:
    # window foreshortening: error grows like z * (1/cos(theta) - 1)
    th = np.radians(np.clip(s.inclination_deg, 0.0, 85.0))
    return _col(s.z_ref_m * (1.0 / np.cos(th) - 1.0))


def _albedo_bias(s: Samples) -> FloatArray:
    # a constant z offset on dark surfaces (m per unit of darkness)
    return _col(1.0 - np.clip(s.albedo, 0.0, 1.0))


def _flying(s: Samples) -> FloatArray:
    # mixed pixels pulled towards the background within a few pixels of a depth edge
    e = np.where(np.isfinite(s.edge_px), s.edge_px, 1e9)
    return _col(np.exp(-e / 2.0))


def _var_disparity(s: Samples) -> FloatArray:
    return _col(_k(s) ** 2)


def _var_albedo(s: Samples) -> FloatArray:
    return _col(_k(s) ** 2 * (1.0 - np.clip(s.albedo, 0.0, 1.0)))


def _var_slant(s: Samples) -> FloatArray:
    th = np.radians(np.clip(s.inclination_deg, 0.0, 85.0))
    return _col(_k(s) ** 2 * np.tan(th) ** 2)


OWN_CANDIDATES: tuple[Candidate, ...] = (
    Candidate("disparity_offset", "bias", ("offset_px",), ("px",),
              "constant disparity offset (what tare calibration fixes): bias -z^2/(fB) * offset",
              _disparity_offset),
    Candidate("depth_scale", "bias", ("scale_error",), ("1",),
              "baseline or focal length error: bias proportional to z", _depth_scale),
    Candidate("lr_focal_mismatch", "bias", ("mismatch",), ("1",),
              "left/right focal mismatch: a wedge z^2/(fB) * m * (u - cx) that averages out", _lr_focal),
    Candidate("distortion_residual", "bias", ("k_px",), ("px",),
              "residual radial distortion: bias z^2/(fB) * k * (r/f)^2", _distortion),
    Candidate("pixel_locking", "bias", ("sin_px", "cos_px"), ("px", "px"),
              "subpixel estimator locking: disparity error oscillating with the fractional disparity",
              _pixel_locking),
    Candidate("thermal_drift", "bias", ("px_per_c", "offset_at_median_px"), ("px/degC", "px"),
              "disparity drift that follows the device temperature", _thermal,
              excludes=("disparity_offset",), convert=_thermal_params),
    Candidate("slant_bias", "bias", ("coefficient",), ("1",),
              "window foreshortening on slanted surfaces: bias z * (1/cos(theta) - 1)", _slant_bias),
    Candidate("albedo_bias", "bias", ("dark_offset_m",), ("m",),
              "dark squares measured at another depth than bright ones", _albedo_bias),
    Candidate("flying_pixels", "bias", ("amplitude_m",), ("m",),
              "mixed pixels near depth edges", _flying),
    Candidate("disparity_noise", "variance", ("sigma_px",), ("px",),
              "subpixel disparity noise: z std z^2/(fB) * sigma", _var_disparity, squared=True),
    Candidate("albedo_noise", "variance", ("sigma_px",), ("px",),
              "extra disparity noise on dark surfaces", _var_albedo, squared=True),
    Candidate("slant_noise", "variance", ("sigma_px",), ("px",),
              "extra disparity noise growing with tan(inclination)", _var_slant, squared=True),
)


def own_candidates() -> dict[str, Candidate]:
    return {c.name: c for c in OWN_CANDIDATES}


# --- candidates from the simulator's own effect modules (contract 5) -------------------------------

_BIAS_MAIN = {"disparity_offset": "offset_px", "depth_scale": "scale_error", "lr_focal_mismatch": "ratio",
              "distortion_residual": "coeff_px", "pixel_locking": "amplitude_px",
              "slant_bias": "offset_px_at_45", "slant_scale": "k", "albedo_bias": "offset_px_black"}
# reference_pose_noise is left out: explain simulates the reference error itself (the rendered
# colour image and the same pose estimate), and what is common to a frame is fitted on the
# frame-common table, where a disparity shift and a reference jitter are told apart by nothing but
# their tiny 1/cos(theta) difference (docs/explain.md)
_VAR_MAIN = {"disparity_noise": "sigma_px", "albedo_noise": "sigma_px_black", "slant_noise": "window_px",
             "window_noise": "sigma_px", "incidence_noise": "sigma_px"}


# Shape parameters (not fitted) of catalogue effects whose module default is not the D455's: the
# slanted window's offset stops growing at 65 deg in the d455 preset (simulate/models/d455.toml;
# grazing pixels drop out), where the module's default 89 deg lets tan^2 reach ~3000
SHAPE: dict[str, dict[str, float]] = {"slant_bias": {"max_deg": 65.0}}

_VAR_REF = {"sigma_px": 0.08, "sigma_px_black": 0.05, "window_px": 2.0, "corner_sigma_px": 0.1}
WINDOW_DEFAULT_PX = 9.0


def _module_column(name: str, param: str, kind: str, present: dict[str, dict[str, float]]) -> Columns:
    """d(bias)/d(param) at the model's current value (central difference), or variance / param^2."""
    def cols(s: Samples) -> FloatArray:

        ctx = PixelContext(**s.context())
        base = dict(present.get(name, {}))
        if kind == "bias":
            p0 = float(base.get(param, 0.0))
            h = 1e-3 * max(abs(p0), 1.0)
            hi = EFFECTS[name]({**base, param: p0 + h}).bias_m(ctx)
            lo = EFFECTS[name]({**base, param: p0 - h}).bias_m(ctx)
            out = (np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)) / (2 * h)
        else:
            # variance per unit of param^2, taken at a realistic size (the 8 s^4 term of the
            # disparity-jitter variance would dominate at param = 1)
            p_ref = float(base.get(param, 0.0)) or _VAR_REF[param]
            one = EFFECTS[name]({**base, param: p_ref}).variance_m2(ctx)
            out = np.asarray(one, dtype=np.float64) / p_ref ** 2
        out = np.broadcast_to(out, (len(s),))
        return _col(np.where(np.isfinite(out), out, 0.0))
    return cols


def module_candidates(present: dict[str, dict[str, float]] | None = None,
                      window_px: float | None = None) -> list[Candidate]:
    """The catalogue as fit bases from `simulate.effects`, in the units of the model TOML.

    Thermal drift keeps the two-column form (slope and temperature of zero drift), written as the
    module's parameters. Window noise is fitted at a fixed width: `window_px` (what the real
    data's neighbour correlation says), else the model's, else the census window of 9 px.
    """
    present = present or {}
    own = own_candidates()
    out: list[Candidate] = []
    for name, param in _BIAS_MAIN.items():
        cls = EFFECTS[name]
        # a shape parameter the model does not set is taken from the D455's own form (written too)
        shape = {k: v for k, v in SHAPE.get(name, {}).items() if k not in present.get(name, {})}
        here = {**present, name: {**shape, **present.get(name, {})}} if shape else present
        out.append(Candidate(name, "bias", (param,), (cls.PARAMS[param][1],), cls.meaning,
                             _module_column(name, param, "bias", here), fixed=shape))
    th = own["thermal_drift"]
    out.append(Candidate("thermal_drift", "bias", ("coeff_px_per_c", "offset_at_median_px"),
                         ("px/degC", "px"), EFFECTS["thermal_drift"].meaning, th.columns,
                         excludes=("disparity_offset",), convert=_thermal_module_params))
    width = float(window_px or present.get("window_noise", {}).get("window_px", WINDOW_DEFAULT_PX))
    for name, param in _VAR_MAIN.items():
        cls = EFFECTS[name]
        corr: Callable[[float, float], float] | None = None
        fixed: dict[str, float] = {}
        here = present
        if name == "window_noise":
            fixed = {"window_px": width}
            here = {**present, name: {**present.get(name, {}), "window_px": width}}

            def corr(du: float, dv: float, w: float = width) -> float:
                return float(box_correlation(w, du, dv))
        out.append(Candidate(name, "variance", (param,), (cls.PARAMS[param][1],), cls.meaning,
                             _module_column(name, param, "variance", here), squared=True,
                             correlation=corr, fixed=fixed))
    return out



def _thermal_module_params(coef: FloatArray, s: Samples) -> dict[str, float]:
    p = _thermal_params(coef, s)
    # the module's shift is c (T - T0) with + = too near; ours is the z-bias -K c (T - T0): same sign
    return {"coeff_px_per_c": p["px_per_c"], "reference_c": p["reference_c"]}
