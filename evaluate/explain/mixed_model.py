"""Fitting a residual table: generalised least squares under the mixed model, BIC, held-out RMSE
and the Wald test that attribute and discover select by.

The Wald test uses the covariance of the mixed model (random plane errors per standpoint and per
frame block), which is what accounts for tiles of one frame block sharing noise, since BIC alone
would trust them too much; it is model-based, not a sandwich estimate. Tables without that
structure (within-frame variance, frame-common) take a cluster-robust covariance instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc, fdtrc

from depthstation.evaluate.explain.samples import FloatArray
from depthstation.evaluate.explain.tables import Table


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


def cluster_cov(t: Table, names: Sequence[str], beta: FloatArray) -> tuple[FloatArray, int]:
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
        cov, n_g = cluster_cov(t, names, fit.beta)
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
