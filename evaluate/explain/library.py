"""The library of generic terms that discovery fits when the catalogue leaves a residual.

Every term lives in the physics' own domain: a bias term is a disparity shift (px), a noise term an
added disparity variance (px^2), along the axes of explain's vocabulary (simulate.effects.generic).
Its fit columns are first-order: a disparity shift phi (px) moves z by -K phi and adds K^2 phi to
the z variance, K = z^2/(fB). The library, simplest first:

- bias: polynomials of degree 1-3 along u, v, radius, distance, disparity, inclination, time,
  temperature; a decay from the board edge; products of two axes; a smooth field over the image
  (polynomial in x, y of degree 2 and 3: fixed-pattern distortion, the CLAMS idea).
- noise: polynomials of degree 1-2 along every axis, a decay from the edge, a smooth field, and the
  frame-common term (one draw per frame, fitted on the frame-common table).

`INTERPRETATION` says which physical causes produce each signature (docs/explain.md, "What a
discovered signature means", with the references).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from depthstation.evaluate.explain.basis import Candidate
from depthstation.evaluate.explain.samples import FloatArray, Samples
from depthstation.simulate.effects import PixelContext
from depthstation.simulate.effects.base import box_correlation
from depthstation.simulate.effects.generic import REFERENCE, TermSpec, basis_columns

BIAS_AXES = ("u", "v", "radius", "distance", "disparity", "inclination", "time", "temperature")
NOISE_AXES = ("u", "v", "radius", "distance", "disparity", "inclination", "albedo", "time", "temperature")
PRODUCTS = (("u", "v"), ("u", "distance"), ("v", "distance"), ("u", "inclination"), ("v", "inclination"),
            ("distance", "inclination"), ("u", "time"), ("v", "time"), ("distance", "time"),
            ("u", "temperature"), ("v", "temperature"), ("distance", "temperature"), ("radius", "distance"))
EDGE_LENGTHS_PX = (2.0, 6.0)

# (quantity, axes) -> physical causes of that signature (research note "physics-signatures", table 1)
INTERPRETATION: dict[tuple[str, tuple[str, ...]], tuple[str, ...]] = {
    ("bias", ("u",)): (
        "left/right focal-length (magnification) mismatch left in rectification: delta = -eps (u - cx) "
        "+ eps d, linear in u with a depth-scale part [derived; thermal focus change of one lens]",
        "relative yaw of the right imager: constant plus x^2 (even in u), with vertical misalignment",
        "differential radial distortion: -f dk x r^2, odd and cubic in u [Herrera et al. 2012]"),
    ("bias", ("v",)): (
        "relative roll of the right imager about the optical axis: delta = -f roll y, linear in v "
        "(on one board it looks like a tilt about x; identified across standpoints) [derived]",
        "vertical misalignment on oriented texture (aperture effect) from a roll or pitch error",
        "rolling-shutter skew of a moving camera (D415)"),
    ("bias", ("radius",)): (
        "uncorrected lens distortion: a common residual k gives delta = k d (3x^2 + y^2) (grows with z "
        "in depth), a differential one -f dk x r^2 [derived; Herrera et al. 2012]",
        "vignetting-linked SNR falling towards the corners (an isotropic r^2 that scales like z^2)"),
    ("bias", ("tile",)): (
        "the unit's static pattern (catalogue `static_pattern`): fixed-pattern rectification residuals, "
        "distortion-model mismatch and the emitter's dot pattern fixed to the unit, a smooth disparity field "
        "fixed in pixel coordinates that frames do not average away (Smisek et al. 2011; Herrera et al. "
        "2012; CLAMS, Teichman et al. 2013)",
        "relative pitch (x y saddle) or differential tangential distortion p1, p2"),
    ("bias", ("distance",)): (
        "convexity of z = fB/d: zero-mean disparity noise biases the mean depth by z^3 sigma_d^2/(fB)^2 "
        "(a noise difference shows as a bias) [derived]",
        "range-dependent subpixel bias (lower texture SNR far away) [Shimizu & Okutomi 2005]"),
    ("bias", ("disparity",)): (
        "baseline or common focal-length error: delta proportional to d, a depth scale "
        "[Keselman et al. 2017]",
        "disparity-dependent subpixel interpolation bias (pixel locking between integers) "
        "[Shimizu & Okutomi 2005; Intel subpixel linearity white paper]"),
    ("bias", ("inclination",)): (
        "fronto-parallel window assumption: scanline/SGM penalties favour constant disparity on slanted "
        "surfaces; larger at near range [Hirschmueller 2008; Kanade & Okutomi 1994]",
        "non-uniform texture weight inside the foreshortened window"),
    ("bias", ("time",)): (
        "warm-up: thermal bending of the stereo head (relative yaw) while the device settles",
        "auto-exposure convergence or laser-power ramp after stream start; host temporal-filter warm-up"),
    ("bias", ("temperature",)): (
        "thermal bending of the stereo head (relative yaw; D45x thermal loop) or lens focal drift "
        "[librealsense thermal compensation PRs and issues]",),
    ("bias", ("edge",)): (
        "edge fattening: the window straddles the board's depth edge and pulls the disparity of nearby "
        "pixels towards the other surface [Scharstein & Szeliski 2002; Hirschmueller et al. 2002]",),
    ("noise", ("distance",)): (
        "projector dot irradiance falls like 1/z^2: read-noise-limited sigma_d grows like z^2, "
        "shot-limited like z, so depth noise grows faster than z^2 [derived; Carfagni et al. 2019; "
        "Servi et al. 2021]",
        "auto exposure and laser power partly compensate; ambient light moves the break point"),
    ("noise", ("disparity",)): (
        "the same SNR law as along distance (d = fB/z): pattern contrast falls with range",),
    ("noise", ("inclination",)): (
        "foreshortened dots and Lambertian fall-off lower the SNR like cos(theta); the disparity "
        "gradient across the window decorrelates it [Kanade & Okutomi 1994; Nguyen et al. 2012]",),
    ("noise", ("albedo",)): (
        "less infrared back from dark print: lower pattern contrast (sigma_d^2 ~ 1/rho .. 1/rho^2)",
        "saturation of bright squares at short range, or ink transparent at 850 nm"),
    ("noise", ("u",)): (
        "vertical misalignment growing across the image (roll: e_v ~ x) degrades matching "
        "[derived]", "vignetting, projector beam profile and lens MTF fall-off"),
    ("noise", ("v",)): (
        "vertical misalignment growing along v (focal mismatch: e_v ~ y) degrades matching [derived]",
        "vignetting, projector beam profile and lens MTF fall-off"),
    ("noise", ("radius",)): (
        "vignetting and lens MTF fall-off towards the corners; projector beam profile [Intel projector "
        "white paper]",),
    ("noise", ("tile",)): (
        "projector beam profile and overlap, vignetting, a field of vertical misalignment",),
    ("noise", ("time",)): (
        "laser power or exposure changing during warm-up; projector temperature",),
    ("noise", ("temperature",)): (
        "projector and imager temperature: laser power, dark current",),
    ("noise", ("edge",)): (
        "mixed (flying) pixels and the occlusion band near the board's depth edge",),
    ("noise", ("frame",)): (
        "something common to all pixels of a frame: micro-thermal yaw jitter of the stereo head, "
        "laser-power or auto-exposure steps, emitter on/off alternation, ambient flicker aliasing "
        "against the frame rate, mount vibration [Intel BKM; research note N6]",
        "or the board pose from the colour image jittering more than the simulated one (the reference "
        "moves with the frame)"),
}
PRODUCT_INTERPRETATION = (
    "an interaction: the cause along the first axis changes with the second (e.g. a pixel-position "
    "error whose size grows with range or temperature); no single catalogued cause",)


def interpretation(quantity: str, axes: tuple[str, ...]) -> tuple[str, ...]:
    """The causes of a signature; products of two axes get the generic interaction reading."""
    if (quantity, axes) in INTERPRETATION:
        return INTERPRETATION[(quantity, axes)]
    if (quantity, axes) == ("bias", ("u", "v")):
        return INTERPRETATION[("bias", ("tile",))][1:]
    return PRODUCT_INTERPRETATION


def _references(real: Samples, spec: TermSpec) -> dict[str, float]:
    """Fixed references of centred axes: the session's median time and temperature."""
    out: dict[str, float] = {}
    for a in spec.axes:
        if a == "time":
            out[REFERENCE[a]] = float(np.median(real.time_s))
        elif a == "temperature":
            t = real.temperature_c[np.isfinite(real.temperature_c)]
            out[REFERENCE[a]] = float(np.median(t)) if t.size else 0.0
    return out


def _columns(spec: TermSpec, fixed: dict[str, float]) -> Callable[[Samples], FloatArray]:
    """Fit columns of a term: z bias (-K phi) or z variance (K^2 phi) per unit coefficient."""
    def cols(s: Samples) -> FloatArray:
        ctx = PixelContext(**s.context())
        phi = np.stack(basis_columns(spec, ctx, fixed), axis=1)
        k = s.k_m_per_px[:, None]
        out = -k * phi if spec.quantity == "bias" else k * k * phi
        return np.asarray(np.where(np.isfinite(out), out, 0.0))
    return cols


def _candidate(real: Samples, spec: TermSpec, fixed: dict[str, float] | None = None, key: str = ""
               ) -> Candidate:
    fixed = {**_references(real, spec), **(fixed or {})}
    units = tuple(spec.coefficient_unit(c) for c in spec.coefficients)
    kind = "bias" if spec.quantity == "bias" else "variance"
    corr: Callable[[float, float], float] | None = None
    if spec.window:
        def corr(du: float, dv: float, w: float = fixed["window_px"]) -> float:
            return float(box_correlation(w, du, dv))
    return Candidate(spec.name + key, kind, spec.coefficients, units, spec.expression(),
                     _columns(spec, fixed),
                     table="frame" if spec.basis == "common" else "tiles", spec=spec, fixed=fixed,
                     interpretation=interpretation(spec.quantity, spec.axes), correlation=corr)


def _usable_axis(real: Samples, axis: str) -> bool:
    """An axis the data vary along (a term along a constant axis is a constant: not identifiable)."""
    if axis == "time":   # a session clock only (a PNG folder's k / fps repeats the frame's position)
        return real.time_stamps and float(np.ptp(real.time_s)) > 0
    if axis == "temperature":
        t = real.temperature_c[np.isfinite(real.temperature_c)]
        return t.size > 0 and float(np.ptp(t)) > 0.2
    if axis == "albedo":
        return float(np.ptp(real.albedo)) > 0
    if axis == "inclination":
        return float(np.ptp(real.inclination_deg)) > 2.0
    if axis == "edge":
        return bool(np.isfinite(real.edge_px).any())
    return True


def library(real: Samples, window_px: float | None = None) -> list[Candidate]:
    """All generic terms, simplest first (single axes by degree, edge decays, products, fields, frame).

    With `window_px` (the real noise is window-correlated) every noise term comes twice: white, and
    shared over that window (matching noise of any cause passes through the same window); the
    neighbour rows of the variance table tell them apart.
    """
    out: list[Candidate] = []
    for deg in (1, 2, 3):
        for a in BIAS_AXES:
            if _usable_axis(real, a):
                out.append(_candidate(real, TermSpec("bias", (a,), f"poly{deg}")))
    if _usable_axis(real, "edge"):
        for length in EDGE_LENGTHS_PX:
            out.append(_candidate(real, TermSpec("bias", ("edge",), "exp"), {"length_px": length},
                                  key=f"@{length:g}px"))
    for a, b in PRODUCTS:
        if _usable_axis(real, a) and _usable_axis(real, b):
            out.append(_candidate(real, TermSpec("bias", (a, b), "product")))
    out += [_candidate(real, TermSpec("bias", ("tile",), f"field{d}")) for d in (2, 3)]
    noise: list[tuple[TermSpec, dict[str, float]]] = []
    for deg in (1, 2):
        noise += [(TermSpec("noise", (a,), f"poly{deg}"), {}) for a in NOISE_AXES if _usable_axis(real, a)]
    if _usable_axis(real, "edge"):
        noise.append((TermSpec("noise", ("edge",), "exp"), {"length_px": EDGE_LENGTHS_PX[0]}))
    noise.append((TermSpec("noise", ("tile",), "field2"), {}))
    for spec, fixed in noise:
        out.append(_candidate(real, spec, fixed))
        if window_px is not None:
            out.append(_candidate(real, replace(spec, window=True), {**fixed, "window_px": float(window_px)}))
    out.append(_candidate(real, TermSpec("noise", ("frame",), "common")))
    return out
