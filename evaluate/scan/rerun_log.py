"""What the reference-scan study streams to rerun: pixel counts per frame, the growing grid as images,
and the final grid as tensors with named, unit-carrying dimensions."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.grid import Grid
from depthstation.core.heatmaps import colorize
from depthstation.core.rerun_bridge import send_heatmap

DESCRIPTION = ("Reference-scan study (paper Section 3.2): every depth pixel is ray cast against "
               "the reference mesh; errors (measured - reference z-depth) are binned over "
               "distance x inclination. `grid/*` shows the growing grid (x: distance, y: "
               "inclination, top = 90 deg).")


def log_frame(rec: Any, index: int, stats: NDArray[np.int64]) -> None:
    """Pixels evaluated, without depth and without a hit in one frame (a series over frames)."""
    if rec is None:
        return
    import rerun as rr

    rec.set_time("frame", sequence=index)
    rec.log("pixels/evaluated", rr.Scalars(float(stats[3])))
    rec.log("pixels/no_depth", rr.Scalars(float(stats[1])))
    rec.log("pixels/no_hit", rr.Scalars(float(stats[2])))


def log_grid(rec: Any, grid: Grid, frame: int, min_count: int) -> None:
    """The grid so far as three images (count, mean, std), as in the PNG heatmaps."""
    if rec is None:
        return
    import rerun as rr

    rec.set_time("frame", sequence=frame)
    count, mean, std = grid.masked(min_count)
    # rows = inclination (top = 90 deg), columns = distance, as in the PNG heatmaps
    flip = (slice(None, None, -1), slice(None))
    cnt = np.log10(np.ma.filled(count.astype(float), np.nan))
    rec.log("grid/count_log10", rr.Image(colorize(cnt.T[flip], 0, max(np.nanmax(cnt), 1), "viridis")))
    m = np.ma.filled(mean * 1000, np.nan)
    lim = float(np.nanpercentile(np.abs(m), 98)) if np.isfinite(m).any() else 1.0
    rec.log("grid/mean_mm", rr.Image(colorize(m.T[flip], -lim, lim, "RdBu_r")))
    s = np.ma.filled(std * 1000, np.nan)
    smax = float(np.nanpercentile(s, 98)) if np.isfinite(s).any() else 1.0
    rec.log("grid/std_mm", rr.Image(colorize(s.T[flip], 0, smax, "magma")))


def log_grid_tensors(rec: Any, grid: Grid, min_count: int) -> None:
    """The final grid as tensors with named dimensions and units (what a reader of the .rrd needs)."""
    if rec is None:
        return
    _, mean, std = grid.masked(min_count)
    edges = (grid.distance_edges_m, grid.inclination_edges_deg)
    send_heatmap(rec, "tensors/count", np.asarray(grid.count, dtype=np.float64), *edges,
                 quantity="samples per cell", unit="1")
    send_heatmap(rec, "tensors/mean_error_m", np.ma.filled(mean.astype(float), np.nan), *edges,
                 quantity=f"mean depth error (cells with >= {min_count} samples)", unit="m")
    send_heatmap(rec, "tensors/std_error_m", np.ma.filled(std.astype(float), np.nan), *edges,
                 quantity=f"std of depth error (cells with >= {min_count} samples)", unit="m")
