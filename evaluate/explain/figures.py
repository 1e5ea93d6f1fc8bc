"""Explain's pictures: the real-minus-simulated residual over distance x inclination, before and
after the refit, for both forms (checkerboard sessions and reference-scan sequences)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.heatmaps import SIGNED, colormap, robust_limits

# (label, distance edges m, inclination edges deg, real - sim per cell in metres, NaN = untested)
ResidualPanel = tuple[str, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def residual_grid_figure(path: Path, panels: list[ResidualPanel], what: str = "bias") -> Path:
    """One heatmap per panel in mm on a shared symmetric colour scale; a panel without cells says so."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, max(1, len(panels)), figsize=(6 * max(1, len(panels)), 4.2), squeeze=False)
    every = [p[3] * 1000 for p in panels]
    finite = np.concatenate([m[np.isfinite(m)] for m in every]) if every else np.array([])
    _, lim = robust_limits(finite, 100.0, symmetric=True)
    for ax, (label, de, ie, _), mm in zip(axes[0], panels, every, strict=True):
        if not np.isfinite(mm).any():
            ax.set_title(f"{label}: no distance x inclination cells to compare")
            ax.axis("off")
            continue
        im = ax.pcolormesh(de, ie, np.ma.masked_invalid(mm.T), cmap=colormap(SIGNED), vmin=-lim, vmax=lim)
        ax.set_xlabel("distance (m)")
        ax.set_ylabel("inclination (deg)")
        ax.set_title(f"real - sim {what}, {label} (mm)")
        fig.colorbar(im, ax=ax, label="mm (grey: not compared)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
