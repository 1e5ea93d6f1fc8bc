"""`model show`'s picture and table: the model beside the measured field it was fitted to."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.heatmaps import POSITIVE, SIGNED, colormap, robust_limits
from depthstation.evaluate.errormodel.schema import TERM_FORMULAS, ErrorModel


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _boxes(ax: Any, rows: list[dict[str, Any]], key: str, cmap: Any, lim: tuple[float, float]) -> Any:
    """The measured rows as rectangles over distance x inclination, coloured by `key` (mm)."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    patches = [Rectangle((r["distance_lo_m"], r["inclination_lo_deg"]),
                         r["distance_hi_m"] - r["distance_lo_m"],
                         r["inclination_hi_deg"] - r["inclination_lo_deg"]) for r in rows]
    pc = PatchCollection(patches, cmap=cmap, edgecolor="none")
    pc.set_array(np.asarray([r[key] * 1e3 for r in rows], dtype=np.float64))
    pc.set_clim(*lim)
    ax.add_collection(pc)
    return pc


def model_figure(model: ErrorModel, path: Path) -> Path:
    """2 x 3 panels: measured mean, model bias, their difference; measured std, model sigma, theirs.
    Distance (m) on x, inclination (deg) on y, millimetres in colour; grey = outside the domain."""
    plt = _plt()
    rows = model.measured["rows"]
    z0, z1 = model.domain.z_range_m
    t0, t1 = model.domain.theta_range_deg
    zz = np.linspace(z0, z1, 200)
    tt = np.linspace(t0, t1, 120)
    zg, tg = np.meshgrid(zz, tt)
    b, s, _ = model.evaluate(zg, tg)
    zr = np.asarray([r["distance_m"] for r in rows])
    tr = np.asarray([r["inclination_deg"] for r in rows])
    bm, sm, _ = model.evaluate(zr, tr)
    resid_b = [dict(r, resid=r["mean_m"] - p) for r, p in zip(rows, bm, strict=True)]
    resid_s = [dict(r, resid=r["std_m"] - p) for r, p in zip(rows, sm, strict=True)]
    fig, ax = plt.subplots(2, 3, figsize=(16, 9), constrained_layout=True)
    signed, pos = colormap(SIGNED), colormap(POSITIVE)
    lim_b = robust_limits([r["mean_m"] * 1e3 for r in rows] + list((b * 1e3).ravel()), symmetric=True)
    lim_s = robust_limits([r["std_m"] * 1e3 for r in rows] + list((s * 1e3).ravel()))
    lim_s = (0.0, lim_s[1])
    lim_rb = robust_limits([r["resid"] * 1e3 for r in resid_b], symmetric=True)
    lim_rs = robust_limits([r["resid"] * 1e3 for r in resid_s], symmetric=True)
    panels = [
        (ax[0, 0], "measured mean error (mm)", lambda a: _boxes(a, rows, "mean_m", signed, lim_b)),
        (ax[0, 1], "model bias b(z, theta) (mm)",
         lambda a: a.pcolormesh(zz, tt, np.ma.masked_invalid(b * 1e3), cmap=signed, vmin=lim_b[0],
                                vmax=lim_b[1], shading="auto")),
        (ax[0, 2], "measured - model bias (mm)", lambda a: _boxes(a, resid_b, "resid", signed, lim_rb)),
        (ax[1, 0], "measured std (mm)", lambda a: _boxes(a, rows, "std_m", pos, lim_s)),
        (ax[1, 1], "model sigma(z, theta) (mm)",
         lambda a: a.pcolormesh(zz, tt, np.ma.masked_invalid(s * 1e3), cmap=pos, vmin=lim_s[0], vmax=lim_s[1],
                                shading="auto")),
        (ax[1, 2], "measured - model sigma (mm)", lambda a: _boxes(a, resid_s, "resid", signed, lim_rs)),
    ]
    for a, title, draw in panels:
        a.set_facecolor("0.5")
        m = draw(a)
        fig.colorbar(m, ax=a, label="mm")
        a.set_xlim(z0, z1)
        a.set_ylim(t0, t1)
        a.set_xlabel("distance z (m)")
        a.set_ylabel("inclination (deg)")
        a.set_title(title, fontsize=10)

    def formula(part: Any) -> str:
        out = ""
        for n, (k, c) in enumerate(zip(part.terms, part.coefficients, strict=True)):
            sign = ("-" if c < 0 else "") if n == 0 else (" - " if c < 0 else " + ")
            out += f"{sign}{abs(c) * 1e3:.3g} mm" + ("" if k == "offset" else f" {TERM_FORMULAS[k]}")
        return out

    cam = model.camera
    fig.suptitle(f"Depth error model of {cam.get('name') or cam.get('model') or 'the camera'}"
                 f" {cam.get('serial_number') or ''} {'x'.join(map(str, cam.get('resolution') or []))}\n"
                 f"b = {formula(model.bias)};  sigma = {formula(model.sigma)}  (z in m; grey: outside the "
                 "measured domain)", fontsize=10)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def model_table(model: ErrorModel) -> list[list[str]]:
    """Rows of the console table: part, term, formula, coefficient, its standard error."""
    out = []
    for name, part in (("bias", model.bias), ("sigma", model.sigma)):
        se = np.sqrt(np.maximum(np.diag(part.covariance), 0.0))
        for k, c, e in zip(part.terms, part.coefficients, se, strict=True):
            out.append([name, k, TERM_FORMULAS[k], f"{c * 1e3:+.4g} mm", f"{e * 1e3:.2g} mm"])
    return out
