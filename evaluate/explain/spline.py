"""A spline along one axis for a located bias that the refit leaves: the non-parametric term.

When a bias region along u, v, distance or inclination still differs after the refit (no catalogue
effect and no polynomial of the library holds its shape: a bump over a band of columns, an error
that bends at one range), the real-minus-re-simulated disparity residual along that axis is fitted
as a natural cubic spline (`simulate.effects.spline_bias`, linear in its knot values) and kept only
where it predicts held-out standpoints better (leave one standpoint out). Along u and v each
standpoint keeps its own offset and slope (its reference pose's plane): the spline holds only the
shape no plane can, its linear part taken out. Along distance and inclination every standpoint is
one point (its mean residual, weighted by its frame scatter and the standpoints' heterogeneity).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from depthstation.evaluate.explain.samples import FloatArray, Samples, standpoint_map
from depthstation.simulate.effects.spline_bias import MAX_KNOTS, SPLINE_AXES, spline_basis

# locate families whose significant bias calls for a spline along this axis
FAMILY_SPLINE_AXIS = {"column": "u", "periodic_u": "u", "gradient_u": "u",
                      "row": "v", "periodic_v": "v", "gradient_v": "v",
                      "distance": "distance", "disparity": "distance", "inclination": "inclination"}
LINE_BIN_PX = 8.0          # width of the image bins a standpoint's profile is cut into (stereo px)
MIN_STANDPOINTS = 4
MIN_BINS = 6               # bins a standpoint needs along u / v


@dataclass
class SplineFit:
    axis: str
    lo: float
    hi: float
    knots: int
    values_px: FloatArray
    heldout_rmse_before_px: float
    heldout_rmse_after_px: float
    standpoints: int

    def params(self) -> dict[str, float]:
        p = {"axis": float(SPLINE_AXES.index(self.axis)), "lo": self.lo, "hi": self.hi,
             "knots": float(self.knots)}
        return {**p, **{f"c{k}": float(v) for k, v in enumerate(self.values_px)}}


def _axis(s: Samples, axis: str) -> FloatArray:
    """The axis as the simulator's effects see it: u, v in depth-image pixels (`u_px`, the lattice it
    renders), z, inclination."""
    values = {"u": s.u_px, "v": s.v_px, "distance": s.z_ref_m, "inclination": s.inclination_deg}
    return np.asarray(values[axis], dtype=np.float64)


def _cells(real: Samples, sim: Samples, axis: str) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """Per standpoint both sides have: (axis value, real - sim mean disparity residual, weight) per
    bin (u, v) or one entry (distance, inclination). Weights are pixel counts (u, v) or the inverse of
    the frame-mean variance of the standpoint's difference."""
    dr, ds = -real.err_m / real.k_m_per_px, -sim.err_m / sim.k_m_per_px
    ar, as_ = _axis(real, axis), _axis(sim, axis)
    to_real = standpoint_map(real, sim)
    sp_sim = to_real[sim.standpoint] if len(sim) else np.zeros(0, np.int64)
    out = []
    for k in np.unique(real.standpoint):
        mr, ms = real.standpoint == k, sp_sim == k
        if mr.sum() < 30 or ms.sum() < 30:
            continue
        if axis in ("u", "v"):
            br = np.floor(ar[mr] / LINE_BIN_PX).astype(np.int64)
            bs = np.floor(as_[ms] / LINE_BIN_PX).astype(np.int64)
            lo = min(br.min(), bs.min())
            nb = max(br.max(), bs.max()) - lo + 1
            nr = np.bincount(br - lo, minlength=nb)
            ns = np.bincount(bs - lo, minlength=nb)
            ok = (nr >= 10) & (ns >= 10)
            if ok.sum() < MIN_BINS:
                continue
            mean_r = np.bincount(br - lo, weights=dr[mr], minlength=nb)[ok] / nr[ok]
            mean_s = np.bincount(bs - lo, weights=ds[ms], minlength=nb)[ok] / ns[ok]
            x = np.bincount(br - lo, weights=ar[mr], minlength=nb)[ok] / nr[ok]
            out.append((x, mean_r - mean_s, np.minimum(nr[ok], ns[ok]).astype(np.float64)))
        else:
            fr = _frame_means(dr[mr], real.frame[mr])
            fs = _frame_means(ds[ms], sim.frame[ms])
            if len(fr) < 2 or len(fs) < 2:
                continue
            var = fr.var(ddof=1) / len(fr) + fs.var(ddof=1) / len(fs)
            out.append((np.array([ar[mr].mean()]), np.array([fr.mean() - fs.mean()]),
                        np.array([1.0 / max(var, 1e-12)])))
    return out


def _frame_means(d: FloatArray, frame: Any) -> FloatArray:
    _, inv = np.unique(frame, return_inverse=True)
    n = np.bincount(inv.ravel())
    return np.asarray(np.bincount(inv.ravel(), weights=d) / n, dtype=np.float64)


def _design(cells: list[tuple[FloatArray, FloatArray, FloatArray]], lo: float, hi: float, knots: int,
            nuisance: bool) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Stacked design: spline columns, then per standpoint an offset and a slope (u, v)."""
    x = np.concatenate([c[0] for c in cells])
    y = np.concatenate([c[1] for c in cells])
    w = np.concatenate([c[2] for c in cells])
    cols = [spline_basis(x, lo, hi, knots)]
    if nuisance:
        sp = np.concatenate([np.full(len(c[0]), i) for i, c in enumerate(cells)])
        onehot = (sp[:, None] == np.arange(len(cells))[None, :]).astype(np.float64)
        xc = (x - 0.5 * (lo + hi)) / (hi - lo)
        cols += [onehot, onehot * xc[:, None]]
    return np.concatenate(cols, axis=1), y, w


def _solve(X: FloatArray, y: FloatArray, w: FloatArray) -> FloatArray:
    sw = np.sqrt(w)
    beta, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    return np.asarray(beta)


def _knot_values(cells: list[tuple[FloatArray, FloatArray, FloatArray]], lo: float, hi: float,
                 knots: int, nuisance: bool) -> FloatArray:
    """The knot values fitted; along u, v without their linear part (the standpoints' planes hold
    any offset and slope, so the spline's own are not determined: the minimum-norm solution's
    linear part is removed at the knots, which leaves the same shape)."""
    X, y, w = _design(cells, lo, hi, knots, nuisance)
    c = _solve(X, y, w)[:knots]
    if nuisance:
        grid = np.linspace(lo, hi, knots)
        a, b = np.polyfit(grid, c, 1)
        c = c - (a * grid + b)
    return np.asarray(c)


def _residual_rms(cells: list[tuple[FloatArray, FloatArray, FloatArray]], pred: list[FloatArray],
                  nuisance: bool) -> float:
    """Weighted RMS of each held-out standpoint's cells minus the prediction, its own plane taken
    out (u, v) as the fit took it out."""
    ss, ws = 0.0, 0.0
    for (x, y, w), p in zip(cells, pred, strict=True):
        r = y - p
        if nuisance:
            X = np.stack([np.ones_like(x), x], axis=1)
            r = r - X @ _solve(X, r, w)
        ss += float((w * r * r).sum())
        ws += float(w.sum())
    return float(np.sqrt(ss / ws)) if ws > 0 else float("nan")


def fit_spline(real: Samples, sim: Samples, axis: str) -> SplineFit | None:
    """The spline along `axis` with the knot count that predicts held-out standpoints best; None when
    too few standpoints or no knot count predicts them better than no term."""
    cells = _cells(real, sim, axis)
    if len(cells) < MIN_STANDPOINTS:
        return None
    nuisance = axis in ("u", "v")
    x_all = np.concatenate([c[0] for c in cells])
    lo, hi = float(np.quantile(x_all, 0.01)), float(np.quantile(x_all, 0.99))
    if not hi > lo:
        return None
    distinct = len(np.unique(np.round(x_all, 3)))
    top = min(MAX_KNOTS, distinct // 2 if not nuisance else MAX_KNOTS, len(cells) - 1)
    zeros = [np.zeros_like(c[1]) for c in cells]
    before = _residual_rms(cells, zeros, nuisance)
    best: SplineFit | None = None
    for knots in range(3, top + 1):
        pred = []
        for i in range(len(cells)):
            others = cells[:i] + cells[i + 1:]
            c = _knot_values(others, lo, hi, knots, nuisance)
            pred.append(spline_basis(cells[i][0], lo, hi, knots) @ c)
        after = _residual_rms(cells, pred, nuisance)
        if after < before and (best is None or after < best.heldout_rmse_after_px):
            best = SplineFit(axis, lo, hi, knots, _knot_values(cells, lo, hi, knots, nuisance), before, after,
                             len(cells))
    return best


def spline_term(regions: list[Any], real: Samples, resim: Samples) -> dict[str, Any] | None:
    """The spline the significant bias regions after the refit call for (one axis: the model holds
    one `spline_bias`), as a model term like fine.fine_terms' entries; None when none predicts held-out
    standpoints better."""
    axes: dict[str, float] = {}
    for t in regions:
        ax = FAMILY_SPLINE_AXIS.get(t.family)
        if t.significant and t.kind == "bias" and ax is not None:
            axes[ax] = min(axes.get(ax, 1.0), float(t.p))
    fits = [f for f in (fit_spline(real, resim, ax) for ax in sorted(axes, key=axes.__getitem__)) if f]
    if not fits:
        return None
    f = max(fits, key=lambda f: 1 - f.heldout_rmse_after_px / f.heldout_rmse_before_px)
    fam = sorted(t.family for t in regions if FAMILY_SPLINE_AXIS.get(t.family) == f.axis and t.significant)
    return {"effect": "spline_bias", "family": fam[0] if fam else f.axis, "axis": f.axis,
            "params": f.params(), "heldout_rmse_before_px": f.heldout_rmse_before_px,
            "heldout_rmse_after_px": f.heldout_rmse_after_px, "standpoints": f.standpoints}
