"""One way to colour a field: colormaps with missing cells in one grey, robust colour limits, and
RGB pictures for rerun. Every PNG figure and every rerun image of the station uses these.

Why grey for missing cells: black or white would read as a value at the dark or light end of the
common colormaps (viridis, magma, RdBu); a mid grey is none of them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

MISSING_GREY = 0.5            # matplotlib grey level of cells without data
MISSING_RGB = (128, 128, 128)  # the same in 8-bit RGB
SIGNED = "RdBu_r"              # signed errors: blue = too near, red = too far
POSITIVE = "magma"             # spreads and noise
COUNTS = "viridis"             # sample counts


def colormap(name: str) -> Any:
    """A matplotlib colormap whose masked / NaN cells are MISSING_GREY."""
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=str(MISSING_GREY))


def robust_limits(values: ArrayLike, percentile: float = 98.0, *,
                  symmetric: bool = False) -> tuple[float, float]:
    """Colour limits that a few outliers cannot stretch: the `percentile` of |values| around zero for
    signed quantities, else (100 - p, p) percentiles; (0, 1) or (-1, 1) when nothing is finite."""
    arr = np.ma.filled(np.ma.asarray(values, dtype=np.float64), np.nan)
    finite = arr[np.isfinite(arr)]
    if symmetric:
        lim = float(np.percentile(np.abs(finite), percentile)) if finite.size else 1.0
        lim = lim if lim > 0 else 1e-12
        return -lim, lim
    if not finite.size:
        return 0.0, 1.0
    lo, hi = (float(x) for x in np.percentile(finite, [100.0 - percentile, percentile]))
    return (lo, hi) if hi > lo else (lo, lo + 1e-12)


def colorize(values: ArrayLike, vmin: float | None = None, vmax: float | None = None,
             cmap: str = COUNTS) -> NDArray[np.uint8]:
    """An RGB uint8 picture of a 2-D array (masked or NaN cells MISSING_RGB), for rerun images."""
    import matplotlib

    arr = np.ma.filled(np.ma.asarray(values, dtype=np.float64), np.nan)
    finite = np.isfinite(arr)
    lo = float(np.min(arr[finite])) if vmin is None and finite.any() else (vmin or 0.0)
    hi = float(np.max(arr[finite])) if vmax is None and finite.any() else (vmax or 1.0)
    scaled = np.clip((arr - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](np.where(finite, scaled, 0.0))
    rgb = (rgba[..., :3] * 255).astype(np.uint8)
    rgb[~finite] = MISSING_RGB
    return rgb
