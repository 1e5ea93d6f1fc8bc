"""The study's pictures: paper Fig. 8 (one frame's maps) and Fig. 9/10 (grid heatmaps).

Heatmaps put distance (m) on x and inclination (deg) on y, mask cells below a count threshold
(paper: 10 for one frame, 2000 for a sequence) and show mean and std in millimetres.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.grid import Grid, display_grid
from depthstation.core.heatmaps import COUNTS, POSITIVE, SIGNED, colormap, robust_limits
from depthstation.evaluate.scan.raycast import FrameImages


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def frame_figure(images: FrameImages, path: Path, title: str = "",
                 appearance: np.ndarray | None = None, appearance_kind: str = "") -> Path:
    """Measured depth, reference depth, inclination and depth error of one frame (Fig. 8); with the
    reference scan's intensity/colour on the surface each pixel sees, when the scan has it."""
    plt = _plt()
    cols = 3 if appearance is not None else 2
    fig, grid = plt.subplots(2, cols, figsize=(5.5 * cols, 8), constrained_layout=True)
    axes = grid[:, :2]
    both = np.concatenate([images.measured_m[np.isfinite(images.measured_m)],
                           images.reference_m[np.isfinite(images.reference_m)]])
    vmax = float(np.percentile(both, 99.5)) if both.size else 1.0
    unmeasured = images.unmeasured
    err_mm = np.where(unmeasured, np.nan, images.error_m * 1000.0)  # as the grid: not those pixels
    finite = err_mm[np.isfinite(err_mm)]
    lim = float(np.percentile(np.abs(finite), 98)) if finite.size else 1.0
    blank = " (grey: no surface, or not scanned)" if unmeasured.any() else ""
    panels = [
        (images.measured_m, "(a) measured depth", "depth (m)", "viridis", 0.0, vmax),
        (images.reference_m, "(b) reference depth (ray cast)", "depth (m)", "viridis", 0.0, vmax),
        (images.inclination_deg, f"(c) inclination{blank}", "inclination (deg)", "magma", 0.0, 90.0),
        (err_mm, "(d) depth error, measured - reference", "error (mm)", "RdBu_r", -lim, lim),
    ]
    for ax, (img, name, unit, cmap, lo, hi) in zip(axes.ravel(), panels, strict=True):
        cm = colormap(cmap)
        im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(name)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        fig.colorbar(im, ax=ax, label=unit)
    if appearance is not None:
        ax = grid[0, 2]
        ax.imshow(np.nan_to_num(np.clip(appearance, 0.0, 1.0), nan=0.5), interpolation="nearest")
        ax.set_title(f"(e) reference scan's {appearance_kind or 'appearance'} (grey: no surface)")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        grid[1, 2].axis("off")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def grid_figure(grid: Grid, path: Path, min_count: int, title: str = "") -> Path:
    """Count, mean error and std per distance x inclination cell (Fig. 9 / Fig. 10), at display bins
    coarse enough for the data; a panel without cells of min_count samples says so."""
    plt = _plt()
    from matplotlib.colors import LogNorm

    shown, (fd, fi) = display_grid(grid, min_count)
    count, mean, std = shown.masked(min_count)
    de, ie = shown.distance_edges_m, shown.inclination_edges_deg
    used = np.nonzero(shown.count.sum(axis=1))[0]
    dmax = float(de[used[-1] + 1]) if used.size else float(de[-1])
    extent = (float(de[0]), float(de[-1]), float(ie[0]), float(ie[-1]))
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.3), constrained_layout=True)
    mean_mm = mean * 1000.0
    std_mm = std * 1000.0
    lo, hi = robust_limits(mean_mm, 98.0, symmetric=True)
    _, smax = robust_limits(std_mm, 98.0)
    cmax = max(int(shown.count.max()), 2)
    bins = (f"{1000 * (de[1] - de[0]):.0f} mm x {ie[1] - ie[0]:.1f} deg cells"
            + (f" (display: {fd} x {fi} analysis cells)" if (fd, fi) != (1, 1) else ""))
    panels = [
        (count, "(a) samples per cell", "count", COUNTS, LogNorm(vmin=1, vmax=cmax)),
        (mean_mm, f"(b) mean error, cells with >= {min_count} samples", "mean error (mm)",
         SIGNED, plt.Normalize(lo, hi)),
        (std_mm, f"(c) std of error, cells with >= {min_count} samples", "std (mm)", POSITIVE,
         plt.Normalize(0.0, max(smax, 1e-9))),
    ]
    for ax, (data, name, unit, cmap, norm) in zip(axes, panels, strict=True):
        im = ax.imshow(data.T, origin="lower", aspect="auto", extent=extent, cmap=colormap(cmap), norm=norm,
                       interpolation="nearest")
        ax.set_xlim(float(de[0]), dmax)
        ax.set_title(name)
        ax.set_xlabel("distance: reference z-depth (m)")
        ax.set_ylabel("inclination (deg)")
        fig.colorbar(im, ax=ax, label=unit)
        if data is not count and not np.ma.count(data):
            ax.text(0.5, 0.5, f"no cell holds {min_count} samples\n(lower --min-count-* or use more frames)",
                    transform=ax.transAxes, ha="center", va="center", fontsize=10,
                    bbox={"facecolor": "white", "alpha": 0.8})
    fig.suptitle((title + "\n" if title else "") + bins, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
