"""Locate: where do real and simulated errors differ, beyond what chance explains?

Pixels of one frame share the frame's pose, temperature and correlated noise, so they are not
independent: every standard error here comes from the scatter of per-frame means within a
standpoint (Welch, Satterthwaite degrees of freedom), and standpoints are combined by pixel-count
weights. One test per group and quantity; all p-values of a run are corrected together (Holm).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from depthstation.evaluate.explain.samples import FloatArray, IntArray, Samples

ALPHA = 0.05
MIN_SAMPLES = 30


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


@dataclass
class LocateResult:
    tests: list[GroupTest] = field(default_factory=list)

    @property
    def significant(self) -> list[GroupTest]:
        return [t for t in self.tests if t.significant]

    def summary(self) -> dict[str, Any]:
        """`mismatch` block of explain.json: flag, differing standpoints, differing regions."""
        sig = self.significant
        standpoints = sorted({t.label for t in sig if t.family == "standpoint"})
        regions = [{"family": t.family, "kind": t.kind, "label": t.label, **t.coords,
                    "diff": t.diff, "se": t.se, "p_adj": t.p_adj}
                   for t in sorted(sig, key=lambda t: t.p) if t.family != "standpoint"]
        return {"significant": bool(sig), "standpoints": standpoints, "regions": regions,
                "tests": len(self.tests), "alpha": ALPHA, "correction": "holm"}

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
    """Per (group, standpoint, frame): sum, count. Returns keys split into group, standpoint."""
    ok = (group >= 0) & np.isfinite(values)
    g, sp, fr, val = group[ok], s.standpoint[ok], s.frame[ok], values[ok]
    key = (g * 100_000 + sp) * 10_000_000 + fr
    uniq, inv = np.unique(key, return_inverse=True)
    inv = inv.ravel()
    sums = np.bincount(inv, weights=val, minlength=len(uniq))
    cnt = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    return uniq // 10_000_000 // 100_000, uniq // 10_000_000 % 100_000, sums / np.maximum(cnt, 1), cnt


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


def compare_groups(real: Samples, sim: Samples, groups: Groups, kind: str,
                   real_values: FloatArray | None = None, sim_values: FloatArray | None = None
                   ) -> list[GroupTest]:
    """One Welch test per group, standpoint-stratified, frame means as the independent units."""
    rv = real.err_m if real_values is None else real_values
    sv = sim.err_m if sim_values is None else sim_values
    rs = _stand_stats(*_frame_table(rv, groups.real, real))
    ss = _stand_stats(*_frame_table(sv, groups.sim, sim))
    # the real reference plane carries one pose error per standpoint that no frame statistic sees;
    # its size comes from the simulation, where the estimated and the true plane are both known
    ref = _stand_stats(*_frame_table(sim.ref_err_m, groups.sim, sim)) if kind == "bias" else {}
    # pose errors grow like z^2 (reference_pose_noise): scale one pooled constant to each group
    c_ref = float(np.mean(sim.ref_err_m ** 2 / sim.z_ref_m ** 4)) if kind == "bias" and len(sim) else 0.0
    z4 = np.bincount(np.maximum(groups.sim, 0), weights=np.where(groups.sim >= 0, sim.z_ref_m ** 4, 0.0),
                     minlength=len(groups.labels))
    n4 = np.bincount(np.maximum(groups.sim, 0), weights=(groups.sim >= 0).astype(float),
                     minlength=len(groups.labels))
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
        ref_var = [ref[k][0] ** 2 for k in ref if k[0] == g]
        # one draw per standpoint is a poor variance estimate: floor it by the pixel-level mean
        ref_floor = c_ref * float(z4[g] / max(n4[g], 1.0))
        v_ref = max(float(np.mean(ref_var)) if ref_var else 0.0, ref_floor)
        a_ref = w ** 2 * v_ref
        var = float(a_r.sum() + a_s.sum() + a_ref.sum())
        diff = float((w * d).sum())
        real_m = float(sum(wi * r[0] for wi, (_, r, _) in zip(w, pairs, strict=True)))
        sim_m = float(sum(wi * s[0] for wi, (_, _, s) in zip(w, pairs, strict=True)))
        denom = float((a_r ** 2 / df_r).sum() + (a_s ** 2 / df_s).sum()
                      + (a_ref.sum() ** 2 / max(len(ref_var), 1) if v_ref > 0 else 0.0))
        dof = var ** 2 / denom if denom > 0 else float("inf")
        se = float(np.sqrt(var))
        if se > 0:
            t = diff / se
            p = float(2 * stats.t.sf(abs(t), dof))
        else:
            t, p = (0.0, 1.0) if diff == 0 else (float("inf"), 0.0)
        out.append(GroupTest(groups.family, kind, label, groups.coords[g], real_m, sim_m, diff, se,
                             float(t), float(dof), p, int(sum(r[3] for _, r, _ in pairs)),
                             int(sum(s[3] for _, _, s in pairs))))
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


def _binned(family: str, xr: FloatArray, xs: FloatArray, edges: FloatArray, unit: str, key: str
            ) -> Groups:
    gr = np.digitize(xr, edges) - 1
    gs = np.digitize(xs, edges) - 1
    nb = len(edges) - 1
    gr[(gr < 0) | (gr >= nb) | ~np.isfinite(xr)] = -1
    gs[(gs < 0) | (gs >= nb) | ~np.isfinite(xs)] = -1
    labels = [f"{edges[i]:.4g}-{edges[i + 1]:.4g} {unit}" for i in range(nb)]
    coords = [{f"{key}_min": float(edges[i]), f"{key}_max": float(edges[i + 1])} for i in range(nb)]
    return Groups(family, gr.astype(np.int64), gs.astype(np.int64), labels, coords)


def default_groups(real: Samples, sim: Samples, distance_step_m: float = 0.25,
                   inclination_step_deg: float = 10.0, column_bins: int = 8) -> list[Groups]:
    """The partitions explain tests: standpoints, the grid, and the axes the grid hides."""
    out: list[Groups] = []
    sp_r = real.standpoint.copy()
    sim_idx = {n: i for i, n in enumerate(sim.names)}
    remap = np.array([sim_idx.get(n, -1) for n in real.names] or [-1])
    inv = np.full(max(len(sim.names), 1), -1)
    for i, j in enumerate(remap):
        if j >= 0:
            inv[j] = i
    out.append(Groups("standpoint", sp_r, inv[sim.standpoint], list(real.names),
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
                      labels, coords))
    width = 2 * real.ppx + 1
    out.append(_binned("column", real.u, sim.u, np.linspace(0, width, column_bins + 1), "px", "u_px"))
    rr = np.hypot(real.u - real.ppx, real.v - real.ppy)
    rs = np.hypot(sim.u - sim.ppx, sim.v - sim.ppy)
    rmax = float(np.hypot(real.ppx, real.ppy)) + 1
    out.append(_binned("radius", rr, rs, np.linspace(0, rmax, 6), "px", "radius_px"))
    out.append(Groups("albedo", (real.albedo >= 0.5).astype(np.int64), (sim.albedo >= 0.5).astype(np.int64),
                      ["black", "white"], [{"albedo": "black"}, {"albedo": "white"}]))
    for fam, xr, xs, unit, key in (("time", real.time_s, sim.time_s, "s", "time_s"),
                                   ("temperature", real.temperature_c, sim.temperature_c, "degC",
                                    "temperature_c")):
        fin = xr[np.isfinite(xr)]
        if fin.size and float(fin.max() - fin.min()) > 0:
            edges = np.unique(np.quantile(fin, np.linspace(0, 1, 6)))
            edges[-1] += 1e-9
            if len(edges) > 2:
                out.append(_binned(fam, xr, xs, edges, unit, key))
    if np.isfinite(real.edge_px).any():
        out.append(_binned("edge", real.edge_px, sim.edge_px, np.array([0.0, 2.0, 5.0, 10.0, 30.0]),
                           "px", "edge_px"))
    return out


def locate(real: Samples, sim: Samples, alpha: float = ALPHA, groups: list[Groups] | None = None
           ) -> LocateResult:
    """All bias and noise tests of real against sim, Holm-corrected together."""
    groups = default_groups(real, sim) if groups is None else groups
    r2, s2 = temporal_dev2(real), temporal_dev2(sim)
    tests: list[GroupTest] = []
    for g in groups:
        tests += compare_groups(real, sim, g, "bias")
        if g.family in ("standpoint", "grid", "albedo"):
            tests += compare_groups(real, sim, g, "noise", r2, s2)
    adj, rej = holm(np.array([t.p for t in tests]), alpha)
    for t, a, r in zip(tests, adj, rej, strict=True):
        t.p_adj, t.significant = float(a), bool(r)
    return LocateResult(tests)


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
