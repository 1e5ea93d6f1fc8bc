"""Locate: where do real and simulated errors differ, beyond what chance explains?

Along every axis the data carry (image column u, row v, radius, a coarse tile field, distance,
disparity, inclination, albedo, frame, time, temperature, distance to the board edge, and the grid
of distance x inclination), for the bias (mean error) and the noise (within-frame temporal
variance); and the structure of the noise: its frame-common part and the correlation of
neighbouring pixels.

Pixels of one frame share the frame's pose, temperature and correlated noise, so they are not
independent: every standard error here comes from the scatter of per-frame means within a
standpoint (Welch, Satterthwaite degrees of freedom; the frame mean's scatter carries the
window-correlated noise, whatever the number of pixels), and standpoints are combined by
pixel-count weights. What no frame statistic can see is shared by all frames of a standpoint: the
reference pose error and anything else static per standpoint. It enters as a random plane per
standpoint in the disparity domain, whose size is the larger of what the simulation measures for
its own reference and the between-standpoint scatter of the real-minus-sim planes that distance
and temperature do not explain (heterogeneity, DerSimonian-Laird moments). One test per group and
quantity; all p-values of a run are corrected together (Holm).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import stdtr

from depthstation.evaluate.explain.fine import fine_tests
from depthstation.evaluate.explain.samples import (
    FloatArray,
    IntArray,
    Samples,
    align_standpoints,
    frame_positions,
    standpoint_map,
)
from depthstation.evaluate.explain.structure import Structure, decompose, frame_common

ALPHA = 0.05
ALBEDO_GROUPS = ("black", "white")   # group 0: albedo < 0.5
MIN_SAMPLES = 30
# a pixel seen in 2 frames has two equal squared deviations: the frame means of the temporal
# variance then do not scatter at all, and a noise test's SE collapses (t ~ 1e5 on a null)
MIN_NOISE_FRAMES = 3


def standpoint_frames(s: Samples) -> dict[str, int]:
    """Frames with samples per standpoint name."""
    _, fsp = s.frame_index()
    counts = np.bincount(fsp, minlength=len(s.names)) if len(s) else np.zeros(len(s.names), np.int64)
    return {n: int(c) for n, c in zip(s.names, counts, strict=True)}


def short_standpoints(s: Samples) -> list[str]:
    """Standpoints with samples in fewer than MIN_NOISE_FRAMES frames (left out of the noise tests)."""
    return [n for n, c in standpoint_frames(s).items() if 0 < c < MIN_NOISE_FRAMES]


@dataclass
class GroupTest:
    """Real versus simulated mean (bias) or temporal variance (noise) in one group of pixels."""

    family: str            # standpoint, grid, column, radius, albedo, time, temperature, edge
    kind: str              # "bias" (mean error, m) or "noise" (temporal variance, m^2)
    label: str
    coords: dict[str, Any]
    real: float
    sim: float
    diff: float
    se: float
    t: float
    dof: float
    p: float
    n_real: int
    n_sim: int
    p_adj: float = float("nan")
    significant: bool = False
    axes: list[str] = field(default_factory=list)   # the family's axes in explain's vocabulary

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Groups:
    """A partition of samples on both sides: integer group per sample (-1 = none) and a label each."""

    family: str
    real: IntArray
    sim: IntArray
    labels: list[str]
    coords: list[dict[str, Any]]
    axes: tuple[str, ...] = ()


@dataclass
class LocateResult:
    tests: list[GroupTest] = field(default_factory=list)
    heterogeneity: Any = None                 # Heterogeneity of the bias tests
    correlation: tuple[Any, Any] | None = None  # (real, sim) Correlation of the within-frame noise

    @property
    def significant(self) -> list[GroupTest]:
        return [t for t in self.tests if t.significant]

    def summary(self) -> dict[str, Any]:
        """`mismatch` block of explain.json: flag, differing standpoints, differing regions."""
        sig = self.significant
        standpoints = sorted({t.label for t in sig if t.family in ("standpoint", "heterogeneity")})
        regions = [{"family": t.family, "kind": t.kind, "label": t.label, "axes": list(t.axes), **t.coords,
                    "diff": t.diff, "se": t.se, "p_adj": t.p_adj}
                   for t in sorted(sig, key=lambda t: t.p) if t.family not in ("standpoint", "heterogeneity")]
        # a standpoint whose real-minus-sim plane is not of the others' kind (heterogeneity_tests)
        odd = sorted({t.label for t in sig if t.family == "heterogeneity"})
        out: dict[str, Any] = {"significant": bool(sig), "standpoints": standpoints,
                               "heterogeneous_standpoints": odd, "regions": regions,
                               "tests": len(self.tests), "alpha": ALPHA, "correction": "holm"}
        if self.heterogeneity is not None:
            out["standpoint_heterogeneity"] = self.heterogeneity.to_dict()
        if self.correlation is not None:
            out["noise_correlation"] = {"real": self.correlation[0].to_dict(),
                                        "sim": self.correlation[1].to_dict()}
        return out

    def family(self, name: str, kind: str = "bias") -> list[GroupTest]:
        return [t for t in self.tests if t.family == name and t.kind == kind]


def temporal_dev2(s: Samples) -> FloatArray:
    """Unbiased squared deviation of each sample from its pixel's mean over the frames (NaN if 1 frame).

    The temporal variance is the noise free of every static bias pattern, so real and simulated
    noise compare without the bias leaking in.
    """
    key = (s.standpoint * 100_000 + np.round(s.v).astype(np.int64)) * 100_000 + np.round(s.u).astype(np.int64)
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    mean = np.bincount(inv, weights=s.err_m) / cnt
    n = cnt[inv].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = (s.err_m - mean[inv]) ** 2 * n / (n - 1)
    out[n < 2] = np.nan
    return out


def _frame_table(values: FloatArray, group: IntArray, s: Samples) -> tuple[NDArray[Any], ...]:
    """Per (group, frame) with samples: group, standpoint, mean of the values, count."""
    fidx, fsp = s.frame_index()
    nf = len(fsp)
    ok = (group >= 0) & np.isfinite(values)
    key = group[ok] * nf + fidx[ok]
    size = (int(group.max()) + 1) * nf if ok.any() else 0
    cnt = np.bincount(key, minlength=size).astype(np.float64)
    sums = np.bincount(key, weights=values[ok], minlength=size)
    nz = np.flatnonzero(cnt)
    return nz // nf, fsp[nz % nf], sums[nz] / cnt[nz], cnt[nz]


def _stand_stats(gk: IntArray, spk: IntArray, means: FloatArray, cnt: FloatArray
                 ) -> dict[tuple[int, int], tuple[float, float, int, float]]:
    """(group, standpoint) -> (mean of frame means, variance of frame means, frames, pixels)."""
    out: dict[tuple[int, int], tuple[float, float, int, float]] = {}
    key = gk * 1_000_000 + spk
    order = np.argsort(key, kind="stable")
    key_s = key[order]
    starts = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
    ends = np.r_[starts[1:], len(key_s)]
    for a, b in zip(starts, ends, strict=True):
        idx = order[a:b]
        m = means[idx]
        nf = len(m)
        var = float(np.var(m, ddof=1)) if nf > 1 else float("nan")
        out[(int(gk[idx[0]]), int(spk[idx[0]]))] = (float(m.mean()), var, nf, float(cnt[idx].sum()))
    return out


@dataclass
class Heterogeneity:
    """Random real-minus-sim plane per standpoint, in the disparity domain: delta = a + b x + c y (px).

    `tau2` (3,) are the variances of (a, b, c) across standpoints beyond their sampling scatter and
    beyond what the standpoint's distance (and temperature) explain: static per-standpoint errors a
    frame statistic cannot see (real reference poses worse than the simulated ones, frozen patterns).
    """

    tau2: FloatArray = field(default_factory=lambda: np.zeros(3))
    dof: float = float("inf")
    standpoints: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"plane_sd_px": [float(np.sqrt(t)) for t in self.tau2], "dof": self.dof,
                "standpoints": self.standpoints}


def _plane_design(s: Samples) -> FloatArray:
    return np.stack([np.ones(len(s)), (s.u - s.ppx) / s.fx, (s.v - s.ppy) / s.fx], axis=1)


def _frame_planes(s: Samples) -> dict[int, tuple[FloatArray, FloatArray, int]]:
    """Per standpoint: mean and variance over frames of the frame's disparity-domain plane (a, b, c)."""
    g = s.err_m / s.k_m_per_px
    X = _plane_design(s)
    out: dict[int, tuple[FloatArray, FloatArray, int]] = {}
    fk = s.frame_key
    uniq, inv = np.unique(fk, return_inverse=True)
    inv = inv.ravel()
    # normal equations per frame by bincount (3 x 3 and 3 x 1 sums)
    xtx = np.stack([np.bincount(inv, weights=X[:, i] * X[:, j], minlength=len(uniq))
                    for i in range(3) for j in range(3)], axis=1).reshape(-1, 3, 3)
    xty = np.stack([np.bincount(inv, weights=X[:, i] * g, minlength=len(uniq)) for i in range(3)], axis=1)
    ok = np.abs(np.linalg.det(xtx)) > 1e-12
    coef = np.full((len(uniq), 3), np.nan)
    coef[ok] = np.linalg.solve(xtx[ok], xty[ok][..., None])[..., 0]
    sp = uniq // 1_000_000
    for k in np.unique(sp):
        c = coef[(sp == k) & ok]
        if len(c) >= 2:
            out[int(k)] = (c.mean(axis=0), c.var(axis=0, ddof=1), len(c))
    return out


def _plane_rows(real: Samples, sim: Samples
                ) -> tuple[list[int], FloatArray, FloatArray, list[FloatArray], FloatArray]:
    """Per paired standpoint: its index, real-minus-sim plane (a, b, c), the plane's sampling variance
    and the covariate columns per component (offset: 1, disparity, temperature if it varies; the
    slopes: 1). The offset may follow distance (scale, offset) and temperature (drift): only what
    they do not explain is heterogeneity; the slopes are the same for every standpoint under any
    pixel effect."""
    pr, ps = _frame_planes(real), _frame_planes(sim)
    to_sim = standpoint_map(sim, real)
    # the reference pose's static error (estimated minus rendered plane, known on the simulated side):
    # each side has one per standpoint that the frames' scatter cannot see; pooled over standpoints
    # (one draw each is a poor variance) and counted twice (real and simulated)
    ref = _frame_planes(replace(sim, err_m=sim.ref_err_m)) if len(sim) else {}
    v_ref = 2 * np.mean([p[0] ** 2 for p in ref.values()], axis=0) if ref else np.zeros(3)
    rows = []
    for i in range(len(real.names)):
        j = int(to_sim[i])
        if i in pr and j >= 0 and j in ps:
            m = real.standpoint == i
            temp = real.temperature_c[m]
            rows.append((i, pr[i][0] - ps[j][0], pr[i][1] / pr[i][2] + ps[j][1] / ps[j][2],
                         float(np.mean(real.disparity_px[m])),
                         float(np.nanmean(temp)) if np.isfinite(temp).any() else 0.0))
    n = len(rows)
    d = np.array([r[1] for r in rows]).reshape(n, 3)
    v = np.array([r[2] for r in rows]).reshape(n, 3)
    disp = np.array([r[3] for r in rows])
    temp = np.array([r[4] for r in rows])
    cov_a = [np.ones(n), disp] + ([temp] if n and np.ptp(temp) > 0.5 else [])
    designs = [np.stack(cols, axis=1) for cols in (cov_a, [np.ones(n)], [np.ones(n)])]
    return [r[0] for r in rows], d, v, designs, np.asarray(v_ref, dtype=np.float64)


def _tau2(d: FloatArray, v: FloatArray, X: FloatArray) -> tuple[float, int]:
    """Moment estimate of the variance beyond sampling around a regression on X, and its dof."""
    n, p = X.shape
    if n - p < 2:
        return 0.0, 0
    H = X @ np.linalg.pinv(X)
    r = d - H @ d
    return max(0.0, float((r ** 2).sum() - ((1 - np.diag(H)) * v).sum()) / (n - p)), n - p


def heterogeneity(real: Samples, sim: Samples) -> Heterogeneity:
    """Between-standpoint variance of the real-minus-sim disparity planes (moments, after covariates)."""
    _, d, v, designs, _ = _plane_rows(real, sim)
    n = len(d)
    if n < 4:
        return Heterogeneity(np.zeros(3), float("inf"), n)
    tau2, dofs = np.zeros(3), []
    for k, X in enumerate(designs):
        tau2[k], dof = _tau2(d[:, k], v[:, k], X)
        if dof:
            dofs.append(dof)
    return Heterogeneity(tau2, float(min(dofs)) if dofs else float("inf"), n)


def heterogeneity_tests(real: Samples, sim: Samples) -> list[GroupTest]:
    """One test per standpoint: is its real-minus-sim plane (offset, slopes) one of the others' kind?

    Each standpoint's plane is predicted from the OTHER standpoints (their regression on the
    covariates and their heterogeneity beyond sampling), and its deviation is tested against the
    prediction's spread (its own sampling variance + the others' tau^2 + the prediction's variance;
    t with the others' dof), the three components combined (Sidak). A standpoint whose depth
    disagrees with its board pose far beyond the scatter of the others (a board moved between the
    colour and the depth frames, a pose from a wrong corner) is flagged; in the other tests it only
    widens the heterogeneity that every standpoint's SE carries."""
    idx, d, v, designs, v_ref = _plane_rows(real, sim)
    v = v + v_ref[None, :]   # a standpoint's own reference error is part of what it may deviate by
    n = len(idx)
    out: list[GroupTest] = []
    if n < 5:
        return out
    for a, i in enumerate(idx):
        keep = np.arange(n) != a
        best: tuple[float, int, float, float, float, float] | None = None
        for k, X in enumerate(designs):
            Xo = X[keep]
            tau2, dof = _tau2(d[keep, k], v[keep, k], Xo)
            if dof < 2:
                continue
            wts = 1.0 / (v[keep, k] + tau2)
            cov = np.linalg.pinv((Xo * wts[:, None]).T @ Xo)
            beta = cov @ (Xo * wts[:, None]).T @ d[keep, k]
            pred = float(X[a] @ beta)
            var = float(v[a, k] + tau2 + X[a] @ cov @ X[a])
            t = (d[a, k] - pred) / np.sqrt(var) if var > 0 else 0.0
            p = float(2 * stdtr(dof, -abs(t)))
            if best is None or p < best[0]:
                best = (p, k, float(d[a, k]), pred, float(np.sqrt(var)), float(dof))
        if best is None:
            continue
        p_min, k_min, real_k, pred_k, se, dof_k = best
        p_all = float(1.0 - (1.0 - p_min) ** len(designs))
        name = real.names[i]
        out.append(GroupTest("heterogeneity", "bias", name,
                             {"standpoint": name, "component": ("offset", "slope_u", "slope_v")[k_min],
                              "plane_px": real_k, "others_predict_px": pred_k},
                             real_k, pred_k, real_k - pred_k, se, (real_k - pred_k) / se if se > 0 else 0.0,
                             dof_k, p_all, int((real.standpoint == i).sum()), 0, axes=[]))
    return out


def compare_groups(real: Samples, sim: Samples, groups: Groups, kind: str,
                   real_values: FloatArray | None = None, sim_values: FloatArray | None = None,
                   het: Heterogeneity | None = None) -> list[GroupTest]:
    """One Welch test per group, standpoint-stratified, frame means as the independent units.

    Bias tests add, per standpoint, the variance of what is static within it: the reference error
    the simulation measures, or (if larger) the heterogeneity of the real-minus-sim planes.
    """
    rv = real.err_m if real_values is None else real_values
    sv = sim.err_m if sim_values is None else sim_values
    rs = _stand_stats(*_frame_table(rv, groups.real, real))
    # the sim side's standpoints in the real side's numbering: pairs are the same standpoint by name
    to_real = standpoint_map(real, sim)

    def sim_stats(values: FloatArray) -> dict[tuple[int, int], tuple[float, float, int, float]]:
        """Per (group, standpoint) frame statistics of the sim side, keyed by the real side's
        standpoint; standpoints the real side lacks are left out."""
        return {(g, int(to_real[sp])): v for (g, sp), v in _stand_stats(*_frame_table(values, groups.sim,
                                                                                      sim)).items()
                if to_real[sp] >= 0}

    ss = sim_stats(sv)
    if kind == "noise":   # standpoints too short for a temporal variance on either side: no noise test
        short = set(short_standpoints(real)) | set(short_standpoints(sim))
        drop = {i for i, n in enumerate(real.names) if n in short}
        rs = {k: v for k, v in rs.items() if k[1] not in drop}
    # the real reference plane carries one pose error per standpoint that no frame statistic sees;
    # its size comes from the simulation, where the estimated and the true plane are both known.
    # Only the standpoints a test pairs count: one the real side lacks would set the size (and its
    # degrees of freedom) of every group it falls in
    ref = sim_stats(sim.ref_err_m) if kind == "bias" else {}
    sp_r = to_real[sim.standpoint] if len(sim) else np.zeros(0, np.int64)
    paired = (sp_r >= 0) & (groups.sim >= 0)
    # pose errors grow like z^2 (reference_pose_noise): scale one pooled constant to each group
    c_ref = (float(np.mean(sim.ref_err_m[paired] ** 2 / sim.z_ref_m[paired] ** 4))
             if kind == "bias" and paired.any() else 0.0)
    nsp = max(len(real.names), 1)
    cell = np.where(paired, groups.sim * nsp + np.maximum(sp_r, 0), 0)
    ncell = len(groups.labels) * nsp
    z4 = np.bincount(cell, weights=np.where(paired, sim.z_ref_m ** 4, 0.0), minlength=ncell)
    n4 = np.bincount(cell, weights=paired.astype(float), minlength=ncell)
    het_v: dict[tuple[int, int], float] = {}
    if kind == "bias" and het is not None and np.any(het.tau2 > 0):
        X = _plane_design(real) * real.k_m_per_px[:, None]
        mom = [_stand_stats(*_frame_table(X[:, j], groups.real, real)) for j in range(3)]
        for key in mom[0]:
            het_v[key] = float(sum(het.tau2[j] * mom[j][key][0] ** 2 for j in range(3)))
    out: list[GroupTest] = []
    for g, label in enumerate(groups.labels):
        pairs = [(k, rs[k], ss[k]) for k in rs if k[0] == g and k in ss]
        pairs = [(k, r, s) for k, r, s in pairs
                 if r[2] >= 2 and s[2] >= 2 and r[3] >= MIN_SAMPLES and s[3] >= MIN_SAMPLES]
        if not pairs:
            continue
        w = np.array([r[3] for _, r, _ in pairs])
        w = w / w.sum()
        d = np.array([r[0] - s[0] for _, r, s in pairs])
        a_r = np.array([r[1] / r[2] for _, r, _ in pairs]) * w ** 2
        a_s = np.array([s[1] / s[2] for _, _, s in pairs]) * w ** 2
        df_r = np.array([r[2] - 1 for _, r, _ in pairs], dtype=np.float64)
        df_s = np.array([s[2] - 1 for _, _, s in pairs], dtype=np.float64)
        ref_var = [ref[k][0] ** 2 for k, _, _ in pairs if k in ref]
        # one draw per standpoint is a poor variance estimate: floor it by the pixel-level mean
        cells = [g * nsp + k[1] for k, _, _ in pairs]
        ref_floor = c_ref * float(z4[cells].sum() / max(n4[cells].sum(), 1.0))
        v_ref = max(float(np.mean(ref_var)) if ref_var else 0.0, ref_floor)
        v_het = np.array([het_v.get(k, 0.0) for k, _, _ in pairs])
        a_ref = w ** 2 * np.maximum(v_ref, v_het)
        use_het = bool(np.any(v_het > v_ref))
        ref_dof = (het.dof if use_het and het is not None else max(len(ref_var), 1))
        var = float(a_r.sum() + a_s.sum() + a_ref.sum())
        diff = float((w * d).sum())
        real_m = float(sum(wi * r[0] for wi, (_, r, _) in zip(w, pairs, strict=True)))
        sim_m = float(sum(wi * s[0] for wi, (_, _, s) in zip(w, pairs, strict=True)))
        denom = float((a_r ** 2 / df_r).sum() + (a_s ** 2 / df_s).sum()
                      + (a_ref.sum() ** 2 / ref_dof if a_ref.sum() > 0 else 0.0))
        dof = var ** 2 / denom if denom > 0 else float("inf")
        se = float(np.sqrt(var))
        if se > 0:
            t = diff / se
            p = float(2 * stdtr(dof, -abs(t)))
        else:
            t, p = (0.0, 1.0) if diff == 0 else (float("inf"), 0.0)
        out.append(GroupTest(groups.family, kind, label, groups.coords[g], real_m, sim_m, diff, se,
                             float(t), float(dof), p, int(sum(r[3] for _, r, _ in pairs)),
                             int(sum(s[3] for _, _, s in pairs)), axes=list(groups.axes)))
    return out


def holm(p: FloatArray, alpha: float = ALPHA) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Holm-Bonferroni adjusted p-values and rejections (controls the family-wise error rate)."""
    p = np.asarray(p, dtype=np.float64)
    m = len(p)
    if m == 0:
        return p, np.zeros(0, dtype=bool)
    order = np.argsort(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj, adj <= alpha


def _binned(family: str, xr: FloatArray, xs: FloatArray, edges: FloatArray, unit: str, key: str,
            axes: tuple[str, ...] = ()) -> Groups:
    gr = np.digitize(xr, edges) - 1
    gs = np.digitize(xs, edges) - 1
    nb = len(edges) - 1
    gr[(gr < 0) | (gr >= nb) | ~np.isfinite(xr)] = -1
    gs[(gs < 0) | (gs >= nb) | ~np.isfinite(xs)] = -1
    labels = [f"{edges[i]:.4g}-{edges[i + 1]:.4g} {unit}" for i in range(nb)]
    coords = [{f"{key}_min": float(edges[i]), f"{key}_max": float(edges[i + 1])} for i in range(nb)]
    return Groups(family, gr.astype(np.int64), gs.astype(np.int64), labels, coords, axes)


def _quantile_edges(x: FloatArray, bins: int) -> FloatArray | None:
    fin = x[np.isfinite(x)]
    if not fin.size or float(fin.max() - fin.min()) <= 0:
        return None
    edges = np.unique(np.quantile(fin, np.linspace(0, 1, bins + 1)))
    edges[-1] += 1e-9 * max(1.0, abs(float(edges[-1])))
    return edges if len(edges) > 2 else None


def _frame_rank(s: Samples, like: Samples | None = None) -> FloatArray:
    """Position of each sample's frame within its standpoint, 0 (first) .. 1 (last) (among the
    frames of `like`, the real side, when given)."""
    pos, count = frame_positions(s, like)
    return np.asarray(pos / np.maximum(count - 1, 1), dtype=np.float64)


# the families of locate and the axes of explain's vocabulary each one looks along
FAMILY_AXES: dict[str, tuple[str, ...]] = {
    "standpoint": (), "grid": ("distance", "inclination"), "column": ("u",), "row": ("v",),
    "radius": ("radius",), "tile": ("tile",), "distance": ("distance",), "disparity": ("disparity",),
    "inclination": ("inclination",), "albedo": ("albedo",), "frame": ("frame",), "time": ("time",),
    "temperature": ("temperature",), "edge": ("edge",), "frame_common": ("frame",),
    "correlation_u": ("u",), "correlation_v": ("v",),
    "periodic_u": ("u",), "periodic_v": ("v",), "gradient_u": ("u",), "gradient_v": ("v",),
    "static": ("tile",), "heterogeneity": (),
}


def default_groups(real: Samples, sim: Samples, distance_step_m: float = 0.25,
                   inclination_step_deg: float = 10.0, column_bins: int = 8) -> list[Groups]:
    """The partitions explain tests: standpoints, the grid, and every axis the grid hides."""
    out: list[Groups] = []
    out.append(Groups("standpoint", real.standpoint.copy(), align_standpoints(real, sim), list(real.names),
                      [{"standpoint": n} for n in real.names]))
    # distance x inclination cells
    dmax = float(np.nanmax(np.r_[real.z_ref_m, sim.z_ref_m])) + distance_step_m
    de = np.arange(0.0, dmax + 1e-9, distance_step_m)
    ie = np.arange(0.0, 90.0 + 1e-9, inclination_step_deg)
    dr = np.digitize(real.z_ref_m, de) - 1
    ds = np.digitize(sim.z_ref_m, de) - 1
    ir = np.clip(np.digitize(real.inclination_deg, ie) - 1, 0, len(ie) - 2)
    is_ = np.clip(np.digitize(sim.inclination_deg, ie) - 1, 0, len(ie) - 2)
    ni = len(ie) - 1
    labels = [f"{de[a]:.2f}-{de[a + 1]:.2f} m, {ie[b]:.0f}-{ie[b + 1]:.0f} deg"
              for a in range(len(de) - 1) for b in range(ni)]
    coords = [{"distance_min_m": float(de[a]), "distance_max_m": float(de[a + 1]),
               "inclination_min_deg": float(ie[b]), "inclination_max_deg": float(ie[b + 1])}
              for a in range(len(de) - 1) for b in range(ni)]
    out.append(Groups("grid", (dr * ni + ir).astype(np.int64), (ds * ni + is_).astype(np.int64),
                      labels, coords, FAMILY_AXES["grid"]))
    width, height = 2 * real.ppx + 1, 2 * real.ppy + 1
    out.append(_binned("column", real.u, sim.u, np.linspace(0, width, column_bins + 1), "px", "u_px",
                       ("u",)))
    out.append(_binned("row", real.v, sim.v, np.linspace(0, height, 7), "px", "v_px", ("v",)))
    rr = np.hypot(real.u - real.ppx, real.v - real.ppy)
    rs = np.hypot(sim.u - sim.ppx, sim.v - sim.ppy)
    rmax = float(np.hypot(real.ppx, real.ppy)) + 1
    out.append(_binned("radius", rr, rs, np.linspace(0, rmax, 6), "px", "radius_px", ("radius",)))
    # a coarse 4 x 3 field of image tiles
    tu, tv = 4, 3
    tile_r = (np.clip((real.u / width * tu).astype(np.int64), 0, tu - 1)
              + tu * np.clip((real.v / height * tv).astype(np.int64), 0, tv - 1))
    tile_s = (np.clip((sim.u / width * tu).astype(np.int64), 0, tu - 1)
              + tu * np.clip((sim.v / height * tv).astype(np.int64), 0, tv - 1))
    out.append(Groups("tile", tile_r, tile_s, [f"tile u{k % tu} v{k // tu}" for k in range(tu * tv)],
                      [{"tile_u": k % tu, "tile_v": k // tu} for k in range(tu * tv)], ("tile",)))
    de1 = np.arange(0.0, dmax + 0.5, 0.5)
    out.append(_binned("distance", real.z_ref_m, sim.z_ref_m, de1, "m", "distance_m", ("distance",)))
    edges = _quantile_edges(np.r_[real.disparity_px, sim.disparity_px], 6)
    if edges is not None:
        out.append(_binned("disparity", real.disparity_px, sim.disparity_px, edges, "px", "disparity_px",
                           ("disparity",)))
    out.append(_binned("inclination", real.inclination_deg, sim.inclination_deg, ie, "deg",
                       "inclination_deg", ("inclination",)))
    out.append(Groups("albedo", (real.albedo >= 0.5).astype(np.int64), (sim.albedo >= 0.5).astype(np.int64),
                      list(ALBEDO_GROUPS), [{"albedo": g} for g in ALBEDO_GROUPS], ("albedo",)))
    fr_r, fr_s = _frame_rank(real), _frame_rank(sim, like=real)
    if np.ptp(fr_r) > 0:
        out.append(_binned("frame", fr_r, fr_s, np.array([0.0, 0.2, 0.4, 0.6, 0.8, 1.0 + 1e-9]), "of frames",
                           "frame_rank", ("frame",)))
    for fam, xr, xs, unit, key in (("time", real.time_s, sim.time_s, "s", "time_s"),
                                   ("temperature", real.temperature_c, sim.temperature_c, "degC",
                                    "temperature_c")):
        if fam == "time" and not real.time_stamps:   # no session clock: time would repeat the frame
            continue
        edges = _quantile_edges(xr, 5)
        if edges is not None:
            out.append(_binned(fam, xr, xs, edges, unit, key, (fam,)))
    if np.isfinite(real.edge_px).any():
        out.append(_binned("edge", real.edge_px, sim.edge_px, np.array([0.0, 3.0, 6.0, 12.0, 24.0, np.inf]),
                           "px", "edge_px", ("edge",)))
    return out


def _frame_common_tests(real: Samples, sim: Samples, st_r: Structure, st_s: Structure) -> list[GroupTest]:
    """Variance of the frames' common part (split-half covariance), real vs sim, per standpoint and
    pooled. Tested in px^2 of disparity (homogeneous over distance for a disparity noise; the pooled
    test weighs standpoints equally) against its spread when nothing is common (from the halves'
    difference, so real noise of any size or correlation sets it), reported in m^2 at the
    standpoint's mean K."""
    fr, fs = frame_common(real, st_r), frame_common(sim, st_s)
    to_sim = standpoint_map(sim, real)
    rows = []
    for i, sp in enumerate(fr.standpoint):
        hit = np.flatnonzero(fs.standpoint == to_sim[sp])   # none where sim lacks it (-1)
        if not hit.size:
            continue
        k = hit[0]
        # under the null both sides share one common variance: their mean (0 if nothing is common)
        pooled = np.array([(fr.excess_px2[i] + fs.excess_px2[k]) / 2])
        se = float(np.hypot(fr.se_null(pooled)[i], fs.se_null(pooled)[k]))
        rows.append((real.names[sp], fr.excess_px2[i], fs.excess_px2[k],
                     se, float(min(fr.frames[i], fs.frames[k]) - 1),
                     fr.k_m[i] ** 2, int(fr.frames[i]), int(fs.frames[k])))
    out = []
    for name, r, s_, se, dof, k2, nr, ns in rows:
        out.append(_test("frame_common", name, {"standpoint": name, "k2_m2_per_px2": k2}, r * k2, s_ * k2,
                         (r - s_) * k2, se * k2,
                         dof, nr, ns))
    if len(rows) >= 2:
        n = len(rows)
        d = float(np.mean([r[1] - r[2] for r in rows]))
        se = float(np.sqrt(sum(r[3] ** 2 for r in rows)) / n)
        k2 = float(np.mean([r[5] for r in rows]))
        out.append(_test("frame_common", "all standpoints", {"standpoint": "all", "k2_m2_per_px2": k2},
                         float(np.mean([r[1] for r in rows])) * k2, float(np.mean([r[2] for r in rows])) * k2,
                         d * k2, se * k2, float(sum(r[4] for r in rows)),
                         sum(r[6] for r in rows), sum(r[7] for r in rows)))
    return out


def _test(family: str, label: str, coords: dict[str, Any], real: float, sim: float, diff: float, se: float,
          dof: float, n_real: int, n_sim: int) -> GroupTest:
    t = diff / se if se > 0 else (0.0 if diff == 0 else float("inf"))
    p = float(2 * stdtr(max(dof, 1.0), -abs(t))) if np.isfinite(t) else 0.0
    return GroupTest(family, "noise", label, coords, real, sim, diff, se, float(t), dof, p, n_real, n_sim,
                     axes=list(FAMILY_AXES.get(family, ())))


def _correlation_tests(real: Samples, sim: Samples, st_r: Structure, st_s: Structure) -> list[GroupTest]:
    """Correlation of neighbouring pixels' within-frame noise along u and v, real vs sim.

    Per pair a normalised product w_i w_j / sigma^2 (sigma^2 of its standpoint); their frame means
    are the units, as for every other test. Two lags per axis: the nearest and one further out.
    """
    out: list[GroupTest] = []
    for axis in ("u", "v"):
        common = sorted({k for k in st_r.pairs if k[0] == axis} & {k for k in st_s.pairs if k[0] == axis},
                        key=lambda k: k[1])
        if not common:
            continue
        chosen = [common[0], *[k for k in common if k[1] >= 3 * common[0][1]][:1]]
        for key in chosen:
            vals = []
            for s, st in ((real, st_r), (sim, st_s)):
                i, j = st.pairs[key]
                tot = np.bincount(s.standpoint, weights=np.nan_to_num(st.dev2), minlength=len(s.names))
                cnt = np.bincount(s.standpoint, weights=np.isfinite(st.dev2).astype(float),
                                  minlength=len(s.names))
                sig2 = tot / np.maximum(cnt, 1)
                x = np.full(len(s), np.nan)
                with np.errstate(invalid="ignore", divide="ignore"):
                    x[i] = st.within[i] * st.within[j] / sig2[s.standpoint[i]]
                vals.append(x)
            g = Groups(f"correlation_{axis}", np.where(np.isfinite(vals[0]), 0, -1),
                       np.where(np.isfinite(vals[1]), 0, -1), [f"{axis} lag {key[1]:.3g} px"],
                       [{"axis": axis, "lag_px": key[1]}], FAMILY_AXES[f"correlation_{axis}"])
            out += compare_groups(real, sim, g, "noise", vals[0], vals[1])
    return out


def locate(real: Samples, sim: Samples, alpha: float = ALPHA, groups: list[Groups] | None = None,
           structures: tuple[Structure, Structure] | None = None) -> LocateResult:
    """All bias and noise tests of real against sim, Holm-corrected together."""
    groups = default_groups(real, sim) if groups is None else groups
    st_r, st_s = structures if structures is not None else (decompose(real), decompose(sim))
    het = heterogeneity(real, sim)
    tests: list[GroupTest] = []
    for g in groups:
        tests += compare_groups(real, sim, g, "bias", het=het)
        tests += compare_groups(real, sim, g, "noise", st_r.dev2, st_s.dev2)
    tests += _frame_common_tests(real, sim, st_r, st_s)
    tests += _correlation_tests(real, sim, st_r, st_s)
    window = st_r.corr.window_px if st_r.corr.fraction > 0.2 else 9.0
    tests += [GroupTest(**t) for t in fine_tests(real, sim, window)]
    tests += heterogeneity_tests(real, sim)
    adj, rej = holm(np.array([t.p for t in tests]), alpha)
    for t, a, r in zip(tests, adj, rej, strict=True):
        t.p_adj, t.significant = float(a), bool(r)
    return LocateResult(tests, het, (st_r.corr, st_s.corr))


def residual_grid(loc: LocateResult, kind: str = "bias") -> tuple[Any, Any, Any] | None:
    """(distance edges m, inclination edges deg, real - sim per cell, NaN where untested)."""
    tests = loc.family("grid", kind)
    if not tests:
        return None
    d = sorted({t.coords["distance_min_m"] for t in tests} | {t.coords["distance_max_m"] for t in tests})
    i = sorted({t.coords["inclination_min_deg"] for t in tests}
               | {t.coords["inclination_max_deg"] for t in tests})
    de, ie = np.array(d), np.array(i)
    m = np.full((len(de) - 1, len(ie) - 1), np.nan)
    for t in tests:
        a = int(np.searchsorted(de, t.coords["distance_min_m"]))
        b = int(np.searchsorted(ie, t.coords["inclination_min_deg"]))
        m[a, b] = t.diff
    return de, ie, m
