"""The residual on tiles: the tables that attribute and discover fit.

The residual lives on tiles (standpoint x frame block x pixel tile x black/white): the difference of
mean errors real minus sim (`bias_table`), and separately of temporal variances (`variance_table`)
and of the frame-common noise (`frame_table`). Each candidate effect's signature is averaged over
the same pixels, a column of the table, so a table is a linear model y ~ X beta with weights w;
`mixed_model` fits it. Tiles are at least 2.5 matching windows wide, so that neighbouring tiles do
not share window-correlated noise the fit would count as independent.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.evaluate.explain.basis import Candidate
from depthstation.evaluate.explain.samples import (
    FloatArray,
    IntArray,
    Samples,
    align_standpoints,
    frame_positions,
    standpoint_map,
)
from depthstation.evaluate.explain.structure import Structure, decompose, frame_common

MIN_TILE = 8

NoiseVar = Callable[[Samples], FloatArray]
# per sample: the window-correlated part of the model's noise variance (m^2) and the window (px)
CorrVar = Callable[[Samples], tuple[FloatArray, float]]


@dataclass
class Table:
    """Tile-level regression data: y ~ X beta with weights w."""

    kind: str                       # "bias" or "variance"
    y: FloatArray
    w: FloatArray
    X: dict[str, FloatArray]
    cluster: IntArray
    fold: IntArray
    standpoint: IntArray
    Z: FloatArray | None = None     # random reference-plane error basis z^2 (1, x/z, y/z) per tile
    group: IntArray | None = None   # rows sharing one reference-plane error (a standpoint)
    T: FloatArray | None = None     # KNOWN prior covariance of the plane coefficients (from the sim)
    block: IntArray | None = None   # frame block of each row (a nested plane error per block)
    name: str = ""                  # "bias", "variance" (tiles and neighbour rows) or "frame"

    def __post_init__(self) -> None:
        self.name = self.name or self.kind

    def __len__(self) -> int:
        return int(self.y.size)



def frame_blocks(s: Samples, blocks: int, like: Samples | None = None) -> IntArray:
    """Block index of every sample: the frames of each standpoint in time order cut into `blocks`
    (the frames of `like`, the real side, when given: both sides' blocks hold the same frames)."""
    pos, count = frame_positions(s, like)
    nb = np.maximum(1, np.minimum(blocks, count))
    return np.asarray(pos * nb // count, dtype=np.int64)


def _tile_keys(s: Samples, tile_px: float, block: IntArray) -> NDArray[np.int64]:
    tu = np.clip(np.floor(s.u / tile_px), 0, 9999).astype(np.int64)
    tv = np.clip(np.floor(s.v / tile_px), 0, 9999).astype(np.int64)
    alb = (s.albedo >= 0.5).astype(np.int64)
    return np.stack([s.standpoint, block, tv, tu, alb], axis=1)


def _aggregate(keys: NDArray[np.int64], values: FloatArray) -> tuple[NDArray[np.int64], FloatArray,
                                                                      FloatArray, FloatArray, IntArray]:
    ok = np.isfinite(values)
    kk = keys[ok]
    _, first, inv = np.unique(_row_keys(kk), return_index=True, return_inverse=True)
    uniq = kk[first]
    inv = inv.ravel()
    n = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    s1 = np.bincount(inv, weights=values[ok], minlength=len(uniq))
    s2 = np.bincount(inv, weights=values[ok] ** 2, minlength=len(uniq))
    mean = s1 / n
    var = np.maximum(s2 / n - mean ** 2, 0.0) * n / np.maximum(n - 1, 1)
    full_inv = np.full(len(values), -1, dtype=np.int64)
    full_inv[np.flatnonzero(ok)] = inv
    return uniq, n, mean, var, full_inv


def _row_keys(rows: NDArray[np.int64]) -> NDArray[np.int64]:
    """Rows of (standpoint, block, tile v, tile u, albedo) as one int64 with a fixed radix."""
    key = np.zeros(len(rows), dtype=np.int64)
    for j, radix in enumerate(_RADIX):
        key = key * radix + rows[:, j]
    return key


_RADIX = (1, 4096, 10_000, 10_000, 2)


def _match(a: NDArray[np.int64], b: NDArray[np.int64]) -> tuple[IntArray, IntArray]:
    """Indices ia, ib of rows present in both key tables."""
    _, ia, ib = np.intersect1d(_row_keys(a), _row_keys(b), assume_unique=True, return_indices=True)
    return ia.astype(np.int64), ib.astype(np.int64)


def default_tile_px(s: Samples) -> float:
    return max(8.0, round((2 * s.ppx + 1) / 24))


def _folds(standpoint: IntArray, block: IntArray) -> IntArray:
    if len(np.unique(standpoint)) >= 3:
        return standpoint.copy()
    return block.copy()


def bias_table(real: Samples, sim: Samples, candidates: Sequence[Candidate], *, blocks: int = 4,
               tile_px: float | None = None, noise_var: NoiseVar | None = None,
               corr_var: CorrVar | None = None, density: FloatArray | None = None) -> Table:
    """Tiles of mean error real minus sim, each candidate's signature averaged over the real pixels.

    A tile mean's variance is the model's noise over the tile's pixels; the window-correlated part
    (`corr_var`) counts with its design factor D = 1 + density (w^2 - 1) (at most the pixels of a
    frame): neighbours inside one window are one sample, not w^2 (effective sample size).
    """
    tp = default_tile_px(real) if tile_px is None else tile_px
    br, bs = frame_blocks(real, blocks), frame_blocks(sim, blocks, like=real)
    sim_sp = align_standpoints(real, sim)
    kr = _tile_keys(real, tp, br)
    ks = _tile_keys(sim, tp, bs)
    ks[:, 0] = sim_sp
    ur, nr, mr, vr, inv_r = _aggregate(kr, real.err_m)
    us, ns, ms, vs, _ = _aggregate(ks[sim_sp >= 0], sim.err_m[sim_sp >= 0])
    ia, ib = _match(ur, us)
    keep = (nr[ia] >= MIN_TILE) & (ns[ib] >= MIN_TILE)
    ia, ib = ia[keep], ib[keep]
    y = mr[ia] - ms[ib]
    if noise_var is not None:
        pv = noise_var(real)
        ok = inv_r >= 0
        sig2 = np.bincount(inv_r[ok], weights=pv[ok], minlength=len(ur)) / np.maximum(nr, 1)
        var_y = sig2[ia] / nr[ia] + sig2[ia] / ns[ib]
        if corr_var is not None:
            cv, window = corr_var(real)
            c2 = np.bincount(inv_r[ok], weights=cv[ok], minlength=len(ur)) / np.maximum(nr, 1)
            frames = _frames_per_block(real, br)
            n_frame = nr / np.maximum(frames[ur[:, 0], ur[:, 1]], 1)
            lam = density[ur[:, 0]] if density is not None else np.ones(len(ur))
            d = np.minimum(1.0 + lam * (window ** 2 - 1.0), np.maximum(n_frame, 1.0))
            var_y = var_y + (c2[ia] * (d[ia] - 1.0)) * (1.0 / nr[ia] + 1.0 / ns[ib])
    else:
        var_y = vr[ia] / nr[ia] + vs[ib] / ns[ib]
    floor = np.median(var_y) * 1e-3 + 1e-18
    w = 1.0 / np.maximum(var_y, floor)
    X = _tile_columns(candidates, "bias", real, inv_r, nr, ia)
    sp, bl = ur[ia, 0], ur[ia, 1]
    Z = _plane_tiles(real, inv_r, len(ur))[ia]
    group = sp.copy()
    T = reference_prior(sim, ks, sim_sp)
    # clusters = standpoints: the real reference plane's error is shared by all tiles of a standpoint
    clusters = sp if len(np.unique(sp)) >= 3 else sp * 1000 + bl
    return Table("bias", y, w, X, clusters, _folds(sp, bl), sp, Z, group, T, bl)


def _frames_per_block(s: Samples, block: IntArray) -> NDArray[np.int64]:
    """Number of frames of every (standpoint, block)."""
    nsp, nb = int(s.standpoint.max()) + 1, int(block.max()) + 1
    key = (s.standpoint * nb + block) * 10_000_000 + s.frame
    u = np.unique(key)
    sb = u // 10_000_000
    return np.bincount(sb, minlength=nsp * nb).reshape(nsp, nb)


def _plane_basis(s: Samples) -> FloatArray:
    """z^2 (1, x, y) per sample, x, y normalised image coordinates: a plane's first-order z error."""
    xn, yn = (s.u - s.ppx) / s.fx, (s.v - s.ppy) / s.fx
    z2 = s.z_ref_m ** 2
    return np.stack([z2, z2 * xn, z2 * yn], axis=1)


def _tile_columns(candidates: Sequence[Candidate], kind: str, real: Samples, inv_r: NDArray[Any],
                  nr: NDArray[Any], ia: NDArray[Any]) -> dict[str, FloatArray]:
    """Each candidate's signature columns averaged over the pixels of every matched tile."""
    ok = inv_r >= 0
    X: dict[str, FloatArray] = {}
    for c in candidates:
        if c.kind != kind or c.table != "tiles":
            continue
        cols = c.columns(real)
        tiles = np.stack([np.bincount(inv_r[ok], weights=cols[ok, j], minlength=len(nr)) / np.maximum(nr, 1)
                          for j in range(cols.shape[1])], axis=1)
        X[c.name] = tiles[ia]
    return X


def _plane_tiles(s: Samples, inv: IntArray, n: int) -> FloatArray:
    ok = inv >= 0
    cnt = np.maximum(np.bincount(inv[ok], minlength=n), 1)
    cols = _plane_basis(s)
    return np.stack([np.bincount(inv[ok], weights=cols[ok, j], minlength=n) / cnt for j in range(3)], axis=1)


def reference_prior(sim: Samples, keys: NDArray[np.int64], sim_sp: IntArray) -> FloatArray:
    """Prior covariance of the per-standpoint plane coefficients of real - sim.

    The simulation knows both its estimated and its rendered board, so `ref_err_m` is the
    reference-plane error itself. Its plane coefficients per standpoint are fitted on the same
    tiles as the residual (all frame blocks: the pose errors of the frames of one standpoint are
    largely shared, the static corner biases of the colour image); their mean outer product is the
    size of one side's error, and the residual carries two (real and sim). This KNOWN variance caps
    the one estimated from the residual, so that an effect constant within a standpoint (a z^2
    offset, a temperature drift) is not absorbed by a free plane per standpoint.
    """
    m = sim_sp >= 0
    if not m.any() or not np.any(sim.ref_err_m[m]):
        return np.zeros((3, 3))
    k = keys[m]
    sub = sim.subset(m)
    uq, n, mean, _, inv = _aggregate(k, sub.ref_err_m)
    Zs = _plane_tiles(sub, inv, len(uq))
    ok_t = n >= MIN_TILE
    grp = uq[:, 0]
    outer = []
    for g in np.unique(grp[ok_t]):
        rows = np.flatnonzero(ok_t & (grp == g))
        if len(rows) < 6:
            continue
        coef = np.linalg.lstsq(Zs[rows] * np.sqrt(n[rows])[:, None], mean[rows] * np.sqrt(n[rows]),
                               rcond=None)[0]
        outer.append(np.outer(coef, coef))
    if not outer:
        return np.zeros((3, 3))
    return np.asarray(2.0 * np.mean(outer, axis=0), dtype=np.float64)


def _design_sq(st: Structure, density: float, n: FloatArray) -> FloatArray:
    """Design factor of a mean of squared (or multiplied) within-frame deviations: the squares of
    correlated Gaussians correlate by rho^2, sum over a triangle's lags (2w^2 + 1) / (3w) per axis."""
    w, frac = st.corr.window_px, st.corr.fraction
    per_axis = (2 * w * w + 1) / (3 * w)
    return np.asarray(np.minimum(1.0 + frac ** 2 * density * (per_axis ** 2 - 1.0), np.maximum(n, 1.0)))


def variance_table(real: Samples, sim: Samples, candidates: Sequence[Candidate], *,
                   tile_px: float | None = None,
                   structures: tuple[Structure, Structure] | None = None) -> Table:
    """Within-frame variance real minus sim: tiles (all frames of a standpoint), plus per standpoint
    the covariance of neighbours at each lag (window noise: the lag rows; white noise adds nothing
    there). The frame-common part is removed first: it has its own table (`frame_table`)."""
    tp = 2 * (default_tile_px(real) if tile_px is None else tile_px)
    st_r, st_s = structures if structures is not None else (decompose(real), decompose(sim))
    sim_sp = align_standpoints(real, sim)
    zero_r, zero_s = np.zeros(len(real), dtype=np.int64), np.zeros(len(sim), dtype=np.int64)
    kr = _tile_keys(real, tp, zero_r)
    ks = _tile_keys(sim, tp, zero_s)
    ks[:, 0] = sim_sp
    dr, ds = st_r.dev2, st_s.dev2
    ur, nr, mr, _, inv_r = _aggregate(kr, dr)
    us, ns, ms, _, _ = _aggregate(ks[sim_sp >= 0], ds[sim_sp >= 0])
    ia, ib = _match(ur, us)
    keep = (nr[ia] >= MIN_TILE) & (ns[ib] >= MIN_TILE)
    ia, ib = ia[keep], ib[keep]
    y = mr[ia] - ms[ib]
    frames_r = max(1.0, len(np.unique(real.frame_key)) / max(len(real.names), 1))
    frames_s = max(1.0, len(np.unique(sim.frame_key)) / max(len(sim.names), 1))
    dsr = _design_sq(st_r, float(np.mean(st_r.density)), nr[ia] / frames_r)
    dss = _design_sq(st_s, float(np.mean(st_s.density)), ns[ib] / frames_s)
    # the simulation's variance on both sides: the real one in the weights would down-weigh every
    # tile where the real noise happens to be larger (self-weighting), biasing the fit low
    var_y = 2 * ms[ib] ** 2 * (dsr / nr[ia] + dss / ns[ib])
    X = _tile_columns(candidates, "variance", real, inv_r, nr, ia)
    sp = ur[ia, 0]
    # neighbour rows: per standpoint and (axis, lag) the mean product of within-frame deviations
    rows_y: list[FloatArray] = []
    rows_v: list[FloatArray] = []
    rows_sp: list[IntArray] = []
    rows_x: dict[str, list[FloatArray]] = {}
    var_cands = [c for c in candidates if c.kind == "variance" and c.table == "tiles"]
    cols_r = {c.name: c.columns(real) for c in var_cands if c.correlation is not None}
    nsp = len(real.names)

    def per_sp(sp_idx: IntArray, values: FloatArray) -> tuple[FloatArray, FloatArray]:
        ok = (sp_idx >= 0) & np.isfinite(values)
        n = np.bincount(sp_idx[ok], minlength=nsp).astype(np.float64)
        return np.bincount(sp_idx[ok], weights=values[ok], minlength=nsp) / np.maximum(n, 1), n

    for key in sorted(set(st_r.pairs) & set(st_s.pairs)):
        axis, lag = key
        (i_r, j_r), (i_s, j_s) = st_r.pairs[key], st_s.pairs[key]
        sp_r, sp_s = real.standpoint[i_r], sim_sp[i_s]
        mpr, npr = per_sp(sp_r, st_r.within[i_r] * st_r.within[j_r])
        mps, nps = per_sp(sp_s, st_s.within[i_s] * st_s.within[j_s])
        vs, _ = per_sp(sp_s, ds[i_s])
        ok = (npr >= MIN_TILE * 4) & (nps >= MIN_TILE * 4)
        if not ok.any():
            continue
        fpr = np.maximum(npr / max(frames_r, 1.0), 1.0)
        fps = np.maximum(nps / max(frames_s, 1.0), 1.0)
        g = np.flatnonzero(ok)
        rows_y.append(mpr[g] - mps[g])
        rows_v.append(vs[g] ** 2 * (_design_sq(st_r, float(np.mean(st_r.density)), fpr[g]) / npr[g]
                                    + _design_sq(st_s, float(np.mean(st_s.density)), fps[g]) / nps[g]))
        rows_sp.append(g)
        du, dv = (lag, 0.0) if axis == "u" else (0.0, lag)
        for c in var_cands:
            if c.name not in X:
                continue
            k = X[c.name].shape[1]
            if c.correlation is not None:
                rho = c.correlation(du, dv)
                col = np.stack([per_sp(sp_r, cols_r[c.name][i_r, j])[0][g] * rho for j in range(k)], axis=1)
            else:
                col = np.zeros((len(g), k))
            rows_x.setdefault(c.name, []).append(col)
    if rows_y:
        # the lag rows of one standpoint are products of the same deviations at neighbouring lags:
        # strongly dependent, so together they weigh as one row (each by 1 / their number)
        lag_sp = np.concatenate(rows_sp)
        per = np.bincount(lag_sp, minlength=nsp)[lag_sp]
        y = np.r_[y, np.concatenate(rows_y)]
        var_y = np.r_[var_y, np.concatenate(rows_v) * per]
        sp = np.r_[sp, np.concatenate(rows_sp)].astype(np.int64)
        n_lag = sum(len(r) for r in rows_y)
        for name in X:
            extra = np.concatenate(rows_x[name]) if name in rows_x else np.zeros((n_lag, X[name].shape[1]))
            X[name] = np.concatenate([X[name], extra])
    floor = np.median(var_y) * 1e-3 + 1e-30 if len(var_y) else 1e-30
    w = 1.0 / np.maximum(var_y, floor)
    blocks = np.zeros_like(sp)
    return Table("variance", y, w, X, sp, _folds(sp, sp if len(np.unique(sp)) >= 3 else blocks), sp,
                 name="variance")


def frame_table(real: Samples, sim: Samples, candidates: Sequence[Candidate],
                structures: tuple[Structure, Structure] | None = None) -> Table:
    """Frame-common variance real minus sim, one row per standpoint (m^2 at the standpoint's K).

    Candidates of this table (`table == "frame"`) are disparity noises common to a frame: their
    column is the standpoint's mean K^2 per px^2 of variance.
    """
    st_r, st_s = structures if structures is not None else (decompose(real), decompose(sim))
    fr, fs = frame_common(real, st_r), frame_common(sim, st_s)
    to_sim = standpoint_map(sim, real)
    # weights from a variance that does not follow each standpoint's own estimate: the standpoints'
    # pooled common variance (px^2) sets it (with 15 frames, weights from each estimate gave the low
    # estimates 2-3x the weight and the fit 30 % low: 0.0016 against 0.0025 px^2 written)
    pooled = [max(float(f.excess_px2.sum()) / max(len(f.standpoint), 1), 0.0) for f in (fr, fs)]
    se_r, se_s = (f.se_null(np.full(len(f.standpoint), c)) for f, c in zip((fr, fs), pooled, strict=True))
    y, v, sp, k2 = [], [], [], []
    for i, g in enumerate(fr.standpoint):
        hit = np.flatnonzero(fs.standpoint == to_sim[g])   # none where sim lacks it (-1)
        if not hit.size:
            continue
        kk = fr.k_m[i] ** 2
        y.append((fr.excess_px2[i] - fs.excess_px2[hit[0]]) * kk)
        v.append((se_r[i] ** 2 + se_s[hit[0]] ** 2) * kk * kk)
        sp.append(int(g))
        k2.append(kk)
    ya, va = np.asarray(y, dtype=float), np.asarray(v, dtype=float)
    spa = np.asarray(sp, dtype=np.int64)
    floor = float(np.median(va)) * 1e-2 + 1e-30 if len(va) else 1e-30
    X = {c.name: np.asarray(k2, dtype=float).reshape(-1, 1) for c in candidates if c.table == "frame"}
    return Table("variance", ya, 1.0 / np.maximum(va, floor), X, spa, spa.copy(), spa, name="frame")

