"""Explain's pictures: the real-minus-simulated residual over distance x inclination, before and
after the refit, for both forms (checkerboard sessions and reference-scan sequences)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.heatmaps import SIGNED, colormap, robust_limits

# (label, distance edges m, inclination edges deg, real - sim per cell in metres, NaN = untested)
ResidualPanel = tuple[str, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def wrapped(title: str, width_in: float, fontsize: float) -> str:
    """A title broken into lines that fit `width_in` inches at `fontsize` points (a discovered term's
    expression runs to 150 characters: on one line it was cut at the figure's edges)."""
    chars = max(20, int(width_in * 72 / (0.6 * fontsize)))
    return "\n".join(textwrap.wrap(title, chars, break_on_hyphens=False)) or title


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


def _frame_binned(x: NDArray[np.float64], val: NDArray[np.float64], frame: NDArray[np.int64],
                  edges: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per bin: mean of the frames' means, and its standard error (frames are the units)."""
    nb = len(edges) - 1
    b = np.digitize(x, edges) - 1
    ok = (b >= 0) & (b < nb) & np.isfinite(val) & np.isfinite(x)
    mean, se = np.full(nb, np.nan), np.full(nb, np.nan)
    if not ok.any():
        return mean, se
    key = b[ok] * 100_000_000 + frame[ok]
    uk, inv = np.unique(key, return_inverse=True)
    fm = np.bincount(inv.ravel(), weights=val[ok]) / np.bincount(inv.ravel())
    fb = uk // 100_000_000
    for i in range(nb):
        m = fm[fb == i]
        if len(m) >= 2:
            mean[i], se[i] = float(m.mean()), float(m.std(ddof=1) / np.sqrt(len(m)))
    return mean, se


def term_residual_figure(path: Path, title: str, xlabel: str, ylabel: str,
                         sides: list[tuple[str, NDArray[np.float64], NDArray[np.float64],
                                           NDArray[np.float64]]],
                         curve: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]) -> Path:
    """The residual along a term's axis before and after the refit (bars 2 SE), with the fitted
    curve and its 2 SE band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    xg, yg, band = curve
    ax.fill_between(xg, yg - band, yg + band, color="tab:green", alpha=0.25, label="fitted term, 2 SE band")
    ax.plot(xg, yg, color="tab:green", lw=2)
    for k, (label, x, m, se) in enumerate(sides):
        ok = np.isfinite(m)
        ax.errorbar(x[ok] + (k - 0.5) * 0.01 * (np.ptp(x[ok]) if ok.sum() > 1 else 1.0), m[ok],
                    yerr=2 * se[ok], marker="o", capsize=3, ls="none", label=label)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(wrapped(title, 6.3, 9), fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def term_field_figure(path: Path, title: str, unit: str, xe: NDArray[np.float64], ye: NDArray[np.float64],
                      panels: list[tuple[str, NDArray[np.float64]]]) -> Path:
    """A term over the image (x, y normalised): residual before, fitted field, residual after, band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6), squeeze=False)
    finite = np.concatenate([m[np.isfinite(m)] for _, m in panels]) if panels else np.array([])
    _, lim = robust_limits(finite, 100.0, symmetric=True)
    for ax, (label, m) in zip(axes[0], panels, strict=True):
        im = ax.pcolormesh(xe, ye, np.ma.masked_invalid(m.T), cmap=colormap(SIGNED), vmin=-lim, vmax=lim)
        ax.invert_yaxis()
        ax.set_xlabel("x = (u - ppx) / fx")
        ax.set_ylabel("y = (v - ppy) / fx")
        ax.set_title(label, fontsize=9)
        fig.colorbar(im, ax=ax, label=unit)
    fig.suptitle(wrapped(title, 4.2 * len(panels) - 0.3, 9), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
