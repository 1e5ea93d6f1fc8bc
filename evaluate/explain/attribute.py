"""Attribute: which catalogue effects explain the real-minus-simulated residual, with what parameters.

The residual's tables (`tables`) are fitted by weighted least squares (`mixed_model`). Selection
is forward, by BIC; a candidate enters only if it also lowers the held-out RMSE (leave one standpoint
out, or frame blocks when there are fewer than three standpoints) and its Wald test is strong.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from depthstation.evaluate.explain.basis import Candidate
from depthstation.evaluate.explain.mixed_model import bic, gls, heldout_rmse, wald_p
from depthstation.evaluate.explain.samples import FloatArray, Samples
from depthstation.evaluate.explain.structure import Structure, decompose
from depthstation.evaluate.explain.tables import (
    CorrVar,
    NoiseVar,
    Table,
    bias_table,
    default_tile_px,
    frame_table,
    variance_table,
)

BIC_THRESHOLD = -10.0      # "very strong" evidence (Kass & Raftery)
NEAR_TIE = 6.0             # a runner-up within this BIC gap is only "positive" evidence apart: reported
WALD_P = 1e-3


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
    tile = max(default_tile_px(real), 2.5 * window)
    bt = bias_table(real, sim, candidates, blocks=blocks, noise_var=noise_var, corr_var=corr_var,
                    density=st[0].density, tile_px=tile)
    vt = variance_table(real, sim, candidates, structures=st)
    ft = frame_table(real, sim, candidates, structures=st)
    fits = forward_select(bt, candidates, present, real) + forward_select(vt, candidates, present, real)
    return Attribution(rank(fits), len(bt), len(vt), {"bias": bt, "variance": vt, "frame": ft})
