"""Explain's result folder: explain.json, model.toml, report.md with figures, result.json."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from depthstation.core.results import write_json, write_result_info
from depthstation.evaluate.explain.attribute import NEAR_TIE
from depthstation.evaluate.explain.coverage import fit_domain
from depthstation.evaluate.explain.figures import (
    _frame_binned,
    residual_grid_figure,
    term_field_figure,
    term_residual_figure,
)
from depthstation.evaluate.explain.locate import ALBEDO_GROUPS, residual_grid
from depthstation.evaluate.explain.samples import FloatArray, Samples, unpaired_standpoints
from depthstation.evaluate.explain.samples import session_clock as samples_session_clock
from depthstation.evaluate.explain.structure import decompose, frame_common
from depthstation.simulate.effects import PixelContext
from depthstation.simulate.effects.generic import AXIS_INFO, axis_value

if TYPE_CHECKING:
    from depthstation.evaluate.explain.discover import DiscoveredTerm
    from depthstation.evaluate.explain.run import Explanation


def reference_lookalikes(selected: list[Any]) -> list[dict[str, Any]]:
    """Selected effects that an error of the checkerboard's reference gives too: the board's pose is
    the truth there, so a depth scale s is also a print s larger than the board file says, or a
    colour focal length s short (docs/checkerboard-study.md, `absorbed`). Said, so that nobody
    writes a print error into the camera's model."""
    out = []
    for c in selected:
        s = c.params.get("scale_error") if c.effect == "depth_scale" else None
        if s is None or not np.isfinite(s) or s == 0:
            continue
        pct = f"{100 * abs(s):.2f} %"
        board, focal = ("larger", "short") if s > 0 else ("smaller", "long")
        out.append({"effect": c.effect, "scale_error": float(s),
                    "also": f"a board printed {pct} {board} than its file's square length, or a colour "
                            f"focal length {pct} too {focal}, gives the same: measure the printed squares "
                            "before applying it to the camera"})
    return out


MAX_REGIONS = 20
"""Regions listed in report.md's table (all of them are in explain.json)."""

NO_TIME_STAMPS = ("the inputs carry no time stamps of their own (a PNG folder's frames are numbered at "
                  "its nominal fps, every standpoint from 0): nothing is shown along time")


def session_clock(clocks: dict[str, Any]) -> bool:
    """Whether the frames' time stamps (FrameClocks by standpoint) are a clock of the session
    (`samples.session_clock`, decided where the samples are built)."""
    return samples_session_clock([c.timestamp_ns for c in clocks.values()])


def in_domain(candidate: dict[str, Any]) -> dict[str, Any]:
    """A candidate of explain.json with its noise widths (sigmas, windows: >= 0) in their domain.

    A variance candidate's fit gives sigma^2 (or its change); where that is negative (the real
    noise below the model's along this signature) its square root was reported signed, as a
    "-0.10 px" sigma. Such a value is clamped at 0 and the fit kept beside it, said in `domain`.
    """
    if candidate.get("kind") != "variance":
        return candidate
    params = {}
    for name, p in candidate["params"].items():
        v = p.get("value")
        if v is not None and np.isfinite(v) and v < 0:
            p = {**p, "value": 0.0, "fitted_signed": float(v),
                 "domain": f"clamped at 0: a width is >= 0, and the fitted variance is negative "
                           f"(-{v * v:.3g}{_unit(p.get('unit'))}{'^2' if _unit(p.get('unit')) else ''}: "
                           "the real noise along this signature is below what the model has)"}
        params[name] = p
    return {**candidate, "params": params}


def _unit(unit: str | None) -> str:
    """A unit after a number: none for a ratio (unit "1" or empty)."""
    return "" if unit in (None, "", "1") else f" {unit}"


def explain_dict(ex: Explanation) -> dict[str, Any]:
    """The content of explain.json (its keys are the users' contract: docs/results.md, docs/explain.md)."""
    before = ex.before.summary()
    after = ex.after.summary() if ex.after is not None else None
    present = {e.name: dict(e.params) for e in ex.model.effects}
    calibrated = []
    for c in ex.attribution.selected:
        if c.role == "calibration":
            calibrated.append({"effect": c.effect, "params": {
                k: {"old": present.get(c.effect, {}).get(k), "new": v, "unit": c.units.get(k, "")}
                for k, v in c.params.items()}})
    return {
        "mismatch": before,
        "mismatch_after": after,
        "candidates": [in_domain({"rank": i + 1, **c.to_dict()})
                       for i, c in enumerate(ex.attribution.candidates)],
        "selected": [c.effect for c in ex.attribution.selected],
        "missing_physics": [c.effect for c in ex.attribution.selected if c.role == "missing_physics"],
        "calibrated": calibrated,
        "near_ties": [{"selected": c.effect, **t} for c in ex.attribution.selected for t in c.near_ties],
        "reference_lookalikes": reference_lookalikes(ex.attribution.selected),
        "valid_depth": [t.to_dict() for t in ex.valid_depth],
        "fit_domain": fit_domain(ex.real.samples),
        "standpoints": list(ex.real.samples.names),
        "standpoints_left_out": _left_out(ex),
        "samples": {"real": len(ex.real.samples), "sim": len(ex.sim.samples)},
        "fit_rows": {"bias": ex.attribution.bias_rows, "variance": ex.attribution.variance_rows,
                     "frame": len(ex.attribution.tables["frame"]) if "frame" in ex.attribution.tables else 0},
        "discovered": [t.to_dict() for t in ex.discovery.terms] if ex.discovery is not None else [],
        "discovery": ex.discovery.summary() if ex.discovery is not None else None,
        "remaining_after": ex.remaining,
        "tests": [t.to_dict() for t in ex.before.tests],
        "time_stamps": ex.real.samples.time_stamps,
        "fine_terms": ex.fine_terms,
        "pose_spread": ex.pose_spread,
        "pose_spread_after": ex.pose_spread_after,
    }


def _left_out(ex: Explanation) -> dict[str, list[str]]:
    """Standpoints only one side has, per comparison: no test covers them (names, never indices)."""
    sides = [("simulation", ex.sim)] + ([("re-simulation", ex.resim)] if ex.resim is not None else [])
    out: dict[str, list[str]] = {}
    for label, side in sides:
        only_real, only_sim = unpaired_standpoints(ex.real.samples, side.samples)
        out[f"real_not_in_{label.replace('-', '')}"] = only_real
        out[f"{label.replace('-', '')}_not_in_real"] = only_sim
    return out


def figures(ex: Explanation, out: Path) -> list[str]:
    """Before/after pictures of real minus sim: grid, columns, black/white, time/temperature."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    sides = [("before", ex.before)] + ([("after", ex.after)] if ex.after is not None else [])
    panels = [(label, g[0], g[1], g[2]) for label, loc in sides
              if (g := residual_grid(loc)) is not None]
    residual_grid_figure(out / "residual_grid.png", panels)
    names.append("residual_grid.png")
    clock = ex.real.samples.time_stamps
    for fam, xlabel, fname, title in (
            ("column", "image column u (px)", "residual_columns.png", "mean error along the image columns"),
            ("albedo", "square colour", "residual_albedo.png", "mean error on black and white squares"),
            ("time", "time since session start (s)", "residual_time.png",
             "mean error over the session's time"),
            ("temperature", "device temperature (degC)", "residual_temperature.png",
             "mean error over the device temperature")):
        if not ex.before.family(fam) or (fam == "time" and not clock):  # no time axis made up
            continue
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.set_title(f"{title}: real - sim", fontsize=10)
        for label, loc in sides:
            ts = loc.family(fam)
            x = np.array([ALBEDO_GROUPS.index(t.label) for t in ts]) if fam == "albedo" else np.array(
                [(t.coords[f"{key}_min"] + t.coords[f"{key}_max"]) / 2 for t in ts
                 for key in [next(k[:-4] for k in t.coords if k.endswith("_min"))]])
            ax.errorbar(x, [t.diff * 1000 for t in ts], yerr=[2 * t.se * 1000 for t in ts], marker="o",
                        capsize=3, label=label)
            if fam == "albedo":
                ax.set_xticks(range(len(ALBEDO_GROUPS)), ALBEDO_GROUPS)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean error real - sim (mm), bars 2 SE")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / fname, dpi=100)
        plt.close(fig)
        names.append(fname)
    return names


def _disparity_residual(s: Samples, quantity: str) -> FloatArray:
    """Per sample, the residual in the term's own domain: disparity error -e/K (px, + = disparity too
    large) for a bias, squared within-frame deviation / K^2 (px^2) for a noise."""
    if quantity == "bias":
        return np.asarray(-s.err_m / s.k_m_per_px)
    return np.asarray(decompose(s).dev2 / s.k_m_per_px ** 2)


def _term_figure(term: DiscoveredTerm, sides: list[tuple[str, Samples, Samples]], path: Path) -> Path:
    """One figure of a discovered term: the residual along its axes, before and after, with the fit."""
    spec = term.candidate.spec
    assert spec is not None
    fixed = term.candidate.fixed
    coef = np.array([term.coef[c] for c in spec.coefficients])
    cov = (np.asarray(term.cov) if term.cov
           else np.diag([term.stderr.get(c, 0.0) ** 2 for c in spec.coefficients]))
    unit = spec.unit
    what = "disparity error" if spec.quantity == "bias" else "within-frame disparity variance"
    title = f"{spec.name}: {spec.expression(term.coef)}"
    if spec.basis == "common":
        xs, rows = [], []
        for label, real, sim in sides:
            fr, fs = frame_common(real, decompose(real)), frame_common(sim, decompose(sim))
            idx = {sim.names[int(g)]: i for i, g in enumerate(fs.standpoint)}
            pts = [(a, fr.excess_px2[a] - fs.excess_px2[idx[real.names[int(g)]]],
                    float(np.hypot(fr.se_px2()[a], fs.se_px2()[idx[real.names[int(g)]]])))
                   for a, g in enumerate(fr.standpoint) if real.names[int(g)] in idx]
            xs = [p[0] for p in pts]
            rows.append((label, np.array(xs, dtype=float), np.array([p[1] for p in pts]),
                         np.array([p[2] for p in pts]) / 2))
        xg = np.linspace(-0.5, max(len(xs) - 0.5, 0.5), 50)
        band = 2 * np.sqrt(max(float(cov[0, 0]), 0.0))
        return term_residual_figure(path, title, "standpoint", f"frame-common variance real - sim ({unit})",
                                    rows, (xg, np.full_like(xg, coef[0]), np.full_like(xg, band)))
    if spec.basis.startswith("field"):
        xe = np.linspace(-0.6, 0.6, 13)
        ye = np.linspace(-0.35, 0.35, 8)
        panels = []
        for label, real, sim in sides:
            maps = []
            for s in (real, sim):
                ctx = PixelContext(**s.context())
                x, y = axis_value(ctx, "u", fixed), axis_value(ctx, "v", fixed)
                val = _disparity_residual(s, spec.quantity)
                key = (np.digitize(x, xe) - 1) * 100 + (np.digitize(y, ye) - 1)
                m = np.full((len(xe) - 1, len(ye) - 1), np.nan)
                ok = (np.digitize(x, xe) >= 1) & (np.digitize(x, xe) < len(xe)) & (np.digitize(y, ye) >= 1) \
                    & (np.digitize(y, ye) < len(ye)) & np.isfinite(val)
                if ok.any():
                    uk, inv, cnt = np.unique(key[ok], return_inverse=True, return_counts=True)
                    mean = np.bincount(inv.ravel(), weights=val[ok]) / cnt
                    for kk, mm, c in zip(uk, mean, cnt, strict=True):
                        if c >= 30:
                            m[kk // 100, kk % 100] = mm
                maps.append(m)
            panels.append((f"residual {label} ({unit})", maps[0] - maps[1]))
        xc, yc = (xe[:-1] + xe[1:]) / 2, (ye[:-1] + ye[1:]) / 2
        gx, gy = np.meshgrid(xc, yc, indexing="ij")
        cols = [np.prod([gx if ch == "x" else gy for ch in c[2:]], axis=0) for c in spec.coefficients]
        phi = np.stack(cols, axis=-1)
        seen = np.isfinite(panels[0][1])    # the field only where the boards were
        fitted = np.where(seen, phi @ coef, np.nan)
        band = np.where(seen, 2 * np.sqrt(np.clip(np.einsum("...i,ij,...j->...", phi, cov, phi), 0, None)),
                        np.nan)
        panels.insert(1, (f"fitted term ({unit})", fitted))
        panels.append((f"2 SE of the fitted term ({unit})", band))
        return term_field_figure(path, title, unit, xe, ye, panels)
    # one variable: a polynomial's axis, a product of two, the edge distance
    def variable(s: Samples) -> FloatArray:
        ctx = PixelContext(**s.context())
        if spec.basis == "product":
            return np.asarray(axis_value(ctx, spec.axes[0], fixed) * axis_value(ctx, spec.axes[1], fixed))
        return np.asarray(axis_value(ctx, spec.axes[0], fixed))

    first = variable(sides[0][1])
    fin = first[np.isfinite(first)]
    if spec.basis == "exp":
        fin = fin[fin < 40]
    lo, hi = (float(np.min(fin)), float(np.max(fin))) if fin.size else (0.0, 1.0)
    edges = np.linspace(lo, hi + 1e-9 * max(1.0, abs(hi)), 11)
    rows = []
    for label, real, sim in sides:
        mr, sr = _frame_binned(variable(real), _disparity_residual(real, spec.quantity), real.frame_key,
                               edges)
        ms, ss = _frame_binned(variable(sim), _disparity_residual(sim, spec.quantity), sim.frame_key, edges)
        rows.append((label, (edges[:-1] + edges[1:]) / 2, mr - ms, np.hypot(sr, ss)))
    xg = np.linspace(lo, hi, 100)
    if spec.basis.startswith("poly"):
        phi = np.stack([xg ** k for k in spec.powers], axis=1)
    elif spec.basis == "exp":
        phi = np.exp(-np.maximum(xg, 0) / fixed.get("length_px", 5.0))[:, None]
    else:
        phi = xg[:, None]
    band = 2 * np.sqrt(np.clip(np.einsum("ni,ij,nj->n", phi, cov, phi), 0, None))
    sym = ("*".join(AXIS_INFO[a][0] for a in spec.axes) if spec.basis == "product"
           else AXIS_INFO[spec.axes[0]][0])
    units = "*".join(AXIS_INFO[a][1] for a in spec.axes if AXIS_INFO[a][1] != "1")
    return term_residual_figure(path, title, f"{sym} ({units})" if units else sym,
                                f"{what} real - sim{f' ({unit})' if _unit(unit) else ''}", rows,
                                (xg, phi @ coef, band))


def discovered_figures(ex: Explanation, out: Path) -> list[str]:
    """One figure per discovered term (residual along its axes before / after with the fit)."""
    if ex.discovery is None or not ex.discovery.terms:
        return []
    sides = [("before (real - sim)", ex.real.samples, ex.sim.samples)]
    if ex.resim is not None:
        sides.append(("after (real - re-simulation)", ex.real.samples, ex.resim.samples))
    names = []
    for k, term in enumerate(ex.discovery.terms):
        name = f"discovered_{k + 1}_{term.effect}.png"
        _term_figure(term, sides, out / name)
        names.append(name)
    return names


def report_md(ex: Explanation, data: dict[str, Any], figs: list[str]) -> str:
    """A human summary: what differs, what explains it, what changed in the model."""
    m = data["mismatch"]
    regions = m["regions"]
    timeless = [r for r in regions if r["family"] == "time"] if not data.get("time_stamps", True) else []
    corr = [r for r in regions if r["family"].startswith("correlation_")]
    plain = [r for r in regions if r not in corr and r not in timeless]
    lines = ["# Explain: simulation versus real", ""]
    if m["significant"]:
        kinds = [f"{len(plain)} of bias or noise"] + ([f"{len(corr)} of noise correlation"] if corr else []) \
            + ([f"{len(timeless)} along frame time without time stamps"] if timeless else [])
        lines.append(f"**The simulation differs from the real data** ({len(regions)} regions: "
                     f"{', '.join(kinds)}; standpoints: {', '.join(m['standpoints']) or 'none alone'}; "
                     f"Holm-corrected, alpha {m['alpha']}).")
        if m.get("heterogeneous_standpoints"):
            odd = ", ".join(m["heterogeneous_standpoints"])
            lines.append(f"Standpoint heterogeneity: {odd} (the real-minus-simulated plane is not of the "
                         "other standpoints' kind: depth off the board pose).")
    else:
        lines.append("No significant difference between simulation and real data (Holm, alpha "
                     f"{m['alpha']}).")
    said = {"real_not_in_simulation": "the simulation found no board in",
            "simulation_not_in_real": "the real frames show no board in",
            "real_not_in_resimulation": "the re-simulation found no board in",
            "resimulation_not_in_real": "the real frames show no board in"}
    left = [f"{said[k]} {', '.join(v)}" for k, v in data.get("standpoints_left_out", {}).items() if v]
    if left:
        lines += ["", f"**Not compared:** {'; '.join(dict.fromkeys(left))}. No test covers these "
                  "standpoints."]
    lines += _regions_md(plain, corr, timeless, data.get("time_stamps", True))
    lines += ["", "## Candidates (ranked)", "",
              "| rank | effect | role | selected | parameters | delta BIC | held-out RMSE before -> after |",
              "|---|---|---|---|---|---|---|"]
    for c in data["candidates"]:
        ps = ", ".join(_param_md(k, v) for k, v in c["params"].items())
        lines.append(f"| {c['rank']} | {c['effect']} | {c['role'].replace('_', ' ')} | "
                     f"{'yes' if c['selected'] else 'no'} | {ps} | {c['delta_bic']:.1f} | "
                     f"{c['heldout_rmse_before_m'] * 1e3:.3g} -> {c['heldout_rmse_after_m'] * 1e3:.3g} mm |")
    lines += ["", "## Verdict", ""]
    mp = data["missing_physics"]
    lines.append(f"- Missing physics: {', '.join(mp) if mp else 'none'}.")
    cal = data["calibrated"]
    lines.append("- Calibration (parameters the model already had): " + (
        "; ".join(f"{c['effect']}: " + ", ".join(f"{k} {v['old']} -> {v['new']:.4g}{_unit(v['unit'])}"
                                                 for k, v in c["params"].items()) for c in cal)
        if cal else "none") + ".")
    for t in data.get("near_ties", []):
        lines.append(f"- Near tie: {t['selected']} was preferred over {t['effect']} by only "
                     f"{t['bic_gap']:.1f} in BIC (< {NEAR_TIE:.0f}); the data hardly tell them apart "
                     "(more distances or inclinations would).")
    after = data.get("mismatch_after")
    if after is not None:
        state = (f"still significant in {len(after['regions'])} regions" if after["significant"]
                 else "no significant mismatch remains")
        lines.append(f"- After re-simulating with the new model (`model.toml`): {state}.")
    lines += _discovered_md(data, [f for f in figs if f.startswith("discovered_")])
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs if not f.startswith("discovered_")]
    lines += ["", "Notes: errors are z-depth (measured - reference, + = too far); standard errors come from "
              "per-frame means within standpoints plus the reference-pose error the simulation measures; "
              "selection needs delta BIC < -10, a lower held-out RMSE (leave one standpoint out) and a "
              "cluster-robust Wald p < 0.001."]
    return "\n".join(lines) + "\n"


def _regions_md(plain: list[dict[str, Any]], corr: list[dict[str, Any]], timeless: list[dict[str, Any]],
                clock: bool) -> list[str]:
    """The section "Where it differs": bias (mm) and noise (mm^2) regions, the smallest p first (at most
    MAX_REGIONS, said so), then the noise correlation of neighbouring pixels, which has no unit."""
    lines = ["", "## Where it differs", ""]
    if not clock:
        lines += [f"Time: {NO_TIME_STAMPS} (the frame family tests the frames' order)"
                  + (f"; {len(timeless)} region(s) along it are left out." if timeless else "."), ""]
    if plain:
        shown = plain[:MAX_REGIONS]
        lines += [f"Top {len(shown)} of {len(plain)} regions of bias or noise, smallest p first (all in "
                  "explain.json):" if len(shown) < len(plain) else
                  f"{len(plain)} region(s) of bias or noise, smallest p first:", "",
                  "| family | quantity | group | real - sim | SE | p (Holm) |", "|---|---|---|---|---|---|"]
        for r in shown:
            unit, scale = ("mm", 1e3) if r["kind"] == "bias" else ("mm^2", 1e6)
            lines.append(f"| {r['family']} | {r['kind']} | {r['label']} | {r['diff'] * scale:.3g} {unit} | "
                         f"{r['se'] * scale:.2g} {unit} | {r['p_adj']:.2g} |")
    if corr:
        lines += ["", f"{len(corr)} region(s) of noise correlation: the correlation coefficient of "
                  "neighbouring pixels' within-frame noise (no unit; 0 = independent pixels):", "",
                  "| family | group | real - sim | SE | p (Holm) |", "|---|---|---|---|---|"]
        for r in corr[:MAX_REGIONS]:
            lines.append(f"| {r['family']} | {r['label']} | {r['diff']:+.3f} | {r['se']:.2g} | "
                         f"{r['p_adj']:.2g} |")
    return lines


def _param_md(name: str, p: dict[str, Any]) -> str:
    """`name = value unit` of a candidate; a clamped width says what the fit gave."""
    text = f"{name} = {p['value']:.4g}{_unit(p.get('unit'))}"
    if "fitted_signed" in p:
        unit = _unit(p.get("unit"))
        text += f" (clamped at 0: the fitted variance is negative, -{p['fitted_signed'] ** 2:.3g}" \
                f"{unit}{'^2' if unit else ''})"
    return text


def _discovered_md(data: dict[str, Any], figs: list[str]) -> list[str]:
    """The section "Missing physics outside the catalogue" and what remains after the refit."""
    lines = ["", "## Missing physics outside the catalogue", ""]
    found = data.get("discovered") or []
    disc = data.get("discovery") or {}
    if not found:
        lines.append(f"Nothing found: no generic term of the library ({disc.get('library_size', 0)} terms) "
                     "passes the guards on what the catalogue leaves.")
    elif not data["mismatch"]["significant"]:
        lines += ["**Caution:** no region differs significantly (Holm), so what follows rests on the "
                  "pooled fit alone. Confirm it on another session before trusting it.", ""]
    for k, d in enumerate(found):
        det = disc["terms"][k] if k < len(disc.get("terms", [])) else {}
        coefs = ", ".join(f"{n} = {c['value']:.4g} +- {c['stderr']:.2g}{_unit(c['unit'])}"
                          for n, c in d["coefficients"].items())
        lines += [f"### {k + 1}. {d['quantity']} along {', '.join(d['axes'])}", "",
                  f"- Term (written into model.toml as `[effects.{det.get('term', '?')}]`): "
                  f"`{d['expression']}`",
                  f"- Coefficients: {coefs}.",
                  f"- Held-out RMSE {d['heldout_rmse_before_m'] * 1e3:.3g} -> "
                  f"{d['heldout_rmse_after_m'] * 1e3:.3g} mm; "
                  f"delta BIC {det.get('delta_bic', float('nan')):.1f}; "
                  f"Wald p {det.get('wald_p', float('nan')):.2g}.",
                  "- What makes this signature: " + " / ".join(d["interpretation"]) + "."]
        for t in det.get("near_ties", []):
            lines.append(f"- Near tie: {t['term']} (BIC gap {t['bic_gap']:.1f}); the data hardly tell "
                         "them apart.")
        if k < len(figs):
            lines += ["", f"![{figs[k]}]({figs[k]})", ""]
    for dr in disc.get("dropped_catalogue", []):
        lines.append(f"- {dr['effect']} was taken out again: {dr['why']}.")
    for ft in data.get("fine_terms") or []:
        shown = ", ".join(f"{k} = {v:.4g}" for k, v in ft["params"].items())
        lines.append(f"- Found by the {ft['family']} test and written into model.toml: "
                     f"`[effects.{ft['effect']}]` {shown}.")
    lines += _pose_spread_md(data)
    for kp in disc.get("kept_catalogue", []):
        lines.append(f"- {kp['effect']} is kept against generic terms of lower BIC: {kp['why']}.")
    rest = data.get("remaining_after")
    if rest:
        lines += ["", "## What remains after the refit", "",
                  "| family | quantity | group | term that would explain it | why it is not in the model |",
                  "|---|---|---|---|---|"]
        for r in rest:
            term = f"`{r['term']}`{_fit_note(r)}" if r.get("term") else "none"
            lines.append(f"| {r['family']} | {r['kind']} | {r['label']} | {term} | {r['why_not_selected']} |")
    return lines


def _pose_spread_md(data: dict[str, Any]) -> list[str]:
    """The colour camera's evidence: the reference distance's spread over frames, real against simulated."""
    ps, after = data.get("pose_spread") or {}, data.get("pose_spread_after") or {}
    if not ps.get("named"):
        return []
    fit = ps["fit"]
    out = [f"- The board pose scatters more than the model's colour camera gives (reference distance over "
           f"frames, {len(ps['significant'])} standpoint(s) differ, Holm): `{ps['named']}`, fitted as "
           f"`reference_pose_noise` corner_sigma_px = {fit['corner_sigma_px']:.3g} +- "
           f"{fit['corner_sigma_se_px']:.2g} (z^2 / (f L cos) growth, {fit['standpoints']} standpoints)."]
    if after:
        out.append(f"- After the refit {len(after.get('significant', []))} standpoint(s) still differ in the "
                   "reference spread (the re-simulated colour image plus the fitted term).")
    return out


def _fit_note(r: dict[str, Any]) -> str:
    """The fit figures of a remaining region's term where it has them (a term named from the noise's
    structure, window_noise, has no fit: no delta BIC, no Wald p)."""
    parts = [f"delta BIC {r['delta_bic']:.1f}" if r.get("delta_bic") is not None else "",
             f"Wald p {r['wald_p']:.2g}" if r.get("wald_p") is not None else ""]
    shown = ", ".join(x for x in parts if x)
    return f" ({shown})" if shown else ""


def write_outputs(ex: Explanation, out: Path, inputs: list[str], parameters: dict[str, Any]
                  ) -> dict[str, Any]:

    out.mkdir(parents=True, exist_ok=True)
    data = explain_dict(ex)
    write_json(out / "explain.json", data)
    (out / "model.toml").write_text(ex.new_model.to_toml())
    figs = figures(ex, out) + discovered_figures(ex, out)
    (out / "report.md").write_text(report_md(ex, data, figs))
    write_result_info(out, "explain", inputs, parameters, ex.real.device,
                      extra={"selected": data["selected"], "significant": data["mismatch"]["significant"]})
    return data
