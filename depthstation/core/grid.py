"""Distance x inclination grid of running statistics (count, mean, M2) per cell, mergeable (Chan).

Why running statistics: the reference-scan study bins ~400 M depth errors; keeping them is out of
the question, and count/mean/M2 per cell is exact, cheap to update (Welford) and can be merged
across frames, chunks or workers (Chan et al.) to the same result up to float rounding.
"""

from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import stdtrit

from depthstation.core.errors import InputError

GRID_FILE = "grid.npz"
DEFAULT_DISTANCE_MAX_M = 6.0
DEFAULT_DISTANCE_BIN_M = 0.005
DEFAULT_INCLINATION_MAX_DEG = 90.0
DEFAULT_INCLINATION_BIN_DEG = 0.1
# No fast maths in the kernels that bin or accumulate: LLVM contracts a * b + c into an FMA where
# the CPU has one and reorders sums to the CPU's vector width, so with it a sample near a bin edge
# lands in the neighbouring bin, and a cell's mean differs in its last bits, from one CPU to
# another (docs/conventions.md, "Same result on every CPU"; tests/test_cpu_targets.py). It cost
# nothing measurable: the scan study's per-frame step 0.99x (benchmarks/bench_scan_parts.py).
EXACT_MATH = False


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def bin_index(x: float, lo: float, step: float, n: int) -> int:
    """Cell of x in n uniform bins from lo; -1 outside. The top edge belongs to the last bin
    (inclination is folded into [0, 90], so 90 must not fall out)."""
    k = int(np.floor((x - lo) / step))
    if k == n and x <= lo + n * step * (1.0 + 1e-12):
        return n - 1
    if k < 0 or k >= n:
        return -1
    return k


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def welford_add(count: Any, mean: Any, m2: Any, k: int, j: int, x: float) -> None:
    """One Welford update of cell (k, j); kept tiny so fused kernels elsewhere can inline it."""
    n = count[k, j] + 1
    count[k, j] = n
    delta = x - mean[k, j]
    mu = mean[k, j] + delta / n
    mean[k, j] = mu
    m2[k, j] += delta * (x - mu)


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _add_batch(count: Any, mean: Any, m2: Any, dist: Any, incl: Any, val: Any,
               d_lo: float, d_step: float, nd: int, i_lo: float, i_step: float, ni: int) -> int:
    added = 0
    for p in range(dist.shape[0]):
        x = val[p]
        d = dist[p]
        a = incl[p]
        if not (np.isfinite(x) and np.isfinite(d) and np.isfinite(a)):
            continue
        k = bin_index(d, d_lo, d_step, nd)
        if k < 0:
            continue
        j = bin_index(a, i_lo, i_step, ni)
        if j < 0:
            continue
        welford_add(count, mean, m2, k, j, x)
        added += 1
    return added


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _chan_merge(count: Any, mean: Any, m2: Any, ocount: Any, omean: Any, om2: Any) -> None:
    nd, ni = count.shape
    for k in range(nd):
        for j in range(ni):
            nb = ocount[k, j]
            if nb == 0:
                continue
            na = count[k, j]
            if na == 0:
                count[k, j] = nb
                mean[k, j] = omean[k, j]
                m2[k, j] = om2[k, j]
                continue
            n = na + nb
            delta = omean[k, j] - mean[k, j]
            mean[k, j] += delta * nb / n
            m2[k, j] += om2[k, j] + delta * delta * (na * nb / n)
            count[k, j] = n


def _uniform_edges(lo: float, hi: float, step: float) -> NDArray[np.float64]:
    n = round((hi - lo) / step)
    if n < 1 or abs(lo + n * step - hi) > 1e-9 * max(1.0, abs(hi)):
        raise InputError(None, f"grid range {lo}..{hi} is not a whole number of {step} bins")
    return np.linspace(lo, hi, n + 1)


@dataclass
class FrameMoments:
    """Per cell, the frames that saw it and moments of their per-frame cell means m_f weighted by
    n_f^2 (n_f the frame's samples in the cell): what the standard error of a cell mean needs.

    Why: the pixels of one frame are not independent (one pose error, one exposure, spatially
    correlated stereo matching move them together), so sqrt(var / n) over pixels understates the
    uncertainty of a cell mean by the square root of the design effect. Frames as clusters give the
    cluster-robust (sandwich) variance  F / (F - 1) * sum n_f^2 (m_f - mean)^2 / N^2, exact to add
    frame by frame and to merge across chunks (the sums add).
    """

    frames: NDArray[np.int64]
    n2: NDArray[np.float64]        # sum over frames of n_f^2
    n2_mean: NDArray[np.float64]   # sum of n_f^2 m_f
    n2_mean2: NDArray[np.float64]  # sum of n_f^2 m_f^2

    @classmethod
    def zeros(cls, shape: tuple[int, int]) -> FrameMoments:
        return cls(np.zeros(shape, np.int64), np.zeros(shape), np.zeros(shape), np.zeros(shape))

    def copy(self) -> FrameMoments:
        return FrameMoments(self.frames.copy(), self.n2.copy(), self.n2_mean.copy(), self.n2_mean2.copy())

    def add_cells(self, cells: NDArray[np.integer[Any]], n: ArrayLike, mean: ArrayLike) -> None:
        """One frame's cells (flat indices, each once), its sample counts and means there."""
        nf = np.asarray(n, dtype=np.float64)
        mf = np.asarray(mean, dtype=np.float64)
        w = nf * nf
        self.frames.ravel()[cells] += 1
        self.n2.ravel()[cells] += w
        self.n2_mean.ravel()[cells] += w * mf
        self.n2_mean2.ravel()[cells] += w * mf * mf

    def merge(self, other: FrameMoments) -> FrameMoments:
        """Fold in the moments of other frames (never the same frames twice); returns self."""
        self.frames += other.frames
        self.n2 += other.n2
        self.n2_mean += other.n2_mean
        self.n2_mean2 += other.n2_mean2
        return self


def _weighted_median(values: NDArray[np.float64], weights: NDArray[np.float64]) -> float:
    """The value below which half the weight lies (NaN values dropped)."""
    ok = np.isfinite(values)
    v, w = values[ok], weights[ok]
    if v.size == 0:
        return float("nan")
    order = np.argsort(v)
    cum = np.cumsum(w[order])
    return float(v[order][np.searchsorted(cum, 0.5 * cum[-1])])


@dataclass
class Grid:
    """count/mean/M2 over (distance bin, inclination bin); bins are uniform and half-open, the last
    one closed (6.0 m and 90 deg are kept).

    Arrays are shaped (distance, inclination). `mean_m` is the mean signed depth error
    (measured - reference, metres); `var_m2` = M2 / (count - 1) (NaN below 2 samples).
    """

    distance_edges_m: NDArray[np.float64]
    inclination_edges_deg: NDArray[np.float64]
    count: NDArray[np.int64]
    mean: NDArray[np.float64]
    m2: NDArray[np.float64]
    # frame-clustered moments for the standard error of the cell means; None where frames are
    # not known (grids of single samples, coarsened display grids, old files)
    moments: FrameMoments | None = field(default=None, compare=False)
    # per cell, the standard uncertainty of the reference itself (a cloud's fitted planes), shared
    # by the cell's pixels and so not averaged down: added to u95_m in quadrature (None: a mesh)
    reference_u_m: NDArray[np.float64] | None = field(default=None, compare=False)

    @classmethod
    def empty(cls, distance_bin_m: float = DEFAULT_DISTANCE_BIN_M,
              inclination_bin_deg: float = DEFAULT_INCLINATION_BIN_DEG,
              distance_max_m: float = DEFAULT_DISTANCE_MAX_M,
              inclination_max_deg: float = DEFAULT_INCLINATION_MAX_DEG,
              distance_min_m: float = 0.0, inclination_min_deg: float = 0.0) -> Grid:
        """The DESIGN §2 grid (0-6 m x 5 mm, 0-90 deg x 0.1 deg) unless told otherwise."""
        if distance_bin_m <= 0 or inclination_bin_deg <= 0:
            raise InputError(None, "grid bin sizes must be positive")
        de = _uniform_edges(distance_min_m, distance_max_m, distance_bin_m)
        ie = _uniform_edges(inclination_min_deg, inclination_max_deg, inclination_bin_deg)
        return cls.with_edges(de, ie)

    @classmethod
    def with_edges(cls, distance_edges_m: ArrayLike, inclination_edges_deg: ArrayLike) -> Grid:
        de = np.asarray(distance_edges_m, dtype=np.float64)
        ie = np.asarray(inclination_edges_deg, dtype=np.float64)
        shape = (de.size - 1, ie.size - 1)
        return cls(de, ie, np.zeros(shape, np.int64), np.zeros(shape), np.zeros(shape))

    def like(self) -> Grid:
        """An empty grid with the same bins (for per-frame or per-chunk partial grids)."""
        return Grid.with_edges(self.distance_edges_m.copy(), self.inclination_edges_deg.copy())

    def copy(self) -> Grid:
        return Grid(self.distance_edges_m.copy(), self.inclination_edges_deg.copy(),
                    self.count.copy(), self.mean.copy(), self.m2.copy(),
                    None if self.moments is None else self.moments.copy())

    def with_frame_moments(self) -> Grid:
        """Start keeping frame-clustered moments (an empty grid: every frame must be added)."""
        if self.total:
            raise ValueError("frame moments must start with an empty grid")
        self.moments = FrameMoments.zeros(self.shape)
        return self

    # -- bin geometry used by the fused kernels ------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return (self.distance_edges_m.size - 1, self.inclination_edges_deg.size - 1)

    @property
    def bins(self) -> tuple[float, float, int, float, float, int]:
        """(d_lo, d_step, nd, i_lo, i_step, ni) for the numba kernels (uniform bins)."""
        de, ie = self.distance_edges_m, self.inclination_edges_deg
        nd, ni = self.shape
        return (float(de[0]), float((de[-1] - de[0]) / nd), nd,
                float(ie[0]), float((ie[-1] - ie[0]) / ni), ni)

    @property
    def distance_centers_m(self) -> NDArray[np.float64]:
        return 0.5 * (self.distance_edges_m[1:] + self.distance_edges_m[:-1])

    @property
    def inclination_centers_deg(self) -> NDArray[np.float64]:
        return 0.5 * (self.inclination_edges_deg[1:] + self.inclination_edges_deg[:-1])

    # -- updates --------------------------------------------------------------------------------
    def add(self, distance_m: ArrayLike, inclination_deg: ArrayLike, values: ArrayLike) -> int:
        """Welford-add a batch of samples; non-finite or out-of-range samples are skipped.

        Returns how many samples landed in the grid.
        """
        d = np.ascontiguousarray(distance_m, dtype=np.float64).ravel()
        a = np.ascontiguousarray(inclination_deg, dtype=np.float64).ravel()
        x = np.ascontiguousarray(values, dtype=np.float64).ravel()
        if not (d.size == a.size == x.size):
            raise ValueError("distance, inclination and values must have the same size")
        return int(_add_batch(self.count, self.mean, self.m2, d, a, x, *self.bins))

    def compatible(self, other: Grid) -> bool:
        return (self.shape == other.shape
                and np.allclose(self.distance_edges_m, other.distance_edges_m)
                and np.allclose(self.inclination_edges_deg, other.inclination_edges_deg))

    def add_frame(self, frame: Grid) -> Grid:
        """Merge one frame's partial grid, keeping its frame moments; `frame` is emptied (where it
        holds samples) for the next frame. Returns self."""
        if not self.compatible(frame):
            raise ValueError("cannot merge grids with different bins")
        cells = np.flatnonzero(frame.count)
        n, m = frame.count.ravel()[cells], frame.mean.ravel()[cells]
        if self.moments is not None:
            self.moments.add_cells(cells, n, m)
        _chan_merge(self.count, self.mean, self.m2, frame.count, frame.mean, frame.m2)
        for a in (frame.count, frame.mean, frame.m2):
            a.ravel()[cells] = 0
        return self

    def merge(self, other: Grid) -> Grid:
        """Fold another grid into this one (Chan's parallel formula); returns self. Frame moments
        survive only when both grids keep them."""
        if not self.compatible(other):
            raise ValueError("cannot merge grids with different bins")
        had = self.total > 0
        _chan_merge(self.count, self.mean, self.m2, other.count, other.mean, other.m2)
        if self.moments is not None and other.moments is not None:
            self.moments.merge(other.moments)
        elif self.moments is None and other.moments is not None and not had:
            self.moments = other.moments.copy()
        elif other.moments is None and other.total:
            self.moments = None
        return self

    # -- read-outs ------------------------------------------------------------------------------
    @property
    def total(self) -> int:
        return int(self.count.sum())

    @property
    def mean_m(self) -> NDArray[np.float64]:
        """Mean per cell, NaN in empty cells."""
        out = np.full(self.shape, np.nan)
        np.copyto(out, self.mean, where=self.count > 0)
        return out

    @property
    def var(self) -> NDArray[np.float64]:
        """Sample variance M2 / (n - 1) per cell, NaN below two samples."""
        out = np.full(self.shape, np.nan)
        ok = self.count > 1
        out[ok] = self.m2[ok] / (self.count[ok] - 1)
        return out

    var_m2 = var

    @property
    def std(self) -> NDArray[np.float64]:
        return np.sqrt(self.var)

    std_m = std

    @property
    def stderr(self) -> NDArray[np.float64]:
        """Standard error of the cell mean as if every sample were independent, sqrt(var / n)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(self.var / self.count)

    @property
    def frames(self) -> NDArray[np.int64] | None:
        """Frames with samples in each cell (None without frame moments)."""
        return None if self.moments is None else self.moments.frames

    @property
    def se_m(self) -> NDArray[np.float64]:
        """Standard error of the cell mean with the frames as clusters (FrameMoments), NaN below two
        frames; without frame moments, the independent-sample stderr (an underestimate)."""
        fm = self.moments
        if fm is None:
            return self.stderr
        out = np.full(self.shape, np.nan)
        ok = fm.frames > 1
        mu = self.mean[ok]
        ss = fm.n2_mean2[ok] - 2.0 * mu * fm.n2_mean[ok] + mu * mu * fm.n2[ok]
        f = fm.frames[ok].astype(np.float64)
        n = self.count[ok].astype(np.float64)
        out[ok] = np.sqrt(np.maximum(ss, 0.0) * f / (f - 1.0)) / n
        return out

    @property
    def effective_frames(self) -> NDArray[np.float64] | None:
        """Kish's effective number of frames N^2 / sum n_f^2 per cell (frames of unequal weight count
        less): the degrees of freedom of se_m are effective_frames - 1."""
        fm = self.moments
        if fm is None:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(fm.n2 > 0, self.count.astype(np.float64) ** 2 / fm.n2, np.nan)

    @property
    def u95_m(self) -> NDArray[np.float64]:
        """Expanded uncertainty (95%) of the cell mean: t(0.975, dof) se_m with dof = effective frames
        - 1 (at least 1), which covers the true mean in ~95% of cells even for frames of very unequal
        size (tests/test_grid.py); without frame moments, 1.96 stderr (an underestimate)."""
        feff = self.effective_frames
        if feff is None:
            u = 1.96 * self.stderr
        else:
            dof = np.maximum(np.nan_to_num(feff, nan=2.0) - 1.0, 1.0)
            u = np.asarray(stdtrit(dof, 0.975) * self.se_m, dtype=np.float64)
        if self.reference_u_m is not None:  # the reference's own error, one per cell (k = 1.96)
            u = np.sqrt(u * u + (1.96 * np.nan_to_num(self.reference_u_m)) ** 2)
        return np.asarray(u, dtype=np.float64)

    @property
    def design_effect(self) -> NDArray[np.float64]:
        """(se_m / stderr)^2 per cell: how many pixels count as one independent sample."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return (self.se_m / self.stderr) ** 2

    def coarsened(self, fd: int, fi: int) -> Grid:
        """The same samples in cells fd x fi times larger (exact: Chan's merge within each block);
        the bin counts must divide by the factors."""
        nd, ni = self.shape
        if nd % fd or ni % fi:
            raise ValueError(f"grid of {nd} x {ni} bins does not divide into blocks of {fd} x {fi}")
        c = self.count.reshape(nd // fd, fd, ni // fi, fi).astype(np.float64)
        m = self.mean.reshape(c.shape)
        n = c.sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = np.where(n > 0, (c * m).sum(axis=(1, 3)) / n, 0.0)
        m2 = (self.m2.reshape(c.shape).sum(axis=(1, 3))
              + (c * (m - mu[:, None, :, None]) ** 2).sum(axis=(1, 3)))
        return Grid(self.distance_edges_m[::fd].copy(), self.inclination_edges_deg[::fi].copy(),
                    n.astype(np.int64), mu, m2)

    def masked(self, min_count: int = 1) -> tuple[np.ma.MaskedArray[Any, Any], np.ma.MaskedArray[Any, Any],
                                                  np.ma.MaskedArray[Any, Any]]:
        """(count, mean, std) with cells below `min_count` samples masked (paper: 10 / 2000)."""
        low = self.count < max(1, int(min_count))
        return (np.ma.masked_array(self.count, mask=self.count == 0),
                np.ma.masked_invalid(np.ma.masked_array(self.mean_m, mask=low)),
                np.ma.masked_invalid(np.ma.masked_array(self.std, mask=low | (self.count < 2))))

    def summary(self) -> dict[str, Any]:
        """Overall figures: samples, occupied cells, pooled mean and std of all samples."""
        n = self.total
        if n == 0:
            return {"samples": 0, "cells": 0, "mean_m": None, "std_m": None}
        c = self.count[self.count > 0].astype(np.float64)
        mu = self.mean[self.count > 0]
        mean = float((c * mu).sum() / n)
        m2 = float(self.m2.sum() + (c * (mu - mean) ** 2).sum())
        out: dict[str, Any] = {"samples": n, "cells": int(c.size), "mean_m": mean,
                               "std_m": float(np.sqrt(m2 / (n - 1))) if n > 1 else None}
        if self.moments is not None:
            out["cell_uncertainty"] = self._uncertainty_summary()
        return out

    def _uncertainty_summary(self) -> dict[str, Any]:
        """How uncertain the cell means are, frames as clusters: what a reader needs to judge a
        heatmap's colour differences (se_m / u95_m per cell are in grid.npz)."""
        fm = self.moments
        assert fm is not None
        ok = (fm.frames > 1) & (self.count > 1)
        if not ok.any():
            return {"cells": 0, "rule": "no cell was seen by two frames: no standard error"}
        w = self.count[ok].astype(np.float64)
        return {"cells": int(ok.sum()),
                "median_frames": _weighted_median(fm.frames[ok].astype(np.float64), w),
                "median_design_effect": _weighted_median(self.design_effect[ok], w),
                "median_u95_m": _weighted_median(self.u95_m[ok], w),
                **({"median_reference_u_m": _weighted_median(self.reference_u_m[ok], w)}
                   if self.reference_u_m is not None else {}),
                "rule": "medians over the samples (cells weighted by their counts) of the cells seen by "
                        "two frames or more; frames as clusters (CR1); u95_m = t(0.975, effective frames "
                        "- 1) se_m; the design effect (se_m / (std / sqrt(count)))^2 is how many pixels "
                        "count as one independent sample"
                        + ("; a cloud reference's own uncertainty per cell (reference_u_m) is added in "
                           "quadrature: u95_m = sqrt(u95^2 + (1.96 reference_u_m)^2)"
                           if self.reference_u_m is not None else "")}

    # -- files ----------------------------------------------------------------------------------
    def save(self, path: Path, compressed: bool = True) -> Path:
        """`grid.npz` (contract 4) plus `m2_m2` so a reload merges without loss. Compressed by
        default: a study's grid is mostly empty cells (86 MB -> 12 MB with the frame moments, in the
        same time, since the disk write shrinks as much as zlib costs)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        saver = np.savez_compressed if compressed else np.savez
        arrays: dict[str, Any] = {
            "distance_edges_m": self.distance_edges_m, "inclination_edges_deg": self.inclination_edges_deg,
            "count": self.count, "mean_m": self.mean_m, "var_m2": self.var, "m2_m2": self.m2}
        if self.moments is not None:
            fm = self.moments
            arrays |= {"frames": fm.frames, "se_m": self.se_m, "u95_m": self.u95_m, "frame_n2": fm.n2,
                       "frame_n2_mean": fm.n2_mean, "frame_n2_mean2": fm.n2_mean2}
        if self.reference_u_m is not None:
            arrays["reference_u_m"] = self.reference_u_m
        saver(tmp, **arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: Path) -> Grid:
        path = Path(path)
        try:
            with np.load(path) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # cut short, not npz
            if "Object arrays" in str(exc):
                raise InputError(path, "is damaged: an array in it holds Python objects, which no grid "
                                       "file does (never loaded with pickle); rerun the study that wrote "
                                       "it") from exc
            if "pickle" in str(exc):  # numpy takes what is neither zip nor .npy for a pickle: never load one
                raise InputError(path, "is damaged: neither an .npz archive nor an .npy array (its "
                                       "beginning is overwritten, or it is another file); rerun the study "
                                       "that wrote it") from exc
            raise InputError(path, f"is damaged: not a readable grid file ({type(exc).__name__}: {exc}); "
                                   "rerun the study that wrote it") from exc
        need = ("distance_edges_m", "inclination_edges_deg", "count", "mean_m", "var_m2")
        missing = [k for k in need if k not in data]
        if missing:
            raise InputError(path, f"not a grid file: it lacks {', '.join(missing)} (missing keys)")
        count = data["count"].astype(np.int64)
        mean = np.nan_to_num(data["mean_m"].astype(np.float64))
        if "m2_m2" in data:
            m2 = data["m2_m2"].astype(np.float64)
        else:
            m2 = np.nan_to_num(data["var_m2"]) * np.maximum(count - 1, 0)
        moments = None
        if all(k in data for k in ("frames", "frame_n2", "frame_n2_mean", "frame_n2_mean2")):
            moments = FrameMoments(data["frames"].astype(np.int64), data["frame_n2"].astype(np.float64),
                                   data["frame_n2_mean"].astype(np.float64),
                                   data["frame_n2_mean2"].astype(np.float64))
        g = cls(data["distance_edges_m"].astype(np.float64),
                data["inclination_edges_deg"].astype(np.float64), count, mean, m2, moments)
        if "reference_u_m" in data and data["reference_u_m"].shape == count.shape:
            g.reference_u_m = data["reference_u_m"].astype(np.float64)
        if count.shape != g.shape:
            raise InputError(path, f"count shape {count.shape} does not match the edges {g.shape}")
        for name, e in (("distance", g.distance_edges_m), ("inclination", g.inclination_edges_deg)):
            steps = np.diff(e)
            if not np.allclose(steps, steps[0], rtol=1e-6, atol=1e-12):
                raise InputError(path, f"{name} bins are not uniform")
        return g


# -- what travels between processes: a grid as its non-empty cells ------------------------------------
@dataclass
class PackedGrid:
    """The non-empty cells of a :class:`Grid`: a partial grid of one chunk fills a few percent of
    the 1200 x 900 cells, so this is ~28 bytes per used cell instead of 26 MB dense."""

    distance_edges_m: NDArray[np.float64]
    inclination_edges_deg: NDArray[np.float64]
    cells: NDArray[np.int32]  # flat (distance, inclination) index, C order
    count: NDArray[np.int64]
    mean: NDArray[np.float64]
    m2: NDArray[np.float64]
    moments: tuple[NDArray[Any], ...] | None = None  # FrameMoments' arrays at the cells

    @property
    def nbytes(self) -> int:
        parts: list[NDArray[Any]] = [self.distance_edges_m, self.inclination_edges_deg, self.cells,
                                     self.count, self.mean, self.m2, *(self.moments or ())]
        return sum(a.nbytes for a in parts)


DISPLAY_FACTORS = (1, 2, 5, 10, 20)  # coarser display bins tried, per axis
DISPLAY_SHARE = 0.7                  # of the samples that shown cells must hold


def display_grid(grid: Grid, min_count: int) -> tuple[Grid, tuple[int, int]]:
    """The grid at the finest display bins where cells of >= min_count samples hold DISPLAY_SHARE of
    all samples (a short sequence spread over 1 million cells of 5 mm x 0.1 deg would show almost
    nothing); the factors (distance, inclination) used, the more balanced first at equal size.
    Figures only: grid.npz and every table keep the analysis bins."""
    nd, ni = grid.shape
    total = max(grid.total, 1)
    best = (grid, (1, 1))
    for f in sorted({(a, b) for a in DISPLAY_FACTORS for b in DISPLAY_FACTORS if nd % a == 0 and ni % b == 0},
                    key=lambda ab: (ab[0] * ab[1], max(ab), ab)):
        g = grid if f == (1, 1) else grid.coarsened(*f)
        if g.count[g.count >= min_count].sum() >= DISPLAY_SHARE * total:
            return g, f
        best = (g, f)
    return best


def pack_grid(grid: Grid) -> PackedGrid:
    """Keep only the cells with samples (exact: the same floats come back)."""
    cells = np.flatnonzero(grid.count).astype(np.int32)
    fm = grid.moments
    moments = None if fm is None else (fm.frames.ravel()[cells], fm.n2.ravel()[cells],
                                       fm.n2_mean.ravel()[cells], fm.n2_mean2.ravel()[cells])
    return PackedGrid(grid.distance_edges_m, grid.inclination_edges_deg, cells,
                      grid.count.ravel()[cells], grid.mean.ravel()[cells], grid.m2.ravel()[cells], moments)


def unpack_grid(packed: PackedGrid) -> Grid:
    grid = Grid.with_edges(packed.distance_edges_m, packed.inclination_edges_deg)
    grid.count.ravel()[packed.cells] = packed.count
    grid.mean.ravel()[packed.cells] = packed.mean
    grid.m2.ravel()[packed.cells] = packed.m2
    if packed.moments is not None:
        fm = grid.moments = FrameMoments.zeros(grid.shape)
        for a, v in zip((fm.frames, fm.n2, fm.n2_mean, fm.n2_mean2), packed.moments, strict=True):
            a.ravel()[packed.cells] = v
    return grid
