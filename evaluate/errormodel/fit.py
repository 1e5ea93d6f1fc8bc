"""Fitting the error model: weighted least squares over the measured field's cells, the terms chosen
by BIC, the coefficients' covariance clustered on cells that share frames, and a held-out check.

Why these choices: the cells' standard errors (frames as clusters) are the honest weights, but
neighbouring cells share the very frames whose pose error moves them together, so the textbook
covariance (X'WX)^-1 is too small; the cluster-robust (CR1) sandwich over blocks of cells is taken
where it is larger, else the textbook one scaled by the reduced chi^2 (Birge ratio) when above 1.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.evaluate.errormodel.inputs import Field
from depthstation.evaluate.errormodel.schema import TERMS, Part, design

F64 = NDArray[np.float64]
FOLDS = 5


@dataclass
class Data:
    """The rows a part is fitted to: positions, values, standard errors, clusters, validation groups."""

    z: F64
    theta: F64
    y: F64
    se: F64
    cluster: NDArray[np.int64]
    group: NDArray[np.int64]      # validation unit of each row
    group_kind: str               # what a validation unit is (said in the model file)


def _wls(x: F64, y: F64, w: F64) -> tuple[F64, F64, float]:
    """Coefficients, (X'WX)^-1 and chi^2 of a weighted least-squares fit."""
    sw = np.sqrt(w)
    xa, ya = x * sw[:, None], y * sw
    beta = np.asarray(np.linalg.lstsq(xa, ya, rcond=None)[0], dtype=np.float64)
    inv = np.asarray(np.linalg.pinv(xa.T @ xa), dtype=np.float64)
    r = ya - xa @ beta
    return beta, inv, float(r @ r)


def _cluster_cov(x: F64, y: F64, w: F64, beta: F64, inv: F64, cluster: NDArray[np.int64]) -> tuple[F64, int]:
    """CR1 cluster-robust covariance of a WLS fit and the number of clusters."""
    r = (y - x @ beta) * w
    ids, inverse = np.unique(cluster, return_inverse=True)
    g = len(ids)
    scores = np.zeros((g, x.shape[1]))
    np.add.at(scores, inverse, x * r[:, None])
    meat = scores.T @ scores
    n, k = x.shape
    adj = (g / max(g - 1, 1)) * ((n - 1) / max(n - k, 1))
    return adj * inv @ meat @ inv, g


def _bic(chi2: float, n: int, k: int) -> float:
    """BIC of a Gaussian fit whose weights are the rows' own standard errors: chi2 + k ln n (the
    errors are taken as given, not rescaled, so a term must lower chi2 by ln n to enter)."""
    return chi2 + k * math.log(n)


def _candidates(allowed: tuple[str, ...], need_theta: bool) -> list[tuple[str, ...]]:
    out = []
    for r in range(1, len(allowed) + 1):
        for c in itertools.combinations(allowed, r):
            if not need_theta and any(t in ("incl_scale", "inclination") for t in c):
                continue
            out.append(c)
    return out


def fit_part(d: Data, allowed: tuple[str, ...] = TERMS, *, name: str) -> Part:
    """Select terms by BIC, fit them, cluster their covariance, validate on held-out groups."""
    n = len(d.y)
    w = 1.0 / d.se ** 2
    theta_spread = float(np.ptp(d.theta)) if n else 0.0
    # at most a third as many terms as rows: every held-out refit still has rows to spare, and five
    # standpoints cannot carry four terms whatever their chi2 says
    kmax = max(1, n // 3)
    cands = [c for c in _candidates(allowed, theta_spread >= 5.0) if len(c) <= kmax]
    if not cands:
        raise ValueError(f"{name}: {n} rows are too few to fit any term")
    table: list[dict[str, Any]] = []
    for c in cands:
        x = design(d.z, d.theta, c)
        if np.linalg.matrix_rank(x * np.sqrt(w)[:, None]) < len(c):
            continue
        beta, inv, chi2 = _wls(x, d.y, w)
        table.append({"terms": list(c), "k": len(c), "chi2": chi2, "bic": _bic(chi2, n, len(c))})
    table.sort(key=lambda e: e["bic"])
    best: tuple[str, ...] = tuple(table[0]["terms"])
    x = design(d.z, d.theta, best)
    beta, inv, chi2 = _wls(x, d.y, w)
    dof = max(n - len(best), 1)
    birge = chi2 / dof
    cov_model = inv * max(1.0, birge)
    cov_cl, g = _cluster_cov(x, d.y, w, beta, inv, d.cluster)
    use_cluster = g >= len(best) + 2 and np.trace(cov_cl) > np.trace(cov_model)
    cov = cov_cl if use_cluster else cov_model
    info: dict[str, Any] = {
        "fit": {"rows": n, "clusters": g, "chi2": chi2, "dof": dof, "reduced_chi2": birge,
                "covariance": ("cluster-robust CR1 over the clusters (larger than the model's)" if use_cluster
                               else "(X'WX)^-1 scaled by max(1, reduced chi^2)"),
                "weights": "1 / se^2 of each row (frames as clusters within a cell)",
                "weighted_rms_residual_m": float(math.sqrt(np.sum(w * (d.y - x @ beta) ** 2) / np.sum(w)))},
        "selection": {"criterion": f"BIC = chi2 + k ln n over every subset of at most {kmax} of the "
                                   "candidate terms (n / 3)"
                                   + ("" if theta_spread >= 5.0 else
                                      " (inclination terms left out: the rows span under 5 deg)"),
                      "chosen": list(best), "candidates": table[:8]},
        "validation": validate(d, best),
    }
    return Part(best, beta, cov, info)


def validate(d: Data, terms: tuple[str, ...]) -> dict[str, Any]:
    """Held-out check: the chosen terms refitted without each validation group and predicting it;
    against the raw field (bias 0 / sigma 0 predicts nothing) and an offset alone."""
    groups = np.unique(d.group)
    if len(groups) < 2:
        return {"unit": d.group_kind, "groups": len(groups), "done": False,
                "why": "a single validation group: nothing to hold out"}
    res, res_off, held = [], [], []
    for g in groups:
        test = d.group == g
        train = ~test
        w = 1.0 / d.se[train] ** 2
        x = design(d.z[train], d.theta[train], terms)
        if train.sum() <= len(terms) or np.linalg.matrix_rank(x) < len(terms):
            continue
        beta, _, _ = _wls(x, d.y[train], w)
        off = float(np.sum(w * d.y[train]) / np.sum(w))
        pred = design(d.z[test], d.theta[test], terms) @ beta
        res.append(d.y[test] - pred)
        res_off.append(d.y[test] - off)
        held.append(d.y[test])
    if not res:
        return {"unit": d.group_kind, "groups": len(groups), "done": False,
                "why": "no group leaves enough rows to refit"}
    r, ro, y = np.concatenate(res), np.concatenate(res_off), np.concatenate(held)
    rms = float(np.sqrt(np.mean(r ** 2)))
    return {"unit": d.group_kind, "groups": len(groups), "done": True, "rows": len(r),
            "rms_residual_m": rms, "rms_raw_m": float(np.sqrt(np.mean(y ** 2))),
            "rms_offset_only_m": float(np.sqrt(np.mean(ro ** 2))),
            "mean_abs_residual_m": float(np.mean(np.abs(r))), "mean_abs_raw_m": float(np.mean(np.abs(y)))}


def stack(fields: list[Field], what: str) -> Data:
    """The rows of all inputs for the bias ('mean') or sigma ('std'); validation groups are whole
    inputs when there are several, else standpoints (checkerboard) or blocks of cells (scan)."""
    z = np.concatenate([f.z_m for f in fields])
    t = np.concatenate([f.theta_deg for f in fields])
    y = np.concatenate([f.mean_m if what == "mean" else f.std_m for f in fields])
    se = np.concatenate([f.se_mean_m if what == "mean" else f.se_std_m for f in fields])
    cl = np.concatenate([f.cluster + 1_000_000_000 * i for i, f in enumerate(fields)])
    if len(fields) >= 2:
        group = np.concatenate([np.full(len(f.z_m), i) for i, f in enumerate(fields)])
        kind = "input results (each study held out in turn: other walks or standpoint sets)"
    elif fields[0].kind == "checkerboard":
        group = fields[0].cluster.copy()
        kind = "standpoints (each held out in turn)"
    else:
        ids = np.unique(fields[0].cluster)
        order = np.random.default_rng(0).permutation(len(ids))
        fold = dict(zip(ids.tolist(), (order % FOLDS).tolist(), strict=True))
        group = np.asarray([fold[c] for c in fields[0].cluster.tolist()], dtype=np.int64)
        kind = (f"held-out cells: {FOLDS} folds of whole 0.5 m x 15 deg blocks of table cells (a grid keeps "
                "no frames to hold out)")
    ok = np.isfinite(y) & np.isfinite(se) & (se > 0)
    return Data(z[ok], t[ok], y[ok], se[ok], cl[ok].astype(np.int64), group[ok].astype(np.int64), kind)
