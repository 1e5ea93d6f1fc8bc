"""Explain's result folder: explain.json, model.toml, report.md with figures, result.json."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from depthstation.core.results import write_json, write_result_info
from depthstation.evaluate.explain.attribute import NEAR_TIE
from depthstation.evaluate.explain.figures import residual_grid_figure
from depthstation.evaluate.explain.locate import residual_grid

if TYPE_CHECKING:
    from depthstation.evaluate.explain.run import Explanation


def explain_dict(ex: Explanation) -> dict[str, Any]:
    """The content of explain.json (contract of issue 7)."""
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
        "candidates": [{"rank": i + 1, **c.to_dict()} for i, c in enumerate(ex.attribution.candidates)],
        "selected": [c.effect for c in ex.attribution.selected],
        "missing_physics": [c.effect for c in ex.attribution.selected if c.role == "missing_physics"],
        "calibrated": calibrated,
        "near_ties": [{"selected": c.effect, **t} for c in ex.attribution.selected for t in c.near_ties],
        "standpoints": list(ex.real.samples.names),
        "samples": {"real": len(ex.real.samples), "sim": len(ex.sim.samples)},
        "fit_rows": {"bias": ex.attribution.bias_rows, "variance": ex.attribution.variance_rows},
        "tests": [t.to_dict() for t in ex.before.tests],
    }


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
    for fam, xlabel, fname in (("column", "image column u (px)", "residual_columns.png"),
                               ("albedo", "square colour", "residual_albedo.png"),
                               ("time", "time since session start (s)", "residual_time.png"),
                               ("temperature", "device temperature (degC)", "residual_temperature.png")):
        if not ex.before.family(fam):
            continue
        fig, ax = plt.subplots(figsize=(6, 4))
        for label, loc in sides:
            ts = loc.family(fam)
            x = np.arange(len(ts)) if fam == "albedo" else np.array(
                [(t.coords[f"{key}_min"] + t.coords[f"{key}_max"]) / 2 for t in ts
                 for key in [next(k[:-4] for k in t.coords if k.endswith("_min"))]])
            ax.errorbar(x, [t.diff * 1000 for t in ts], yerr=[2 * t.se * 1000 for t in ts], marker="o",
                        capsize=3, label=label)
            if fam == "albedo":
                ax.set_xticks(x, [t.label for t in ts])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean error real - sim (mm), bars 2 SE")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / fname, dpi=100)
        plt.close(fig)
        names.append(fname)
    return names


def report_md(ex: Explanation, data: dict[str, Any], figs: list[str]) -> str:
    """A human summary: what differs, what explains it, what changed in the model."""
    m = data["mismatch"]
    lines = ["# Explain: simulation versus real", ""]
    if m["significant"]:
        lines.append(f"**The simulation differs from the real data** ({len(m['regions'])} regions, "
                     f"standpoints: {', '.join(m['standpoints']) or 'none alone'}; Holm-corrected, "
                     f"alpha {m['alpha']}).")
    else:
        lines.append("No significant difference between simulation and real data (Holm, alpha "
                     f"{m['alpha']}).")
    lines += ["", "## Where it differs", "", "| family | quantity | group | real - sim | SE | p (Holm) |",
              "|---|---|---|---|---|---|"]
    for r in m["regions"][:20]:
        unit, scale = ("mm", 1e3) if r["kind"] == "bias" else ("mm^2", 1e6)
        lines.append(f"| {r['family']} | {r['kind']} | {r['label']} | {r['diff'] * scale:.3g} {unit} | "
                     f"{r['se'] * scale:.2g} | {r['p_adj']:.2g} |")
    lines += ["", "## Candidates (ranked)", "",
              "| rank | effect | role | selected | parameters | delta BIC | held-out RMSE before -> after |",
              "|---|---|---|---|---|---|---|"]
    for c in data["candidates"]:
        ps = ", ".join(f"{k} = {v['value']:.4g} {v['unit']}" for k, v in c["params"].items())
        lines.append(f"| {c['rank']} | {c['effect']} | {c['role'].replace('_', ' ')} | "
                     f"{'yes' if c['selected'] else 'no'} | {ps} | {c['delta_bic']:.1f} | "
                     f"{c['heldout_rmse_before_m'] * 1e3:.3g} -> {c['heldout_rmse_after_m'] * 1e3:.3g} mm |")
    lines += ["", "## Verdict", ""]
    mp = data["missing_physics"]
    lines.append(f"- Missing physics: {', '.join(mp) if mp else 'none'}.")
    cal = data["calibrated"]
    lines.append("- Calibration (parameters the model already had): " + (
        "; ".join(f"{c['effect']}: " + ", ".join(f"{k} {v['old']} -> {v['new']:.4g} {v['unit']}"
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
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figs]
    lines += ["", "Notes: errors are z-depth (measured - reference, + = too far); standard errors come from "
              "per-frame means within standpoints plus the reference-pose error the simulation measures; "
              "selection needs delta BIC < -10, a lower held-out RMSE (leave one standpoint out) and a "
              "cluster-robust Wald p < 0.001."]
    return "\n".join(lines) + "\n"


def write_outputs(ex: Explanation, out: Path, inputs: list[str], parameters: dict[str, Any]
                  ) -> dict[str, Any]:

    out.mkdir(parents=True, exist_ok=True)
    data = explain_dict(ex)
    write_json(out / "explain.json", data)
    (out / "model.toml").write_text(ex.new_model.to_toml())
    figs = figures(ex, out)
    (out / "report.md").write_text(report_md(ex, data, figs))
    write_result_info(out, "explain", inputs, parameters,
                      extra={"selected": data["selected"], "significant": data["mismatch"]["significant"]})
    return data
