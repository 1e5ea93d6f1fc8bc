"""Attribute: which catalogue effects explain the real-minus-simulated residual, with what parameters.

The residual lives on tiles (standpoint x frame block x pixel tile x black/white): the difference of
mean errors real minus sim, and separately of temporal variances. Each candidate effect's signature
is averaged over the same pixels, giving a linear model fitted by weighted least squares. Selection
is forward, by BIC; a candidate enters only if it also lowers the held-out RMSE (leave one standpoint
out, or frame blocks when there are fewer than three standpoints) and its Wald test is strong. The
Wald test uses the covariance of the mixed model (random plane errors per standpoint and per frame
block), which is what accounts for tiles of one frame block sharing noise, since BIC alone would
trust them too much; it is model-based, not a sandwich estimate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc, fdtrc

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

BIC_THRESHOLD = -10.0      # "very strong" evidence (Kass & Raftery)
NEAR_TIE = 6.0             # a runner-up within this BIC gap is only "positive" evidence apart: reported
WALD_P = 1e-3
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


@dataclass
class CandidateFit:
    """One candidate's verdict: parameters, evidence, held-out effect, whether it was selected."""

    effect: str
    kind: str
    role: str                       # "missing_physics" (not in the model) or "calibration"
    params: dict[str, float]
    units: dict[str, str]
    meaning: str
    delta_bic: float
    heldout_rmse_before_m: float
    heldout_rmse_after_m: float
    wald_p: float
    stderr: dict[str, float] = field(default_factory=dict)
    selected: bool = False
    step: int | None = None
    coef: list[float] = field(default_factory=list)
    near_ties: list[dict[str, Any]] = field(default_factory=list)   # runners-up within NEAR_TIE

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["params"] = {k: {"value": v, "unit": self.units.get(k, ""), "stderr": self.stderr.get(k)}
                       for k, v in self.params.items()}
        d.pop("units")
        d.pop("stderr")
        return d


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


def _tile_px(s: Samples) -> float:
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
    tp = _tile_px(real) if tile_px is None else tile_px
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
    tp = 2 * (_tile_px(real) if tile_px is None else tile_px)
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
    y, v, sp, k2 = [], [], [], []
    for i, g in enumerate(fr.standpoint):
        hit = np.flatnonzero(fs.standpoint == to_sim[g])   # none where sim lacks it (-1)
        if not hit.size:
            continue
        kk = fr.k_m[i] ** 2
        y.append((fr.excess_px2[i] - fs.excess_px2[hit[0]]) * kk)
        v.append((fr.se_px2()[i] ** 2 + fs.se_px2()[hit[0]] ** 2) * kk * kk)
        sp.append(int(g))
        k2.append(kk)
    ya, va = np.asarray(y, dtype=float), np.asarray(v, dtype=float)
    spa = np.asarray(sp, dtype=np.int64)
    floor = float(np.median(va)) * 1e-2 + 1e-30 if len(va) else 1e-30
    X = {c.name: np.asarray(k2, dtype=float).reshape(-1, 1) for c in candidates if c.table == "frame"}
    return Table("variance", ya, 1.0 / np.maximum(va, floor), X, spa, spa.copy(), spa, name="frame")


def _design(t: Table, names: Sequence[str]) -> FloatArray:
    if not names:
        return np.zeros((len(t), 0))
    return np.concatenate([t.X[n] for n in names], axis=1)


def wls(X: FloatArray, y: FloatArray, w: FloatArray) -> FloatArray:
    if X.shape[1] == 0:
        return np.zeros(0)
    sw = np.sqrt(w)
    beta, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    return np.asarray(beta)


@dataclass
class Fit:
    beta: FloatArray
    cov: FloatArray
    loglik: float


def gls(t: Table, names: Sequence[str], rows: NDArray[Any] | None = None, iterations: int = 2) -> Fit:
    """Mixed model y = X b + Z g + e, g ~ N(0, diag(tau)) per standpoint.

    Each side's reference plane (the board pose estimated from the colour image) is off by a small
    offset and tilt, shared by all tiles of a standpoint: random plane coefficients. Their variances
    are the between-standpoint scatter (moments, iterated with GLS) CAPPED by the size the
    simulation measured (`reference_prior`): a free estimate alone would let a coherent effect that
    is constant within a standpoint (a z^2 offset, a temperature drift) hide in the planes. The
    noise scale s2 comes from the residual within standpoints. Without a known reference error this
    is plain WLS with a fitted scale.
    """
    idx_all = np.arange(len(t)) if rows is None else np.asarray(rows)
    X = _design(t, names)[idx_all]
    y, w = t.y[idx_all], t.w[idx_all]
    n, k = X.shape
    beta = wls(X, y, w)
    if t.Z is None or t.T is None or t.group is None or not np.any(t.T):
        r = y - X @ beta
        s2 = float((w * r ** 2).sum()) / max(n - k, 1)
        xw = X * w[:, None]
        cov = np.linalg.pinv(X.T @ xw) * s2 if k else np.zeros((0, 0))
        ll = -0.5 * float(np.sum(np.log(2 * np.pi * s2 / w)) + (w * r ** 2).sum() / s2)
        return Fit(beta, cov, ll)
    Z0 = t.Z[idx_all]
    grp = t.group[idx_all]
    blk = t.block[idx_all] if t.block is not None else np.zeros(len(idx_all), dtype=np.int64)
    nb = int(blk.max()) + 1
    p = Z0.shape[1]
    # nested planes: one per standpoint (shared by its frames: static pose bias) plus one per frame
    # block (frame-to-frame jitter of the pose), Z = [Z0, Z0 * 1{block = b} ...]
    Z = np.concatenate([Z0] + [Z0 * (blk == b)[:, None] for b in range(nb)], axis=1)
    groups = [np.flatnonzero(grp == s) for s in np.unique(grp)]
    known = np.clip(np.diag(t.T), 0.0, None)
    tau = np.zeros((Z.shape[1], Z.shape[1]))
    s2 = 1.0
    A = np.zeros((k, k))
    for _ in range(iterations):
        r = y - X @ beta
        rss, dof, gam, dev = 0.0, 0, [], []
        for g in groups:
            if len(g) <= Z.shape[1]:
                continue
            gg = wls(Z[g], r[g], w[g])
            blocks = [b for b in range(nb) if np.any(blk[g] == b)]
            per_block = np.array([gg[:p] + gg[p * (b + 1):p * (b + 2)] for b in blocks])
            gam.append(per_block.mean(axis=0))
            dev += list(per_block - per_block.mean(axis=0))
            rss += float((w[g] * (r[g] - Z[g] @ gg) ** 2).sum())
            dof += len(g) - Z.shape[1]
        s2 = rss / dof if dof > 0 else 1.0
        # between-standpoint scatter of the planes, but never more than the simulation measured:
        # what exceeds the known pose error is left to the fixed effects
        scatter = np.var(np.array(gam), axis=0, ddof=1) if len(gam) >= 3 else known
        jitter = np.mean(np.array(dev) ** 2, axis=0) * nb / max(nb - 1, 1) if dev else np.zeros(p)
        tau = np.diag(np.r_[np.minimum(scatter, known), np.tile(jitter, nb)]) / s2
        A = np.zeros((k, k))
        b = np.zeros(k)
        for g in groups:
            vx, vy = _vinv(Z[g], w[g], tau, X[g]), _vinv(Z[g], w[g], tau, y[g][:, None])
            A += X[g].T @ vx
            b += (X[g].T @ vy).ravel()
        beta = np.asarray(np.linalg.lstsq(A, b, rcond=None)[0], dtype=np.float64) if k else np.zeros(0)
    r = y - X @ beta
    ll = 0.0
    for g in groups:
        zw = Z[g] * w[g][:, None]
        logdet = float(np.sum(np.log(s2 / w[g]))) + float(np.linalg.slogdet(
            np.eye(Z.shape[1]) + (Z[g].T @ zw) @ tau)[1])
        quad = float((r[g] * _vinv(Z[g], w[g], tau, r[g][:, None]).ravel()).sum()) / s2
        ll += -0.5 * (len(g) * np.log(2 * np.pi) + logdet + quad)
    cov = np.asarray(np.linalg.pinv(A) * s2, dtype=np.float64) if k else np.zeros((0, 0))
    return Fit(beta, cov, ll)


def _vinv(Z: FloatArray, w: FloatArray, tau: FloatArray, a: FloatArray) -> FloatArray:
    """(W^-1 + Z tau Z')^-1 a by Woodbury in the form that allows a singular tau:
    W a - W Z tau (I + Z' W Z tau)^-1 Z' W a."""
    wz = Z * w[:, None]
    m = np.eye(Z.shape[1]) + (Z.T @ wz) @ tau
    wa = a * w[:, None]
    return np.asarray(wa - wz @ (tau @ np.linalg.solve(m, wz.T @ a)))


def bic(t: Table, names: Sequence[str]) -> float:
    """BIC of the mixed model: -2 log L + k ln n."""
    fit = gls(t, names)
    return -2 * fit.loglik + len(fit.beta) * np.log(len(t))


def heldout_rmse(t: Table, names: Sequence[str]) -> float:
    """Weighted RMS (in the units of y) of held-out residuals, every fold fitted without itself."""
    X = _design(t, names)
    res = np.empty(len(t))
    for f in np.unique(t.fold):
        test = t.fold == f
        train = np.flatnonzero(~test)
        beta = gls(t, names, train).beta if len(train) else np.zeros(X.shape[1])
        res[test] = t.y[test] - X[test] @ beta
    return float(np.sqrt((t.w * res ** 2).sum() / t.w.sum()))


def _cluster_cov(t: Table, names: Sequence[str], beta: FloatArray) -> tuple[FloatArray, int]:
    """Cluster-robust (sandwich) covariance of a WLS fit, clusters = standpoints, and their number.

    Tables without a random-effect structure (within-frame variance, frame-common) use it: the rows
    of one standpoint share its sampling scatter (a small far board with window-correlated noise
    holds few effective samples), which model-based weights underrate.
    """
    X = _design(t, names)
    sw = np.sqrt(t.w)
    Xw = X * sw[:, None]
    r = (t.y - X @ beta) * sw
    bread = np.linalg.pinv(Xw.T @ Xw)
    meat = np.zeros_like(bread)
    groups = np.unique(t.cluster)
    for g in groups:
        m = t.cluster == g
        v = Xw[m].T @ r[m]
        meat += np.outer(v, v)
    n_g = len(groups)
    return np.asarray(bread @ meat @ bread * n_g / max(n_g - 1, 1)), n_g


def wald_p(t: Table, names: Sequence[str], name: str) -> tuple[float, FloatArray, FloatArray]:
    """Wald p-value of one candidate's columns; its beta and SEs. Mixed model (bias): chi^2 with the
    model's covariance; plain WLS tables: cluster-robust covariance, F test with clusters - 1 dof."""
    fit = gls(t, names)
    start = sum(t.X[n].shape[1] for n in names[:list(names).index(name)])
    k = t.X[name].shape[1]
    b = fit.beta[start:start + k]
    if t.Z is None:
        cov, n_g = _cluster_cov(t, names, fit.beta)
        c = cov[start:start + k, start:start + k]
        try:
            stat = float(b @ np.linalg.solve(c, b))
        except np.linalg.LinAlgError:
            return 1.0, b, np.full(k, np.nan)
        if not np.isfinite(stat) or stat < 0 or n_g < 3:
            return 1.0, b, np.sqrt(np.clip(np.diag(c), 0, None))
        # clusters do not inform the coefficient equally (near boards carry more pixels): the
        # effective number of clusters, (sum s)^2 / sum s^2 of their information shares, sets the dof
        xc = t.X[name]
        share = np.array([float((t.w[t.cluster == g][:, None] * xc[t.cluster == g] ** 2).sum())
                          for g in np.unique(t.cluster)])
        g_eff = float(share.sum() ** 2 / max((share ** 2).sum(), 1e-300))
        return (float(fdtrc(k, max(g_eff - 1.0, 1.0), stat / k)), b,
                np.sqrt(np.clip(np.diag(c), 0, None)))
    c = fit.cov[start:start + k, start:start + k]
    try:
        stat = float(b @ np.linalg.solve(c, b))
    except np.linalg.LinAlgError:
        return 1.0, b, np.full(k, np.nan)
    if not np.isfinite(stat) or stat < 0:
        return 1.0, b, np.full(k, np.nan)
    return float(chdtrc(k, stat)), b, np.sqrt(np.clip(np.diag(c), 0, None))


def _usable(t: Table, name: str) -> bool:
    x = t.X.get(name)
    if x is None or not np.isfinite(x).all():
        return False
    return bool(np.all(np.abs(x).max(axis=0) > 0))


def forward_select(t: Table, candidates: Sequence[Candidate], present: dict[str, dict[str, float]],
                   samples: Samples | None = None) -> list[CandidateFit]:
    """Forward selection by BIC, gated by held-out RMSE and the mixed-model Wald test; all scored."""
    pool = [c for c in candidates
            if c.kind == t.kind and not c.generic and c.name in t.X and _usable(t, c.name)]
    by_name = {c.name: c for c in pool}
    selected: list[str] = []
    fits: dict[str, CandidateFit] = {}
    step = 0
    if len(t) < 3:
        return []
    while True:
        base_bic = bic(t, selected)
        base_rmse = heldout_rmse(t, selected)
        trials: list[tuple[float, str]] = []
        for c in pool:
            if c.name in selected or any(c.name in by_name[o].excludes or o in c.excludes
                                         for o in selected):
                continue
            trials.append((bic(t, [*selected, c.name]) - base_bic, c.name))
        if not trials:
            break
        trials.sort()
        for dbic, name in trials:
            c = by_name[name]
            after = heldout_rmse(t, [*selected, name])
            p, b, se = wald_p(t, [*selected, name], name)
            fits[name] = _fit_record(c, present, dbic, base_rmse, after, p, b, se, samples)
        best_d, best = trials[0]
        rec = fits[best]
        improves = rec.heldout_rmse_after_m < rec.heldout_rmse_before_m
        if best_d < BIC_THRESHOLD and improves and rec.wald_p < WALD_P \
                and not negative_variances(t, [*selected, best], by_name, present):
            step += 1
            rec.selected, rec.step = True, step
            # the data barely prefer the winner: say so rather than pick silently
            rec.near_ties = [{"effect": n, "delta_bic": float(d), "bic_gap": float(d - best_d)}
                             for d, n in trials[1:] if d - best_d < NEAR_TIE]
            selected.append(best)
            continue
        break
    # final parameters of the selected effects come from the joint fit
    if selected:
        fit = gls(t, selected)
        beta, cov = fit.beta, fit.cov
        start = 0
        for name in selected:
            k = t.X[name].shape[1]
            c = by_name[name]
            rec = fits[name]
            b = beta[start:start + k]
            se = np.sqrt(np.clip(np.diag(cov)[start:start + k], 0, None))
            rec.coef = [float(x) for x in b]
            rec.params, rec.stderr = _params(c, present, b, se, samples)
            start += k
    return list(fits.values())


def negative_variances(t: Table, names: Sequence[str], by_name: dict[str, Candidate],
                       present: dict[str, dict[str, float]]) -> list[str]:
    """Variance effects whose total the joint fit takes below zero (nearly collinear columns trading
    off): the simulator cannot render a negative variance, so such a fit is not a model."""
    if t.kind != "variance" or not names:
        return []
    fit = gls(t, names)
    out, start = [], 0
    for n in names:
        k = t.X[n].shape[1]
        b = fit.beta[start:start + k]
        start += k
        c = by_name.get(n)
        if c is None:
            continue
        if c.generic:
            own = t.X[n] @ b
            if own.min() < -0.05 * max(float(own.max()), 0.0):
                out.append(n)
        elif c.squared:
            p0 = float(present.get(n, {}).get(c.params[0], 0.0))
            if p0 ** 2 + float(b[0]) < 0:
                out.append(n)
    return out


def _params(c: Candidate, present: dict[str, dict[str, float]], b: FloatArray, se: FloatArray,
            samples: Samples | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """Fitted values; for an effect the model has, old + delta (bias) or sqrt(old^2 + delta) (variance)."""
    old = present.get(c.name, {})
    if c.squared:
        p0 = float(old.get(c.params[0], 0.0))
        total = p0 ** 2 + float(b[0])
        val = float(np.sign(total) * np.sqrt(abs(total)))
        err = float(se[0] / (2 * max(abs(val), 1e-12)))
        return {c.params[0]: val}, {c.params[0]: err}
    if c.convert is not None and samples is not None:
        vals = c.to_params(b, samples)
        rel = {p: float(e / abs(x)) if x else float("nan") for p, x, e in zip(c.params, b, se, strict=True)}
        return vals, {p: abs(v) * rel.get(p, float("nan")) if p in rel else float("nan")
                      for p, v in vals.items()}
    vals = {p: float(old.get(p, 0.0)) + float(x) for p, x in zip(c.params, b, strict=True)}
    return vals, {p: float(e) for p, e in zip(c.params, se, strict=True)}


def _fit_record(c: Candidate, present: dict[str, dict[str, float]], dbic: float, before: float, after: float,
                p: float, b: FloatArray, se: FloatArray, samples: Samples | None) -> CandidateFit:
    params, errs = _params(c, present, b, se, samples)
    role = "calibration" if c.name in present else "missing_physics"
    if c.kind == "variance":   # variance misfit shown as a standard deviation (m)
        before, after = float(np.sqrt(before)), float(np.sqrt(after))
    units = dict(zip(c.params, c.units, strict=True))
    units.update({k: units.get(k, "degC" if k.endswith("_c") else "") for k in params})
    return CandidateFit(c.name, c.kind, role, params, units, c.meaning,
                        float(dbic), before, after, p, errs, coef=[float(x) for x in b])


def rank(fits: Sequence[CandidateFit]) -> list[CandidateFit]:
    """Selected missing physics first (bias before variance, in selection order), then calibration,
    then the rest by delta BIC."""
    def key(f: CandidateFit) -> tuple[int, int, int, float]:
        if f.selected:
            return (0 if f.role == "missing_physics" else 1, 0 if f.kind == "bias" else 1, f.step or 0,
                    f.delta_bic)
        return (2, 0, 0, f.delta_bic)
    return sorted(fits, key=key)


@dataclass
class Attribution:
    candidates: list[CandidateFit]
    bias_rows: int
    variance_rows: int
    tables: dict[str, Table] = field(default_factory=dict)   # "bias", "variance", "frame"

    @property
    def selected(self) -> list[CandidateFit]:
        return [c for c in self.candidates if c.selected]


def attribute(real: Samples, sim: Samples, candidates: Sequence[Candidate],
              present: dict[str, dict[str, float]] | None = None, *, blocks: int = 4,
              noise_var: NoiseVar | None = None, corr_var: CorrVar | None = None,
              structures: tuple[Structure, Structure] | None = None) -> Attribution:
    """Fit, select and rank the catalogue candidates for the bias and the variance residual.

    `candidates` may hold generic terms of the discovery library too: their columns go into the
    tables (for `discover.discover`), but only catalogue effects are selected here.
    """
    present = present or {}
    st = structures if structures is not None else (decompose(real), decompose(sim))
    # tiles at least 2.5 windows wide: neighbouring tiles of window-correlated noise would otherwise
    # share their errors, and the fit would count them as independent
    window = max([x.corr.window_px for x in st if x.corr.fraction > 0.2], default=1.0)
    tile = max(_tile_px(real), 2.5 * window)
    bt = bias_table(real, sim, candidates, blocks=blocks, noise_var=noise_var, corr_var=corr_var,
                    density=st[0].density, tile_px=tile)
    vt = variance_table(real, sim, candidates, structures=st)
    ft = frame_table(real, sim, candidates, structures=st)
    fits = forward_select(bt, candidates, present, real) + forward_select(vt, candidates, present, real)
    return Attribution(rank(fits), len(bt), len(vt), {"bias": bt, "variance": vt, "frame": ft})
