"""Discover: physics outside the catalogue, fitted from a library of generic terms.

After the catalogue selection (`attribute`), the same tables (bias tiles, within-frame variance
tiles with neighbour rows, frame-common rows) are searched again with the generic terms of
`library` added to the pool, under the same guards: a term enters only if delta BIC < -10, the
held-out RMSE (leave one standpoint out, or frame blocks) falls and its Wald test gives p < 0.001.
At every step:

- catalogue effects keep priority: one within `NEAR_TIE` in BIC of the best generic term is tried
  first (it explains as well, and has a name);
- the simplest sufficient term first: of the generic terms within `NEAR_TIE` of the best, the one
  with the fewest coefficients is tried first; the others are reported as near ties;
- a term along axes that an already selected generic term of the same quantity covers is not tried.

A catalogue effect selected before a generic term entered is checked again at the end (backward):
if the joint fit no longer needs it (its Wald p >= 0.001 or dropping it costs less than 10 in BIC)
it is dropped: the discovered term explained what it had absorbed (a z^4 noise refitted as a
larger `disparity_noise`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from depthstation.evaluate.explain.attribute import (
    BIC_THRESHOLD,
    NEAR_TIE,
    WALD_P,
    Attribution,
    CandidateFit,
    _fit_record,
    _params,
    _usable,
    negative_variances,
    rank,
)
from depthstation.evaluate.explain.basis import Candidate
from depthstation.evaluate.explain.mixed_model import bic, cluster_cov, gls, heldout_rmse, wald_p
from depthstation.evaluate.explain.samples import Samples
from depthstation.evaluate.explain.tables import Table


@dataclass
class DiscoveredTerm:
    """A generic term that entered the model: what, where, how much, how sure, what it means."""

    candidate: Candidate
    table: str
    coef: dict[str, float]
    stderr: dict[str, float]
    delta_bic: float
    heldout_rmse_before_m: float
    heldout_rmse_after_m: float
    wald_p: float
    step: int
    near_ties: list[dict[str, Any]] = field(default_factory=list)
    cov: list[list[float]] = field(default_factory=list)

    @property
    def quantity(self) -> str:
        assert self.candidate.spec is not None
        return self.candidate.spec.quantity

    @property
    def axes(self) -> list[str]:
        assert self.candidate.spec is not None
        return list(self.candidate.spec.axes)

    @property
    def effect(self) -> str:
        """The model TOML name of the term (`term_<quantity>_<axes>_<basis>`)."""
        assert self.candidate.spec is not None
        return self.candidate.spec.name

    def params(self) -> dict[str, float]:
        """Everything the model's effect needs: fitted coefficients and fixed references."""
        return {**self.candidate.fixed, **self.coef}

    def to_dict(self) -> dict[str, Any]:
        """The `discovered` entry of explain.json (exactly the issue's fields)."""
        spec = self.candidate.spec
        assert spec is not None
        units = dict(zip(self.candidate.params, self.candidate.units, strict=True))
        return {
            "quantity": spec.quantity,
            "axes": list(spec.axes),
            "expression": (spec.expression({**self.coef, **self.candidate.fixed})
                           + _fixed_text(self.candidate)),
            "coefficients": {k: {"value": v, "unit": units[k], "stderr": self.stderr.get(k)}
                             for k, v in self.coef.items()},
            "heldout_rmse_before_m": self.heldout_rmse_before_m,
            "heldout_rmse_after_m": self.heldout_rmse_after_m,
            "interpretation": list(self.candidate.interpretation),
        }

    def details(self) -> dict[str, Any]:
        """What the selection saw (explain.json `discovery.terms`)."""
        return {"term": self.effect, "table": self.table, "step": self.step, "delta_bic": self.delta_bic,
                "wald_p": self.wald_p, "fixed": dict(self.candidate.fixed), "near_ties": self.near_ties}


def _fixed_text(c: Candidate) -> str:
    return "".join(f"; {k} = {v:.6g}" for k, v in c.fixed.items())


@dataclass
class Discovery:
    terms: list[DiscoveredTerm] = field(default_factory=list)
    dropped: list[dict[str, Any]] = field(default_factory=list)     # catalogue effects superseded
    kept: list[dict[str, Any]] = field(default_factory=list)        # catalogue effects kept against generic
    rejected: list[dict[str, Any]] = field(default_factory=list)    # best terms that failed a guard
    library_size: int = 0

    def summary(self) -> dict[str, Any]:
        return {"library_size": self.library_size, "terms": [t.details() for t in self.terms],
                "dropped_catalogue": self.dropped, "kept_catalogue": self.kept, "rejected": self.rejected}


def _covers(c: Candidate) -> set[str]:
    """The axes a generic term spans: a field over the image spans u, v and the radius too."""
    assert c.spec is not None
    axes = set(c.spec.axes)
    return axes | {"u", "v", "radius"} if "tile" in axes else axes


def _eligible(c: Candidate, selected: Sequence[str], by_name: dict[str, Candidate]) -> bool:
    if c.name in selected:
        return False
    for o in selected:
        other = by_name[o]
        if c.name in other.excludes or o in c.excludes:
            return False
        if c.spec is not None and other.spec is not None and other.spec.quantity == c.spec.quantity \
                and _covers(other) & _covers(c):
            return False
    return True


def _identifiable(t: Table, names: Sequence[str]) -> bool:
    """The joint design has full rank: no column a combination of the others (e.g. a quadratic in
    albedo on a board of two reflectances, or a term inside an effect already selected)."""
    X = np.concatenate([t.X[n] for n in names], axis=1) * np.sqrt(t.w)[:, None]
    norms = np.linalg.norm(X, axis=0)
    if np.any(norms == 0):
        return False
    sv = np.linalg.svd(X / norms, compute_uv=False)
    return bool(sv[-1] > 1e-4 * sv[0])


MAX_TRIES = 4   # further terms tried at a step when the near ties fail the guards


def generic_threshold(n_terms: int) -> float:
    """delta BIC a generic term must beat: the catalogue's -10 plus the extended-BIC price of
    searching n terms, 2 ln n (Chen & Chen 2008): the best of many null terms looks good by chance."""
    return BIC_THRESHOLD - 2.0 * float(np.log(max(n_terms, 1)))


def _guards(t: Table, selected: list[str], name: str, base_rmse: float
            ) -> tuple[float, float, Any, Any, str]:
    """Held-out RMSE after, Wald p, coefficients and SEs, and which guard failed ('' if none)."""
    after = heldout_rmse(t, [*selected, name])
    p, b, se = wald_p(t, [*selected, name], name)
    why = ""
    if not after < base_rmse:
        why = "held-out RMSE does not fall"
    elif not p < WALD_P:
        why = f"Wald p {p:.2g} >= {WALD_P:g}"
    return after, p, b, se, why


@dataclass
class TableResult:
    selected: list[str]
    terms: list[DiscoveredTerm]
    fits: dict[str, CandidateFit]
    dropped: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    bic: float


Record = dict[str, Any]
PROXIES = {"time": "frame", "frame": "time", "disparity": "distance", "distance": "disparity"}
"""Axes that stand in for one another: time within a standpoint is the frame's position; disparity is
fB / distance. A generic term along one is tested against the catalogue effect of the same physics."""


def select_table(t: Table, catalogue: Sequence[Candidate], lib: Sequence[Candidate],
                 fits: dict[str, CandidateFit], present: dict[str, dict[str, float]], real: Samples,
                 max_terms: int = 4
                 ) -> tuple[list[DiscoveredTerm], list[Record], list[Record], list[Record]]:
    """Discovery on one table (updates `fits` in place): the catalogue's choice continued with the
    library; if the catalogue chose anything, the same from an empty model too. The path without
    the catalogue's choice wins only if it is better in BIC AND on held-out standpoints, and every
    catalogue effect it leaves out is no longer significant beside its generic terms.
    Returns (terms, catalogue effects dropped, best rejected terms, catalogue effects kept against a
    generic path), each drop and keep with why."""
    start = [f.effect for f in fits.values() if f.selected and f.effect in t.X]
    seq = _select(t, catalogue, lib, copy_fits(fits), present, real, start, max_terms)
    best = seq
    kept: list[dict[str, Any]] = []
    if start:
        fresh = copy_fits(fits)
        for f in fresh.values():
            f.selected, f.step, f.near_ties = False, None, []
        uni = _select(t, catalogue, lib, fresh, present, real, [], max_terms)
        left_out = [n for n in start if n not in uni.selected]
        if uni.bic < seq.bic and left_out:
            why_keep = _catalogue_holds(t, seq, uni, left_out)
            if why_keep:
                kept = [{"effect": n, "table": t.name, "generic_path": [x.effect for x in uni.terms],
                         "bic_gap": float(uni.bic - seq.bic), "why": why_keep} for n in left_out]
            else:
                best = uni
                h_seq, h_uni = heldout_rmse(t, seq.selected), heldout_rmse(t, uni.selected)
                a, b = _rmse_pair(t, h_seq, h_uni)
                best.dropped = [{"effect": n, "table": t.name, "bic_gap": float(uni.bic - seq.bic),
                                 "heldout_rmse_with_m": a, "heldout_rmse_without_m": b,
                                 "why": "the discovered terms (" + ", ".join(x.effect for x in uni.terms)
                                 + f") explain the residual better without it: BIC {uni.bic - seq.bic:.1f}, "
                                 f"held-out RMSE {_mm(t, a)} -> {_mm(t, b)}, and beside them it is no "
                                 "longer significant"} for n in left_out]
        elif uni.bic < seq.bic:
            best = uni
    fits.clear()
    fits.update(best.fits)
    return best.terms, best.dropped, best.rejected, kept


def _mm(t: Table, x: float) -> str:
    return f"{x * 1e3:.3g} mm"


def _catalogue_holds(t: Table, seq: TableResult, uni: TableResult, left_out: list[str]) -> str:
    """Why the catalogue's path stands against a generic path of lower BIC ('' if it does not):
    the generic path must also predict held-out standpoints better, and each catalogue effect it
    leaves out must lose its significance beside the generic terms (tested jointly; where they
    contain it, it has none of its own)."""
    h_seq, h_uni = heldout_rmse(t, seq.selected), heldout_rmse(t, uni.selected)
    a, b = _rmse_pair(t, h_seq, h_uni)
    generic = ", ".join(x.effect for x in uni.terms) or "none"
    if not h_uni < h_seq:
        return (f"the generic terms ({generic}) fit better in BIC ({uni.bic - seq.bic:.1f}) but not on "
                f"held-out standpoints (RMSE {_mm(t, b)} against {_mm(t, a)} with the catalogue effect)")
    proxy = sorted({a2 for x in uni.terms for a2 in x.axes if a2 in PROXIES})
    for n in left_out:
        joint = [*uni.selected, n]
        if not _identifiable(t, joint):
            # the generic terms contain the effect (a radial distortion inside a quadratic field) and
            # say more: better in BIC and on held-out standpoints, the larger form stands
            continue
        p, _, _ = wald_p(t, joint, n)
        if p < WALD_P:
            return (f"{n} stays significant beside the generic terms ({generic}; Wald p {p:.2g} in the joint "
                    "fit)" + (f"; their axes ({', '.join(proxy)}) are proxies of "
                              f"{', '.join(PROXIES[x] for x in proxy)}" if proxy else ""))
    return ""


def copy_fits(fits: dict[str, CandidateFit]) -> dict[str, CandidateFit]:
    return {k: replace(f, params=dict(f.params), stderr=dict(f.stderr), units=dict(f.units),
                       coef=list(f.coef), near_ties=list(f.near_ties)) for k, f in fits.items()}


def _select(t: Table, catalogue: Sequence[Candidate], lib: Sequence[Candidate], fits: dict[str, CandidateFit],
            present: dict[str, dict[str, float]], real: Samples, start: list[str], max_terms: int
            ) -> TableResult:
    """Forward selection over catalogue + library from `start` (catalogue priority, simplest first)."""
    cat = [c for c in catalogue if c.name in t.X and _usable(t, c.name)]
    gen = [c for c in lib if c.name in t.X and _usable(t, c.name)]
    by_name = {c.name: c for c in [*cat, *gen]}
    selected = list(start)
    terms: list[DiscoveredTerm] = []
    rejected: list[dict[str, Any]] = []
    if not gen or len(t) < 4:
        return TableResult(selected, terms, fits, [], rejected, bic(t, selected))
    step = max((f.step or 0 for f in fits.values() if f.selected), default=0)
    proxy_notes: list[dict[str, Any]] = []
    while len(terms) < max_terms:
        base_bic = bic(t, selected)
        base_rmse = heldout_rmse(t, selected)
        trials = [(bic(t, [*selected, c.name]) - base_bic, c) for c in [*cat, *gen]
                  if _eligible(c, selected, by_name) and _identifiable(t, [*selected, c.name])]
        g_trials = sorted(((d, c) for d, c in trials if c.generic), key=lambda x: x[0])
        if not g_trials:
            break
        best_g = g_trials[0][0]
        c_trials = sorted(((d, c) for d, c in trials if not c.generic and d <= best_g + NEAR_TIE),
                          key=lambda x: x[0])
        near = [(d, c) for d, c in g_trials if d - best_g < NEAR_TIE]
        near.sort(key=lambda x: (x[1].complexity, x[0]))
        accepted: tuple[float, Candidate, Any] | None = None
        first_fail: dict[str, Any] | None = None
        # the near ties first (simplest first), then the next best terms, a few at most: a term the
        # guards reject (e.g. one that needs a negative variance elsewhere) leaves room for another
        rest = [(d, c) for d, c in g_trials if (d, c) not in near][:MAX_TRIES]
        for d, c in [*c_trials, *near, *rest]:
            limit = generic_threshold(len(gen)) if c.generic else BIC_THRESHOLD
            if d >= limit:
                first_fail = first_fail or {"term": c.name, "delta_bic": float(d),
                                            "why": f"delta BIC {d:.1f} >= {limit:.1f}"}
                continue
            after, p, b, se, why = _guards(t, selected, c.name, base_rmse)
            if not why:
                neg = negative_variances(t, [*selected, c.name], by_name, present)
                if neg:
                    why = ("the joint fit takes the variance of " + ", ".join(neg) + " below zero "
                           "(nearly collinear noises trading off): not a noise the simulator can render")
            if why:
                first_fail = first_fail or {"term": c.name, "delta_bic": float(d), "wald_p": float(p),
                                            "heldout_rmse_after": after, "heldout_rmse_before": base_rmse,
                                            "why": why}
                continue
            accepted = (d, c, (after, p, b, se))
            break
        if accepted is None:
            if first_fail is not None:
                rejected.append({**first_fail, "table": t.name, "quantity": _quantity(t)})
            break
        if accepted[1].generic:
            accepted = _proxy_check(t, selected, accepted, trials, base_rmse, by_name, present, proxy_notes)
        d, c, (after, p, b, se) = accepted
        step += 1
        selected.append(c.name)
        ties = [{"term": o.name, "delta_bic": float(od), "bic_gap": float(od - d)}
                for od, o in [*c_trials, *near] if o.name != c.name and abs(od - d) < NEAR_TIE]
        if c.generic:
            terms.append(DiscoveredTerm(c, t.name, {}, {}, float(d), *_rmse_pair(t, base_rmse, after),
                                        float(p), step, ties))
        else:   # a catalogue effect passes: selected as such, the catalogue keeps priority
            fit = _fit_record(c, present, float(d), base_rmse, after, p, b, se, real)
            fit.selected, fit.step, fit.near_ties = True, step, [
                {"effect": x["term"], "delta_bic": x["delta_bic"], "bic_gap": x["bic_gap"]} for x in ties]
            fits[c.name] = fit
    dropped: list[dict[str, Any]] = []
    for name in (start if terms else []):
        full = bic(t, selected)
        without = [n for n in selected if n != name]
        p, _, _ = wald_p(t, selected, name)
        cost = bic(t, without) - full
        if p >= WALD_P or cost < -BIC_THRESHOLD:
            # dropped only where held-out standpoints do not need it either
            h_with, h_without = heldout_rmse(t, selected), heldout_rmse(t, without)
            if not h_without <= h_with:
                continue
            a, b = _rmse_pair(t, h_with, h_without)
            selected = without
            fits[name].selected = False
            dropped.append({"effect": name, "table": t.name, "wald_p": float(p),
                            "bic_cost_of_dropping": float(cost),
                            "heldout_rmse_with_m": a, "heldout_rmse_without_m": b,
                            "why": f"the discovered terms explain what it had absorbed (beside them Wald p "
                                   f"{p:.2g}, dropping it costs {cost:.1f} in BIC, held-out RMSE "
                                   f"{_mm(t, a)} with it, {_mm(t, b)} without)"})
    if selected != start:
        _final(t, selected, by_name, terms, fits, present, real)
    return TableResult(selected, terms, fits, dropped, rejected + proxy_notes, bic(t, selected))


def _proxy_check(t: Table, selected: list[str], accepted: tuple[float, Candidate, Any],
                 trials: list[tuple[float, Candidate]], base_rmse: float, by_name: dict[str, Candidate],
                 present: dict[str, dict[str, float]], notes: list[dict[str, Any]]
                 ) -> tuple[float, Candidate, Any]:
    """A generic term along a proxy axis (time within a standpoint ~ the frame's position, disparity
    ~ distance) against the catalogue effects that pass the guards on their own: one that predicts
    held-out standpoints as well is taken instead (the same physics, with a name); said in `notes`."""
    d, c, (after, *_rest) = accepted
    assert c.spec is not None
    proxies = [a for a in c.spec.axes if a in PROXIES]
    if not proxies:
        return accepted
    named = sorted(((x, y) for x, y in trials if not y.generic and x < BIC_THRESHOLD), key=lambda z: z[0])
    for dc, cc in named:
        a2, p2, b2, se2, why = _guards(t, selected, cc.name, base_rmse)
        if why or negative_variances(t, [*selected, cc.name], by_name, present):
            continue
        if a2 <= after:
            shown = _rmse_pair(t, a2, after)
            notes.append({"term": c.name, "table": t.name, "quantity": _quantity(t), "delta_bic": float(d),
                          "why": f"along {', '.join(proxies)} (a proxy of "
                                 f"{', '.join(PROXIES[x] for x in proxies)}): {cc.name} predicts held-out "
                                 f"standpoints as well (RMSE {_mm(t, shown[0])} against "
                                 f"{_mm(t, shown[1])}) and is "
                                 "taken instead"})
            return dc, cc, (a2, p2, b2, se2)
    return accepted


def _quantity(t: Table) -> str:
    return "bias" if t.kind == "bias" else "noise"


def _rmse_pair(t: Table, before: float, after: float) -> tuple[float, float]:
    if t.kind == "variance":     # a variance misfit is shown as a standard deviation (m)
        return float(np.sqrt(before)), float(np.sqrt(after))
    return float(before), float(after)


def _final(t: Table, selected: list[str], by_name: dict[str, Candidate], terms: list[DiscoveredTerm],
           fits: dict[str, CandidateFit], present: dict[str, dict[str, float]], real: Samples) -> None:
    """Coefficients of everything selected on this table from one joint fit."""
    fit = gls(t, selected)
    # standard errors as the Wald test sees them: cluster-robust on the plain tables
    full_cov = cluster_cov(t, selected, fit.beta)[0] if t.Z is None else fit.cov
    start = 0
    by_term = {x.candidate.name: x for x in terms}
    for name in selected:
        k = t.X[name].shape[1]
        b = fit.beta[start:start + k]
        cov = full_cov[start:start + k, start:start + k]
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        c = by_name[name]
        if name in by_term:
            x = by_term[name]
            x.coef = {p: float(v) for p, v in zip(c.params, b, strict=True)}
            x.stderr = {p: float(e) for p, e in zip(c.params, se, strict=True)}
            x.cov = [[float(v) for v in row] for row in cov]
        elif name in fits:
            fits[name].coef = [float(v) for v in b]
            fits[name].params, fits[name].stderr = _params(c, present, b, se, real)
        start += k


def discover(attr: Attribution, catalogue: Sequence[Candidate], lib: Sequence[Candidate],
             present: dict[str, dict[str, float]], real: Samples) -> Discovery:
    """Phase 2 on every table; updates `attr` (catalogue effects added or dropped) in place."""
    fits = {f.effect: f for f in attr.candidates}
    out = Discovery(library_size=len(lib))
    for name, t in attr.tables.items():
        if len(t) == 0:
            continue
        kind = "bias" if name == "bias" else "variance"
        where = "frame" if name == "frame" else "tiles"
        cat = [c for c in catalogue if c.kind == kind and c.table == where]
        gen = [c for c in lib if c.kind == kind and c.table == where]
        sub = {k: f for k, f in fits.items() if f.kind == kind and k in t.X}
        terms, dropped, rejected, kept = select_table(t, cat, gen, sub, present, real)
        fits.update(sub)
        out.terms += terms
        out.dropped += dropped
        out.kept += kept
        out.rejected += rejected
    attr.candidates = rank(list(fits.values()))
    out.terms.sort(key=lambda x: (0 if x.quantity == "bias" else 1, x.step))
    return out


def best_term(t: Table, lib: Sequence[Candidate], selected: Sequence[str], axes: set[str],
              catalogue: Sequence[Candidate] = (), present: dict[str, dict[str, float]] | None = None
              ) -> dict[str, Any] | None:
    """The library term along `axes` that would explain most of what remains, and why it is not in
    the model (for regions still significant after the refit)."""
    pool = [c for c in lib if c.name in t.X and c.spec is not None and set(c.spec.axes) & axes
            and c.name not in selected and _usable(t, c.name) and _identifiable(t, [*selected, c.name])]
    if not pool:
        return None
    base = bic(t, list(selected))
    scored = sorted(((bic(t, [*selected, c.name]) - base, c) for c in pool), key=lambda x: x[0])
    d, c = scored[0]
    base_rmse = heldout_rmse(t, list(selected))
    after, p, _, _, why = _guards(t, list(selected), c.name, base_rmse)
    neg = negative_variances(t, [*selected, c.name], {x.name: x for x in [*lib, *catalogue]}, present or {})
    if not why and neg:
        why = ("the joint fit takes the variance of " + ", ".join(neg) + " below zero (nearly collinear "
               "noises trading off)")
    limit = generic_threshold(len([x for x in lib if x.name in t.X]))
    if d >= limit:
        why = (f"delta BIC {d:.1f} >= {limit:.1f} (-10 plus the price of searching the library): "
               "not strong enough")
    before_m, after_m = _rmse_pair(t, base_rmse, after)
    return {"term": c.spec.name if c.spec else c.name, "expression": c.meaning, "delta_bic": float(d),
            "wald_p": float(p), "heldout_rmse_before_m": before_m, "heldout_rmse_after_m": after_m,
            "why_not_selected": why or "passes the guards on this table; not reached (the selection "
                                       "stopped at a term limit or an earlier term took its place)"}


def remaining(regions: Sequence[dict[str, Any]], attr: Attribution, lib: Sequence[Candidate],
              discovery: Discovery | None, family_axes: dict[str, tuple[str, ...]],
              catalogue: Sequence[Candidate] = (), present: dict[str, dict[str, float]] | None = None,
              correlation: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """For every region still significant after the refit: the term that would explain it best and
    why it was not selected (a guard it fails), or why no term can."""
    chosen: dict[str, list[str]] = {}
    for f in attr.selected:
        for name, t in attr.tables.items():
            if f.effect in t.X:
                chosen.setdefault(name, []).append(f.effect)
    for d in (discovery.terms if discovery is not None else []):
        chosen.setdefault(d.table, []).append(d.candidate.name)
    out: list[dict[str, Any]] = []
    cache: dict[tuple[str, tuple[str, ...]], dict[str, Any] | None] = {}
    for r in regions:
        axes = tuple(family_axes.get(r["family"], ()))
        table = "bias" if r["kind"] == "bias" else ("frame" if r["family"] == "frame_common" else "variance")
        entry = {"family": r["family"], "kind": r["kind"], "label": r["label"], "axes": list(axes)}
        found = attr.tables.get(table)
        if not axes or found is None or not len(found):
            entry["term"] = None
            entry["why_not_selected"] = ("a single standpoint differs: a static error of its own (pose of "
                                         "the reference, frozen pattern) that no term shared by "
                                         "standpoints describes" if r["family"] == "standpoint"
                                         else "no fit table for this quantity")
            out.append(entry)
            continue
        if r["family"] == "frame_common" and r.get("k2_m2_per_px2"):
            entry.update(_frame_common_remedy(r, [*chosen.get("frame", []), *(present or {})]))
            out.append(entry)
            continue
        if r["family"].startswith("periodic") or r["family"] == "static":
            entry.update(_fine_remedy(r))
            out.append(entry)
            continue
        if r["family"].startswith("correlation") and correlation:
            real, sim = correlation["real"], correlation["sim"]
            entry["term"] = "window_noise"
            entry["why_not_selected"] = (
                f"the real noise is more window-correlated than the model's: correlated fraction "
                f"{real['correlated_fraction']:.2f} over {real['window_px']:.3g} px against "
                f"{sim['correlated_fraction']:.2f} over {sim['window_px']:.3g} px re-simulated; the model's "
                "white noises (disparity_noise and any white term) keep neighbours independent, and a "
                "window_noise that took their variance would need them below zero")
            out.append(entry)
            continue
        t = found
        key = (table, axes)
        if key not in cache:
            kind = "bias" if table == "bias" else "variance"
            where = "frame" if table == "frame" else "tiles"
            pool = [c for c in lib if c.kind == kind and c.table == where]
            cache[key] = best_term(t, pool, chosen.get(table, []), set(axes), catalogue, present)
        best = cache[key]
        if best is None:
            entry["term"] = None
            entry["why_not_selected"] = "no library term along these axes"
        else:
            entry.update(best)
        out.append(entry)
    return out


def _frame_common_remedy(r: dict[str, Any], held: Sequence[str]) -> dict[str, Any]:
    """The frame-common variance the re-simulation lacks (or has too much of), in px^2: the smallest
    term that removes the region is a frame-common disparity noise of that size on top of what the
    model holds."""
    extra = float(r["diff"]) / float(r["k2_m2_per_px2"])
    se = float(r["se"]) / float(r["k2_m2_per_px2"])
    term = "term_noise_frame_common"
    had = [h for h in held if h == term or h.endswith("frame_common")]
    why = (f"the model's {had[0]} is fitted {'short' if extra > 0 else 'over'} of the real frame-common "
           f"variance by {extra:.3g} +- {se:.3g} px^2 in the re-simulation" if had else
           "no frame-common term in the model")
    return {"term": term, "why_not_selected": why,
            "expression": f"var_d += {extra:.3g} px^2 (one draw per frame, shared by all its pixels)"}


def _fine_remedy(r: dict[str, Any]) -> dict[str, Any]:
    """The smallest term that would remove a periodic or static region, and why it is not in the model."""
    if r["family"].startswith("periodic"):
        axis = r["family"].split("_")[1]
        return {"term": "periodic_bias",
                "expression": (f"delta = {r.get('amplitude_px', float('nan')):.3g} px sin(2 pi {axis} / "
                               f"{r.get('period_px', float('nan')):.3g} px + {r.get('phase_rad', 0.0):.2f})"),
                "why_not_selected": "a ripple the refit did not remove: its amplitude or period differs "
                                    "in the re-simulation (the written term is fitted on all standpoints)"}
    length = r.get("correlation_px", float("nan"))
    return {"term": "static_pattern",
            "expression": (f"a static field of {np.sqrt(max(r.get('real_px2', 0.0), 0.0)):.3g} px RMS"
                           + (f" over {length:.3g} px" if np.isfinite(length) else "")),
            "why_not_selected": ("a pattern repeating in every frame of this standpoint beyond the model's "
                                 "static_pattern; one fixed to the unit is calibrated from the pooled test, "
                                 "one of a single standpoint (its texture, its pose) is no term the "
                                 "standpoints share")}

