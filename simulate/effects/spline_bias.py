"""A disparity bias along one axis given by a natural cubic spline through equally spaced knots."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext

MAX_KNOTS = 8
SPLINE_AXES = ("u", "v", "distance", "inclination")   # axis code 0..3


def spline_basis(x: Array, lo: float, hi: float, knots: int) -> NDArray[np.float64]:
    """(len(x), knots): the natural cubic spline through the unit vector of each knot, equally
    spaced on [lo, hi], held at its end value outside. The spline is linear in the knot values, so
    a fit is a least-squares problem in these columns."""
    from scipy.interpolate import CubicSpline  # scipy.interpolate costs 0.3 s at every start

    x = np.clip(np.asarray(x, dtype=np.float64).ravel(), lo, hi)
    grid = np.linspace(lo, hi, knots)
    return np.asarray(CubicSpline(grid, np.eye(knots), bc_type="natural")(x), dtype=np.float64)


def axis_values(ctx: PixelContext, axis: int) -> Array:
    """The spline's axis at every entry: u or v (px), z (m) or the inclination (deg)."""
    return np.asarray((ctx.u, ctx.v, ctx.z_m, ctx.inclination_deg)[axis], dtype=np.float64)


class SplineBias(DisparityShift):
    """d_meas = d + s(a), s the natural cubic spline through (a_k, c_k), a_k equally spaced on
    [lo, hi] (`knots` of them), s held at its end values outside; a = u, v (px), z (m) or the
    inclination (deg) (`axis` 0..3).

    A located bias along one axis whose shape no polynomial of the library holds (a bump of the
    rectification along a column band, an error that bends at one range): explain writes it when a
    region along that axis still differs after the refit, and keeps it only where it predicts
    held-out standpoints better.
    """

    name: ClassVar[str] = "spline_bias"
    meaning: ClassVar[str] = "a disparity bias along one axis (u, v, distance or inclination), a cubic spline"
    source: ClassVar[str] = ("explain: a located residual along one axis outside the catalogue and the "
                             "polynomial library, fitted as a natural cubic spline")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "axis": (0.0, "1", "0: u (px), 1: v (px), 2: distance z (m), 3: inclination (deg)"),
        "lo": (0.0, "axis unit", "first knot"),
        "hi": (1.0, "axis unit", "last knot"),
        "knots": (2.0, "1", f"number of knots, 2..{MAX_KNOTS}, equally spaced on [lo, hi]"),
        **{f"c{k}": (0.0, "px", f"disparity bias at knot {k}") for k in range(MAX_KNOTS)},
    }

    def validate(self) -> None:
        p = self.params
        if p["axis"] not in (0.0, 1.0, 2.0, 3.0) or p["knots"] not in range(2, MAX_KNOTS + 1):
            raise ValueError(f"axis 0..3 and knots an integer 2..{MAX_KNOTS} required")
        if not p["hi"] > p["lo"]:
            raise ValueError(f"hi > lo required (got lo {p['lo']:g}, hi {p['hi']:g})")
        if not all(np.isfinite(p[f"c{k}"]) for k in range(MAX_KNOTS)):
            raise ValueError("finite knot values c0.. required")

    def shift_px(self, ctx: PixelContext) -> Array:
        p = self.params
        n = int(p["knots"])
        a = axis_values(ctx, int(p["axis"]))
        c = np.array([p[f"c{k}"] for k in range(n)])
        return np.asarray((spline_basis(a, p["lo"], p["hi"], n) @ c).reshape(np.shape(a)))
