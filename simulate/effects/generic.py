"""Generic terms: a bias or noise over the axes of the pixel context, for physics outside the catalogue.

`explain` discovers terms like these when no catalogue effect explains a residual; written into a
model TOML they are rendered like any effect. The physics is stated in the disparity domain: a bias
term is a disparity shift delta (px; + = disparity too large = surface too near), a noise term an
added disparity variance (px^2). A term's structure is its name,

    term_<quantity>_<axis>[_<axis>]_<basis>      e.g. term_bias_v_poly2, term_noise_frame_common

(a noise term may end in `_window`: shared by neighbours over a `window_px` box, as the matcher's
window shares its noise) and its parameters are the coefficients (plus fixed references of
centred axes, the edge decay length, the window):

| basis | axes | form |
|---|---|---|
| poly1..3 | one axis a | sum_k c_k a^k (no constant: `disparity_offset` / `disparity_noise` are that) |
| product | two axes a, b | c a b |
| exp | edge | c exp(-e / length_px) |
| field2, field3 | tile | polynomial field over the image in (x, y) of total degree 2 or 3, no constant |
| common | frame | noise only: one draw per frame shared by every pixel, variance c |

Axis variables: u -> x = (u - ppx) / fx, v -> y = (v - ppy) / fx, radius -> r = sqrt(x^2 + y^2)
(normalised image coordinates), distance -> z (m), disparity -> d = fB/z (px), inclination -> theta
(rad), albedo -> a = 1 - rho (darkness), time -> t - ref_time_s (s), temperature ->
T - ref_temperature_c (degC), edge -> e (px to the nearest depth edge). A noise term along distance
goes in even powers, sum_k c_k z^(2k) (the SNR law: sigma_d ~ z or z^2). A noise term's variance
is clipped at 0.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from depthstation.core.errors import SimulationError
from depthstation.simulate.effects.base import (
    Array,
    CorrelatedJitter,
    DisparityJitter,
    DisparityShift,
    Effect,
    FrameJitter,
    PixelContext,
)

AXES = ("u", "v", "radius", "tile", "distance", "disparity", "inclination", "albedo", "frame", "time",
        "temperature", "edge")
QUANTITIES = ("bias", "noise")
# axis -> (symbol in expressions, unit, definition)
AXIS_INFO: dict[str, tuple[str, str, str]] = {
    "u": ("x", "1", "x = (u - ppx) / fx"),
    "v": ("y", "1", "y = (v - ppy) / fx"),
    "radius": ("r", "1", "r = sqrt(x^2 + y^2), normalised image radius"),
    "distance": ("z", "m", "z = distance (z-depth, m)"),
    "disparity": ("d", "px", "d = f B / z (px)"),
    "inclination": ("theta", "rad", "theta = inclination (rad)"),
    "albedo": ("a", "1", "a = 1 - reflectance (darkness: less infrared back)"),
    "time": ("t", "s", "t = time - ref_time_s (s)"),
    "temperature": ("T", "degC", "T = temperature - ref_temperature_c (degC)"),
    "edge": ("e", "px", "e = distance to the nearest depth edge (px)"),
}
REFERENCE = {"time": "ref_time_s", "temperature": "ref_temperature_c"}
FIELD_TERMS = {2: ("x", "y", "xx", "xy", "yy"), 3: ("x", "y", "xx", "xy", "yy", "xxx", "xxy", "xyy", "yyy")}
_NAME = re.compile(r"^term_(bias|noise)_([a-z_]+?)_(poly[123]|product|exp|field[23]|common)(_window)?$")


@dataclass(frozen=True)
class TermSpec:
    """The structure of a generic term: what it is about, along which axes, in which basis."""

    quantity: str          # "bias" (disparity shift, px) or "noise" (disparity variance, px^2)
    axes: tuple[str, ...]
    basis: str             # poly1..3, product, exp, field2, field3, common
    window: bool = False   # noise shared by neighbours through the matching window (window_px)

    @property
    def name(self) -> str:
        return f"term_{self.quantity}_{'_'.join(self.axes)}_{self.basis}" + ("_window" if self.window else "")

    @property
    def coefficients(self) -> tuple[str, ...]:
        if self.basis.startswith("poly"):
            return tuple(f"c{k}" for k in range(1, int(self.basis[4:]) + 1))
        if self.basis.startswith("field"):
            return tuple(f"c_{t}" for t in FIELD_TERMS[int(self.basis[5:])])
        return ("c",)

    @property
    def powers(self) -> tuple[int, ...]:
        """Exponents of a polynomial's monomials: 1, 2, 3; a noise along distance 2, 4, 6."""
        n = len(self.coefficients)
        step = 2 if (self.quantity == "noise" and self.axes == ("distance",)) else 1
        return tuple(step * k for k in range(1, n + 1))

    @property
    def unit(self) -> str:
        return "px" if self.quantity == "bias" else "px^2"

    def coefficient_unit(self, coef: str) -> str:
        """Unit of one coefficient: the quantity's unit per unit of the axis powers it multiplies."""
        base = self.unit
        if self.basis.startswith("poly"):
            u = AXIS_INFO[self.axes[0]][1]
            k = self.powers[int(coef[1:]) - 1]
            return base if u == "1" else f"{base}/{u}" + (f"^{k}" if k > 1 else "")
        if self.basis == "product":
            units = [AXIS_INFO[a][1] for a in self.axes if AXIS_INFO[a][1] != "1"]
            if not units:
                return base
            return f"{base}/({'*'.join(units)})" if len(units) > 1 else f"{base}/{units[0]}"
        return base

    @property
    def fixed(self) -> dict[str, tuple[float, str, str]]:
        """Parameters that are not fitted: references of centred axes, the edge decay length."""
        out: dict[str, tuple[float, str, str]] = {}
        for a in self.axes:
            if a in REFERENCE:
                unit = AXIS_INFO[a][1]
                out[REFERENCE[a]] = (0.0, unit, f"{a} at which the term is zero")
        if self.basis == "exp":
            out["length_px"] = (5.0, "px", "decay length away from the edge")
        if self.window:
            out["window_px"] = (9.0, "px", "width of the matching window that shares the noise")
        return out

    def expression(self, values: dict[str, float] | None = None) -> str:
        """A readable formula with units, e.g. 'delta_d = c1*y + c2*y^2 [px]; y = (v - ppy) / fx'."""
        lhs = "delta_d" if self.quantity == "bias" else "var_d"
        if self.basis.startswith("poly"):
            s = AXIS_INFO[self.axes[0]][0]
            terms = [f"{c}*{s}" + (f"^{k}" if k > 1 else "") for k, c in zip(self.powers, self.coefficients,
                                                                           strict=True)]
        elif self.basis == "product":
            terms = ["c*" + "*".join(AXIS_INFO[a][0] for a in self.axes)]
        elif self.basis == "exp":
            terms = ["c*exp(-e/length_px)"]
        elif self.basis.startswith("field"):
            terms = [f"c_{t}*" + "*".join(t) for t in FIELD_TERMS[int(self.basis[5:])]]
        else:
            terms = ["c (one draw per frame, shared by all its pixels)"]
        if values:
            for c in self.coefficients:
                if c in values:
                    terms = [t.replace(f"{c}*", f"({values[c]:.4g})*", 1) if t.startswith(f"{c}*") else t
                             for t in terms]
        axes = [a for a in self.axes if a in AXIS_INFO]
        if self.basis.startswith("field"):
            axes = ["u", "v"]
        defs = "; ".join(AXIS_INFO[a][2] for a in axes)
        text = f"{lhs} = {' + '.join(terms)} [{self.unit}]"
        if self.quantity == "noise" and self.basis != "common":
            text += " (clipped at 0" + (", shared over a window_px box)" if self.window else ")")
        return text + (f"; {defs}" if defs else "")


def parse_term(name: str) -> TermSpec | None:
    """The spec of a generic term's name, or None when the name is not one (catalogue names)."""
    m = _NAME.match(name)
    if not m:
        return None
    quantity, axes_s, basis, window = m.groups()
    axes = tuple(axes_s.split("_"))
    if any(a not in AXES for a in axes):
        raise SimulationError(f"generic term '{name}': axes must be from {', '.join(AXES)}")
    ok = ((basis.startswith("poly") and len(axes) == 1 and axes[0] not in ("tile", "frame", "edge"))
          or (basis == "product" and len(axes) == 2 and not set(axes) & {"tile", "frame", "edge"})
          or (basis == "exp" and axes == ("edge",))
          or (basis.startswith("field") and axes == ("tile",))
          or (basis == "common" and axes == ("frame",) and quantity == "noise"))
    if not ok or (window and (quantity != "noise" or basis == "common")):
        raise SimulationError(f"generic term '{name}': basis '{basis}' does not go with axes {list(axes)}")
    return TermSpec(quantity, axes, basis, bool(window))


def axis_value(ctx: PixelContext, axis: str, params: dict[str, float]) -> Array:
    """The variable of one axis for every entry of the context (see the module docstring)."""
    f = float(ctx.fx)
    if axis == "u":
        return np.asarray((np.asarray(ctx.u, dtype=np.float64) - ctx.ppx) / f)
    if axis == "v":
        return np.asarray((np.asarray(ctx.v, dtype=np.float64) - ctx.ppy) / f)
    if axis == "radius":
        return np.asarray(np.hypot(axis_value(ctx, "u", params), axis_value(ctx, "v", params)))
    if axis == "distance":
        return np.asarray(ctx.z_m, dtype=np.float64)
    if axis == "disparity":
        return np.asarray(ctx.disparity_px())
    if axis == "inclination":
        return np.asarray(np.radians(np.asarray(ctx.inclination_deg, dtype=np.float64)))
    if axis == "albedo":
        return np.asarray(1.0 - np.asarray(ctx.albedo, dtype=np.float64))
    if axis == "time":
        return np.asarray(np.asarray(ctx.time_s, dtype=np.float64) - params.get("ref_time_s", 0.0))
    if axis == "temperature":
        t = np.asarray(ctx.temperature_c, dtype=np.float64) - params.get("ref_temperature_c", 0.0)
        return np.asarray(np.where(np.isfinite(t), t, 0.0))
    if axis == "edge":
        return np.asarray(ctx.edge_distance_px, dtype=np.float64)
    raise SimulationError(f"axis '{axis}' has no per-pixel variable")


def basis_columns(spec: TermSpec, ctx: PixelContext, params: dict[str, float]) -> list[Array]:
    """The term's value per unit of each coefficient (same order as `spec.coefficients`)."""
    shape = ctx.shape()
    if spec.basis.startswith("poly"):
        a = axis_value(ctx, spec.axes[0], params)
        cols = [a ** k for k in spec.powers]
    elif spec.basis == "product":
        cols = [axis_value(ctx, spec.axes[0], params) * axis_value(ctx, spec.axes[1], params)]
    elif spec.basis == "exp":
        e = axis_value(ctx, "edge", params)
        cols = [np.where(np.isfinite(e), np.exp(-np.maximum(e, 0.0) / params.get("length_px", 5.0)), 0.0)]
    elif spec.basis.startswith("field"):
        x, y = axis_value(ctx, "u", params), axis_value(ctx, "v", params)
        cols = [np.prod([x if ch == "x" else y for ch in t], axis=0)
                for t in FIELD_TERMS[int(spec.basis[5:])]]
    else:
        cols = [np.ones(shape)]
    return [np.broadcast_to(np.asarray(c, dtype=np.float64), shape) for c in cols]


class _Term:
    """What every generic term class shares: its spec and the value of its expression."""

    spec: ClassVar[TermSpec]
    params: dict[str, float]

    def value(self, ctx: PixelContext) -> Array:
        cols = basis_columns(self.spec, ctx, self.params)
        out = np.zeros(ctx.shape())
        for c, col in zip(self.spec.coefficients, cols, strict=True):
            out = out + self.params[c] * col
        return out


class GenericShift(_Term, DisparityShift):
    """A generic bias term: disparity shift = the term's expression (px)."""

    def shift_px(self, ctx: PixelContext) -> Array:
        return self.value(ctx)


class GenericNoise(_Term, DisparityJitter):
    """A generic noise term: added disparity variance = the term's expression (px^2, clipped at 0)."""

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(np.sqrt(np.clip(self.value(ctx), 0.0, None)))


class GenericWindowNoise(_Term, CorrelatedJitter):
    """A generic noise term shared by neighbours through the matching window (window_px)."""

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(np.sqrt(np.clip(self.value(ctx), 0.0, None)))


class GenericFrameNoise(_Term, FrameJitter):
    """A frame-common noise term: one disparity draw per frame of variance c (px^2), all pixels alike."""

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(np.sqrt(max(self.params["c"], 0.0)))


_CLASSES: dict[str, type[Effect]] = {}


def term_class(name: str) -> type[Effect] | None:
    """The effect class of a generic term's name (built once per name), None for other names."""
    spec = parse_term(name)
    if spec is None:
        return None
    if name in _CLASSES:
        return _CLASSES[name]
    base: type[Effect] = (GenericFrameNoise if spec.basis == "common" else
                          GenericShift if spec.quantity == "bias" else
                          GenericWindowNoise if spec.window else GenericNoise)
    params: dict[str, tuple[float, str, str]] = {
        c: (0.0, spec.coefficient_unit(c), "coefficient of the term") for c in spec.coefficients}
    params.update(spec.fixed)
    cls = type(f"Term_{name}", (base,), {
        "name": name, "spec": spec, "PARAMS": params,
        "meaning": f"generic {spec.quantity} term along {', '.join(spec.axes)}: {spec.expression()}",
        "time_dependent": bool({"time", "temperature"} & set(spec.axes)),
        "__doc__": f"Generic term {name} (see simulate.effects.generic).",
    })
    _CLASSES[name] = cls
    return cls


# axes whose variable is >= 0 wherever it is evaluated (u, v, time, temperature change sign)
NON_NEGATIVE_AXES = {"radius", "distance", "disparity", "inclination", "albedo", "edge"}


def never_positive(spec: TermSpec, params: dict[str, float]) -> bool:
    """Whether the term's value is <= 0 everywhere and < 0 somewhere: every basis column is >= 0
    and no coefficient is positive, one negative (for other bases the sign is not decided here)."""
    coefs = [float(params.get(c, 0.0)) for c in spec.coefficients]
    if not coefs or max(coefs) > 0 or min(coefs) >= 0:
        return False
    if spec.basis in ("common", "exp"):
        return True
    if spec.basis.startswith("poly"):
        return spec.axes[0] in NON_NEGATIVE_AXES or all(k % 2 == 0 for k in spec.powers)
    if spec.basis == "product":
        return all(a in NON_NEGATIVE_AXES for a in spec.axes)
    return False


def term_spec(effect: Effect | type[Effect]) -> TermSpec | None:
    """The spec of a generic term effect (None for catalogue effects)."""
    return getattr(effect, "spec", None) if isinstance(getattr(effect, "spec", None), TermSpec) else None


def term_value(spec: TermSpec, ctx: PixelContext, params: dict[str, Any]) -> Array:
    """The expression's value (px or px^2) for given coefficients, without building an effect."""
    cols = basis_columns(spec, ctx, {k: float(v) for k, v in params.items()})
    return np.asarray(sum(float(params.get(c, 0.0)) * col
                          for c, col in zip(spec.coefficients, cols, strict=True)))
