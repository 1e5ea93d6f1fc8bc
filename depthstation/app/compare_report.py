"""`depthstation compare`: read result folders, compare them, write tables, figures and a recording."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from depthstation.app.compare import (
    GridDifference,
    StandpointComparison,
    compare_grids,
    compare_standpoints,
)
from depthstation.core import rerun_bridge as viz
from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE, Grid, display_grid
from depthstation.core.heatmaps import SIGNED, colormap, robust_limits
from depthstation.core.progress import stderr_console
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import (
    STANDPOINTS_FILE,
    open_result,
    read_standpoints,
    result_folder,
    unique_labels,
    write_json,
    write_result_info,
)
from depthstation.core.run_warnings import warn

COMPARE_CSV = "standpoints_compare.csv"


def safe_name(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label).strip("_") or "result"


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys.extend(k for k in r if k not in keys)
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()})


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _standpoint_figure(path: Path, cmp: StandpointComparison, label: str) -> None:
    """Per standpoint, difference of noise and accuracy (mm) placed over distance x inclination (the
    axes of the evaluation figures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = cmp.labels[0]
    dist = np.array([r["distance_m"] for r in cmp.rows], dtype=float)
    incl = np.array([r["inclination_deg"] for r in cmp.rows], dtype=float)
    panels = [("noise_m", "noise", 1e3, "mm"), ("accuracy_m", "accuracy (mean signed)", 1e3, "mm")]
    if any(np.isfinite(_num(r.get(f"dqt_plane_fit_rms_pct[{label} - {ref}]"))) for r in cmp.rows):
        panels.append(("dqt_plane_fit_rms_pct", "DQT plane-fit RMS", 1.0, "% of distance"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.5), constrained_layout=True)
    for ax, (col, title, scale, unit) in zip(axes, panels, strict=True):
        key = f"{col}[{label} - {ref}]"
        diff = np.array([_num(r.get(key)) for r in cmp.rows], dtype=float) * scale
        ok = np.isfinite(diff)
        lo, hi = robust_limits(diff, 100.0, symmetric=True)
        sc = ax.scatter(dist[ok], incl[ok], c=diff[ok], cmap=colormap(SIGNED), vmin=lo, vmax=hi, s=160,
                        edgecolors="k")
        if (~ok).any():
            ax.scatter(dist[~ok], incl[~ok], marker="x", c="grey", label="unmatched")
            ax.legend(loc="best")
        fig.colorbar(sc, ax=ax, label=f"difference [{unit}]")
        ax.set_xlabel("distance [m]")
        ax.set_ylabel("inclination [deg]")
        ax.set_title(f"{title} difference per standpoint")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{label} - {ref}: {int(ok.sum())} of {len(cmp.rows)} standpoints matched", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _display_difference(ref: Grid, other: Grid, min_count: int) -> tuple[GridDifference, tuple[int, int]]:
    """The difference at display cells coarse enough that cells with min_count samples in both grids
    hold most of the samples (the same rule as Fig. 9/10); the factors used."""
    both = Grid(ref.distance_edges_m, ref.inclination_edges_deg, np.minimum(ref.count, other.count),
                np.zeros(ref.shape), np.zeros(ref.shape))
    f = display_grid(both, min_count)[1]
    if f == (1, 1):
        return compare_grids(ref, other, min_count), f
    return compare_grids(ref.coarsened(*f), other.coarsened(*f), min_count), f


def _grid_figure(path: Path, diff: GridDifference, label: str, ref: str,
                 factors: tuple[int, int] = (1, 1)) -> None:
    """Heatmaps of the mean and std differences (mm) over distance x inclination, cropped to data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    de, ie = diff.distance_edges_m, diff.inclination_edges_deg
    rows = np.flatnonzero(diff.mask.any(axis=1))
    cols = np.flatnonzero(diff.mask.any(axis=0))
    for ax, arr, title in zip(axes, (diff.mean_diff_m, diff.std_diff_m),
                                  ("mean error", "std of error"), strict=True):
        mm = np.ma.masked_invalid(arr * 1e3)
        lo, hi = robust_limits(mm, 98.0, symmetric=True)
        mesh = ax.pcolormesh(de, ie, mm.T, cmap=colormap(SIGNED), vmin=lo, vmax=hi, shading="flat")
        fig.colorbar(mesh, ax=ax, label="difference [mm]")
        if rows.size and cols.size:
            ax.set_xlim(de[rows[0]], de[rows[-1] + 1])
            ax.set_ylim(ie[cols[0]], ie[cols[-1] + 1])
        else:
            ax.text(0.5, 0.5, f"no cell holds {diff.min_count} samples in both", transform=ax.transAxes,
                    ha="center", va="center")
        ax.set_xlabel("distance [m]")
        ax.set_ylabel("inclination [deg]")
        ax.set_title(f"{title} difference (cells with >= {diff.min_count} samples in both)")
    cells = (f"{1000 * (de[1] - de[0]):.0f} mm x {ie[1] - ie[0]:.1f} deg cells"
             + (f" (display: {factors[0]} x {factors[1]} analysis cells)" if factors != (1, 1) else ""))
    fig.suptitle(f"{label} - {ref}: {cells}", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _print_standpoints(cmp: StandpointComparison) -> None:


    ref = cmp.labels[0]
    table = Table(title=f"checkerboard results side by side (differences against {ref}), mm")
    for head in ("standpoint", "dist m", "incl deg"):
        table.add_column(head)
    for col in ("noise_m", "accuracy_m"):
        for lab in cmp.labels:
            table.add_column(f"{col[:-2]} {lab}", justify="right")
        for lab in cmp.labels[1:]:
            table.add_column(f"d{col[:-2]} {lab}", justify="right")

    def mm(v: Any) -> str:
        return "-" if not np.isfinite(v) else f"{1e3 * float(v):.2f}"

    for r in cmp.rows:
        cells = [str(r["standpoint"]), f"{r['distance_m']:.2f}", f"{r['inclination_deg']:.1f}"]
        for col in ("noise_m", "accuracy_m"):
            cells += [mm(r.get(f"{col}[{lab}]", np.nan)) for lab in cmp.labels]
            cells += [mm(r.get(f"{col}[{lab} - {ref}]", np.nan)) for lab in cmp.labels[1:]]
        table.add_row(*cells)
    stderr_console.print(table)
    dqt = [("dqt_plane_fit_rms_pct", "RMS %"), ("dqt_subpixel_rms_px", "subpx px"),
           ("dqt_z_accuracy_pct", "Z acc %"), ("dqt_fill_rate_pct", "fill %")]
    if not any(np.isfinite(_num(r.get(f"{c}[{ref}]"))) for r in cmp.rows for c, _ in dqt):
        return
    table = Table(title="Intel Depth Quality Tool metrics side by side (board mask)")
    table.add_column("standpoint")
    for _, head in dqt:
        for lab in cmp.labels:
            table.add_column(f"{head} {lab}", justify="right")
    for r in cmp.rows:
        cells = [str(r["standpoint"])]
        for c, _ in dqt:
            cells += [f"{_num(r.get(f'{c}[{lab}]')):.3g}" for lab in cmp.labels]
        table.add_row(*cells)
    stderr_console.print(table)


def _print_grids(ref: str, diffs: dict[str, GridDifference]) -> None:


    table = Table(title=f"scan grids against {ref} (other - reference), mm")
    for head in ("result", "cells", "mean diff", "rms diff", "max |diff|", "std diff mean",
                 "cells > 3 sigma"):
        table.add_column(head, justify="right")

    def mm(v: Any) -> str:
        return "-" if v is None else f"{1e3 * v:.3f}"

    for lab, d in diffs.items():
        s = d.summary()
        table.add_row(lab, str(s["cells_compared"]), mm(s["mean_diff_m"]["mean"]),
                      mm(s["mean_diff_m"]["rms"]),
                      mm(s["mean_diff_m"]["max_abs"]), mm(s["std_diff_m"]["mean"]),
                      str(s["cells_significant_3sigma"]))
    stderr_console.print(table)


def run_compare(dirs: list[Path], out: Path, *, min_count: int = 2000, match: str = "auto",
                max_offset: float = 1.0, target: RerunTarget | None = None,
                quiet: bool = False, force: bool = False) -> dict[str, Any]:
    """Compare result folders of one kind (the first is the reference) into `out` (written whole or
    not at all; a non-empty `out` only with `force`); returns the summary."""
    if min_count < 1:
        raise InputError(None, f"--min-count must be at least 1 sample, not {min_count}")
    if not (math.isfinite(max_offset) and max_offset >= 0):  # negative or NaN matched nothing, exit 0
        raise InputError(None, f"--max-offset must be a finite number of units >= 0 (1 = 10 cm of distance "
                               f"or 5 deg of inclination), not {max_offset}")
    with result_folder(out, force=force, inputs=dirs, kind="compare") as tmp:
        return _compare(dirs, tmp, min_count=min_count, match=match, max_offset=max_offset,
                        target=None if target is None else target.within(out, tmp), quiet=quiet)


def _compare(dirs: list[Path], out: Path, *, min_count: int, match: str, max_offset: float,
             target: RerunTarget | None, quiet: bool) -> dict[str, Any]:
    if len(dirs) < 2:
        raise InputError(None, "compare needs at least two result folders")
    folders = [open_result(d) for d in dirs]
    kinds = {f.kind for f in folders}
    if len(kinds) > 1:
        listing = ", ".join(f"{f.path} ({f.kind})" for f in folders)
        raise InputError(None, f"compare needs results of one kind; got {listing}")
    kind = folders[0].kind
    if kind not in ("checkerboard", "scan"):
        raise InputError(folders[0].path, f"compare reads checkerboard and scan results, not {kind}")
    labels = unique_labels(folders)
    pairs = list(zip(labels, folders, strict=True))
    summary: dict[str, Any] = {"kind": kind, "reference": labels[0], "labels": labels,
                               "inputs": {lab: str(f.path) for lab, f in pairs},
                               "devices": {lab: f.info.get("device", {}) for lab, f in pairs}}
    files: list[str] = []
    rec_items: list[tuple[str, Any]] = []
    if kind == "checkerboard":
        tables = [(lab, read_standpoints(f.path / STANDPOINTS_FILE)) for lab, f in pairs]
        for (_, f), (_, rows) in zip(pairs, tables, strict=True):
            if not rows:
                raise InputError(f.path / STANDPOINTS_FILE, "no standpoints")
        cmp = compare_standpoints(tables, match, max_offset)
        write_csv(out / COMPARE_CSV, cmp.rows)
        files.append(COMPARE_CSV)
        for lab in labels[1:]:
            name = f"compare_{safe_name(lab)}.png"
            _standpoint_figure(out / name, cmp, lab)
            files.append(name)
        summary["standpoints"] = cmp.summary
        if not quiet:
            _print_standpoints(cmp)
        rec_items.append(("standpoints", cmp))
    else:
        grids = [Grid.load(f.path / GRID_FILE) for f in folders]
        diffs: dict[str, GridDifference] = {}
        for lab, path, g in zip(labels[1:], dirs[1:], grids[1:], strict=True):
            d = compare_grids(grids[0], g, min_count)
            diffs[lab] = d
            stem = f"grid_diff_{safe_name(lab)}"
            np.savez(out / f"{stem}.npz", distance_edges_m=d.distance_edges_m,
                     inclination_edges_deg=d.inclination_edges_deg, mask=d.mask,
                     mean_diff_m=d.mean_diff_m, std_diff_m=d.std_diff_m, z_mean=d.z_mean)
            if not d.mask.any():
                warn(f"no cell holds {min_count} samples in both {labels[0]} and {lab} (--min-count); "
                     "the figure compares coarser display cells", str(path), "sparse-grid")
            shown, factors = _display_difference(grids[0], g, min_count)
            _grid_figure(out / f"{stem}.png", shown, lab, labels[0], factors)
            files += [f"{stem}.npz", f"{stem}.png"]
        summary["grids"] = {lab: d.summary() for lab, d in diffs.items()}
        if not quiet:
            _print_grids(labels[0], diffs)
        rec_items.append(("grids", diffs))
    summary["files"] = files
    write_json(out / "summary.json", summary)
    write_result_info(out, "compare", [str(d) for d in dirs],
                      {"min_count": min_count, "match": match, "max_offset": max_offset},
                      extra={"compared_kind": kind, "reference": labels[0]})
    if target is not None and target.enabled:
        _record(target, kind, labels, rec_items)
    return summary


def _record(target: RerunTarget, kind: str, labels: list[str], items: list[tuple[str, Any]]) -> None:

    ref = labels[0]
    text = (f"# Comparison of {kind} results\n\nReference: **{ref}**. Every other result is shown as "
            f"`other - reference`.\n\n")
    views: list[Any] = []
    with viz.recording("depthstation-compare", target, None, None) as rec:
        for what, obj in items:
            if what == "grids":
                text += ("Heatmaps: tensors over `distance [m]` (rows) x `inclination [deg]` (columns); "
                         "values in metres; empty where either grid has too few samples.\n")
                for lab, d in obj.items():
                    base = f"compare/{safe_name(lab)}"
                    viz.send_heatmap(rec, f"{base}/mean_diff", d.mean_diff_m, d.distance_edges_m,
                                     d.inclination_edges_deg, quantity=f"mean error {lab} - {ref}",
                                     unit="m")
                    viz.send_heatmap(rec, f"{base}/std_diff", d.std_diff_m, d.distance_edges_m,
                                     d.inclination_edges_deg, quantity=f"std of error {lab} - {ref}",
                                     unit="m")
                    views += [viz.heatmap_view(f"{base}/mean_diff", f"mean diff {lab} [m]"),
                              viz.heatmap_view(f"{base}/std_diff", f"std diff {lab} [m]")]
            else:
                text += ("Series: per standpoint (in table order) noise and accuracy of every result, "
                         "metres.\n")
                for lab in labels:
                    for col in ("noise_m", "accuracy_m"):
                        vals = [r.get(f"{col}[{lab}]", np.nan) for r in obj.rows]
                        viz.send_series(rec, f"standpoints/{col}/{safe_name(lab)}", np.arange(len(vals)),
                                        vals,
                                        name=f"{col[:-2]} {lab}", unit="m", timeline="standpoint")
                views += [viz.series_view("standpoints/noise_m", "noise per standpoint [m]"),
                          viz.series_view("standpoints/accuracy_m", "accuracy per standpoint [m]")]
                viz.send_table(rec, "standpoints/table", obj.rows)
        viz.send_text(rec, viz.DESCRIPTION_PATH, text)
        if rec is not None:
            import rerun as rr

            rr.send_blueprint(viz.blueprint(*views), recording=rec)
