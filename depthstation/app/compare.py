"""Several evaluations side by side: matched standpoint tables and cell-by-cell grid differences.

The first folder is the reference; every other is compared against it (other - reference), so a
table reads "how does B differ from A". Pure functions here; files and figures in `compare_write`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import InputError
from depthstation.core.grid import Grid
from depthstation.core.run_warnings import warn

# The figures of a standpoint that are compared (columns of the checkerboard study's standpoints.csv).
STANDPOINT_COLUMNS = (
    "frames", "fill_rate", "reference_distance_std_m", "noise_m", "noise_std_m", "accuracy_m",
    "accuracy_std_m", "accuracy_rms_m", "noise_black_m", "noise_white_m", "accuracy_black_m",
    "accuracy_white_m", "dqt_fill_rate_pct", "dqt_plane_fit_rms_mm", "dqt_plane_fit_rms_pct",
    "dqt_subpixel_rms_px", "dqt_z_accuracy_pct", "dqt_temporal_noise_pct", "dqt_rms_ratio",
)
# Scales that make "nearest standpoint" meaningful across distance and inclination.
DISTANCE_SCALE_M = 0.10
INCLINATION_SCALE_DEG = 5.0


def _finite(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def _offset(a: dict[str, Any], b: dict[str, Any]) -> float:
    """Distance between two standpoints in (distance / 10 cm, inclination / 5 deg) units."""
    dd = (_finite(a["distance_m"]) - _finite(b["distance_m"])) / DISTANCE_SCALE_M
    di = (_finite(a["inclination_deg"]) - _finite(b["inclination_deg"])) / INCLINATION_SCALE_DEG
    return math.hypot(dd, di)


def _place(r: dict[str, Any]) -> str:
    return f"{_finite(r['distance_m']):.2f} m, {_finite(r['inclination_deg']):.0f} deg"


def match_standpoints(ref: list[dict[str, Any]], other: list[dict[str, Any]], mode: str = "auto",
                      max_offset: float = 1.0) -> list[int | None]:
    """For each reference row, the index of its counterpart in `other` (None when unmatched).

    mode 'name': same standpoint name. 'nearest': smallest offset in (distance / 10 cm,
    inclination / 5 deg) units, within `max_offset`, each row of `other` used once (greedy by offset).
    'auto': by name when every reference name exists in `other` and each pair lies within
    `max_offset`, else nearest (a warning says the names disagreed with the geometry).
    """
    if mode not in ("auto", "name", "nearest"):
        raise InputError(None, f"unknown match mode {mode!r} (auto, name, nearest)")
    names = {str(r["standpoint"]): i for i, r in enumerate(other)}
    if mode == "name" or (mode == "auto" and all(str(r["standpoint"]) in names for r in ref)):
        by_name = [names.get(str(r["standpoint"])) for r in ref]
        apart = [(a, other[j]) for a, j in zip(ref, by_name, strict=True)
                 if j is not None and not _offset(a, other[j]) <= max_offset]
        if not apart:
            return by_name
        a, b = apart[0]
        where = (f"{a['standpoint']} is at {_place(a)} in the first and {_place(b)} in the other "
                 f"({len(apart)} such name(s))")
        if mode == "name":  # asked for: kept, and said
            warn(f"standpoints matched by name lie apart: {where}", None, "compare-match")
            return by_name
        # two sessions of different plans share the names standpoint_01..N: geometry decides
        warn(f"standpoint names do not mean the same place ({where}): matched by distance and "
             "inclination instead (--match name forces the names)", None, "compare-match")
    pairs = []
    for i, a in enumerate(ref):
        for j, b in enumerate(other):
            off = _offset(a, b)
            if math.isfinite(off) and off <= max_offset:
                pairs.append((off, i, j))
    out: list[int | None] = [None] * len(ref)
    used: set[int] = set()
    for _, i, j in sorted(pairs):
        if out[i] is None and j not in used:
            out[i] = j
            used.add(j)
    return out


@dataclass
class StandpointComparison:
    labels: list[str]
    rows: list[dict[str, Any]]          # wide table: one row per reference standpoint
    columns: list[str]                  # compared figures present in every table
    summary: dict[str, Any]             # per other label: matched, max |diff|, median ratio per column


def compare_standpoints(tables: list[tuple[str, list[dict[str, Any]]]], mode: str = "auto",
                        max_offset: float = 1.0) -> StandpointComparison:
    """Wide table: per reference standpoint, each label's value of each figure and the difference
    `<col>[<label> - <ref>]`; plus a summary per label (max |difference|, median ratio)."""
    if len(tables) < 2:
        raise InputError(None, "compare needs at least two checkerboard results")
    ref_label, ref_rows = tables[0]
    columns = [c for c in STANDPOINT_COLUMNS if all(rows and c in rows[0] for _, rows in tables)]
    matches = [match_standpoints(ref_rows, rows, mode, max_offset) for _, rows in tables[1:]]
    for (label, _), match in zip(tables[1:], matches, strict=True):
        if all(j is None for j in match):  # every difference empty: the table would read as "no change"
            how = ("by name" if mode == "name" else f"by name or within --max-offset {max_offset:g} "
                   "(1 = 10 cm of distance or 5 deg of inclination)")
            warn(f"no standpoint in common between {ref_label} and {label} (matched {how}): every difference "
                 "is empty", None, "compare-match")
    out_rows: list[dict[str, Any]] = []
    for i, r in enumerate(ref_rows):
        row: dict[str, Any] = {"standpoint": r["standpoint"], "distance_m": r["distance_m"],
                               "inclination_deg": r["inclination_deg"]}
        for (label, rows), match in zip(tables[1:], matches, strict=True):
            j = match[i]
            row[f"standpoint[{label}]"] = rows[j]["standpoint"] if j is not None else ""
        for c in columns:
            a = _finite(r[c])
            row[f"{c}[{ref_label}]"] = a
            for (label, rows), match in zip(tables[1:], matches, strict=True):
                j = match[i]
                b = _finite(rows[j][c]) if j is not None else math.nan
                row[f"{c}[{label}]"] = b
                row[f"{c}[{label} - {ref_label}]"] = b - a
        out_rows.append(row)
    summary: dict[str, Any] = {"reference": ref_label, "columns": columns, "others": {}}
    for (label, _), match in zip(tables[1:], matches, strict=True):
        per: dict[str, Any] = {"matched": sum(j is not None for j in match), "of": len(ref_rows)}
        for c in columns:
            diff = np.array([row[f"{c}[{label} - {ref_label}]"] for row in out_rows], dtype=float)
            va = np.array([row[f"{c}[{ref_label}]"] for row in out_rows], dtype=float)
            vb = np.array([row[f"{c}[{label}]"] for row in out_rows], dtype=float)
            ok = np.isfinite(diff)
            ratio_ok = ok & (np.abs(va) > 0)
            per[c] = {
                "max_abs_diff": float(np.max(np.abs(diff[ok]))) if ok.any() else None,
                "mean_diff": float(np.mean(diff[ok])) if ok.any() else None,
                "median_ratio": float(np.median(vb[ratio_ok] / va[ratio_ok])) if ratio_ok.any() else None,
            }
        summary["others"][label] = per
    return StandpointComparison(labels=[t[0] for t in tables], rows=out_rows, columns=columns,
                                summary=summary)


@dataclass
class GridDifference:
    """Cell-by-cell difference (other - reference) where both grids have at least `min_count`."""

    distance_edges_m: NDArray[np.float64]
    inclination_edges_deg: NDArray[np.float64]
    mask: NDArray[np.bool_]             # cells compared
    mean_diff_m: NDArray[np.float64]    # NaN outside the mask
    std_diff_m: NDArray[np.float64]
    z_mean: NDArray[np.float64]         # mean difference / its standard error
    min_count: int

    def summary(self) -> dict[str, Any]:
        m = self.mask
        n = int(m.sum())

        def stats(a: NDArray[np.float64]) -> dict[str, float | None]:
            v = a[m]
            if n == 0:
                return {"mean": None, "rms": None, "max_abs": None}
            return {"mean": float(np.mean(v)), "rms": float(np.sqrt(np.mean(v**2))),
                    "max_abs": float(np.max(np.abs(v)))}

        return {"cells_compared": n, "min_count": self.min_count,
                "mean_diff_m": stats(self.mean_diff_m), "std_diff_m": stats(self.std_diff_m),
                "cells_significant_3sigma": int(np.sum(np.abs(self.z_mean[m]) > 3.0)) if n else 0}


def _same_edges(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=0, atol=1e-9))


def compare_grids(ref: Grid, other: Grid, min_count: int = 2000) -> GridDifference:
    """Differences of mean and std in the cells where both grids hold at least `min_count` samples."""
    if not (_same_edges(ref.distance_edges_m, other.distance_edges_m)
            and _same_edges(ref.inclination_edges_deg, other.inclination_edges_deg)):
        raise InputError(None, "the grids have different bins; evaluate both with the same grid options")
    mask = (ref.count >= max(min_count, 2)) & (other.count >= max(min_count, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_diff = np.where(mask, other.mean_m - ref.mean_m, np.nan)
        std_diff = np.where(mask, other.std_m - ref.std_m, np.nan)
        se = np.sqrt(ref.var_m2 / np.maximum(ref.count, 1) + other.var_m2 / np.maximum(other.count, 1))
        z = np.where(mask & (se > 0), mean_diff / se, np.where(mask, 0.0, np.nan))
    return GridDifference(ref.distance_edges_m, ref.inclination_edges_deg, mask, mean_diff, std_diff,
                          z, min_count)
