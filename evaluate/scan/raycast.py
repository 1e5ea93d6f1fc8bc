"""Ray casting of posed depth frames against the reference mesh, with the post-processing fused.

Why fused: Open3D casts 6-12 M rays/s on two cores; the per-pixel work around it (rays out,
reference z-depth, inclination from the hit triangle's normal, error, binning) must cost
less than that, so it runs as one numba pass over the frame instead of a dozen numpy temporaries.

Conventions (DESIGN §2): rays go through integer pixel centres (librealsense, not Open3D's +0.5
helpers), their camera-frame direction has z = 1 so Open3D's t_hit is the reference z-depth in the
units of the reference; inclination is the angle between ray and triangle normal folded to
[0, 90] degrees; depth error = measured - reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.grid import EXACT_MATH, FrameMoments, Grid, bin_index
from depthstation.core.lazy_open3d import open3d
from depthstation.core.raster import fill_rays, pinhole_axes
from depthstation.evaluate.scan.hit_refine import TrianglePlanes, refine_depths

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _inclination_deg(nx: float, ny: float, nz: float, dx: float, dy: float, dz: float) -> float:
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    dd = np.sqrt(dx * dx + dy * dy + dz * dz)
    if nn == 0.0 or dd == 0.0:
        return np.nan
    c = abs(nx * dx + ny * dy + nz * dz) / (nn * dd)
    c = min(c, 1.0)
    return np.degrees(np.arccos(c))


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _inclination_bin(c: float, cos_edges: Any, i_lo: float, i_step: float, ni: int) -> int:
    """Inclination bin of cos(inclination) = c without an exact arccos per pixel.

    Why: arccos dominated the fused pass. A polynomial arccos (Abramowitz & Stegun 4.4.45,
    |error| < 7e-5 rad) picks the bin, then comparisons with the exact cosines of the bin edges
    correct it, so the bin is the one an exact arccos would give.
    """
    if c > cos_edges[0] or c < cos_edges[ni]:
        if c > 1.0 and cos_edges[0] >= 1.0:  # rounding above 1 means 0 degrees
            c = 1.0
        else:
            return -1
    x = min(c, 1.0)
    a = np.sqrt(1.0 - x) * (1.5707288 + x * (-0.2121144 + x * (0.0742610 - 0.0187293 * x)))
    j = int(np.floor((np.degrees(a) - i_lo) / i_step))
    j = min(max(j, 0), ni - 1)
    while j > 0 and c > cos_edges[j]:
        j -= 1
    while j < ni - 1 and c <= cos_edges[j + 1]:
        j += 1
    return j


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _world_dir(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float, r20: float, r21: float,
               r22: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """`core.raster.fill_rays`' direction of a camera-frame ray (float64 products, one rounding to
    float32 per component). Fast maths off (`EXACT_MATH`), set here too: numba compiles a callee
    with its caller's fast-maths flags unless the callee sets its own, and contracted into an FMA
    the product moves the direction by an ulp and a pixel near a bin edge to the next bin now and
    then, on CPUs with FMA only. Scalars only: an array argument costs reference counting per call."""
    return (float(np.float32(r00 * x + r01 * y + r02 * z)), float(np.float32(r10 * x + r11 * y + r12 * z)),
            float(np.float32(r20 * x + r21 * y + r22 * z)))


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _axis_products(rot: Any, xs: Any, ys: Any, cols: Any, rows: Any) -> None:
    """A pinhole's ray products per column (rot[:, 0] * x) and per row (rot[:, 1] * y): `_world_dir`
    of pixel (u, v) is then two sums per component, the same operations in the same order (z = 1,
    so rot[:, 2] * z is rot[:, 2]). Fast maths off, as `_world_dir`."""
    for u in range(xs.shape[0]):
        cols[u, 0] = rot[0, 0] * xs[u]
        cols[u, 1] = rot[1, 0] * xs[u]
        cols[u, 2] = rot[2, 0] * xs[u]
    for v in range(ys.shape[0]):
        rows[v, 0] = rot[0, 1] * ys[v]
        rows[v, 1] = rot[1, 1] * ys[v]
        rows[v, 2] = rot[2, 1] * ys[v]


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _dir_sum(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float, r02: float, r12: float,
             r22: float) -> tuple[float, float, float]:
    """`_world_dir` of a pinhole ray from its column's (a) and row's (b) products, summed in that
    order; fast maths off, as `_world_dir` (with reassociation allowed LLVM had summed them as
    (b + r02) + a). Not `core.raster`'s `_dir_sum`: that one is inlined into its caller and takes
    the caller's flags."""
    return (float(np.float32(a0 + b0 + r02)), float(np.float32(a1 + b1 + r12)),
            float(np.float32(a2 + b2 + r22)))


@cache
def pixel_bins_kernel(pinhole: bool) -> Any:
    """`_pixel_bins` compiled for pinhole rays (built from per-column and per-row products, without
    reading a 12-byte ray per pixel: the study step 0.97-0.99x, docs/scan-study.md, Speed) or for
    per-pixel rays (a lens); the choice a constant, so the other path folds away."""

    @numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
    def _pixel_bins(t_hit: Any, index: Any, normals: Any, dirs: Any, cols: Any, rows: Any, rot: Any,
                    inv_norm: Any, depth: Any, depth_scale: float, d_lo: float, d_step: float, nd: int,
                    cos_edges: Any, guess: Any, ni: int, kk: Any, sj: Any, se: Any, start: Any,
                    stats: Any) -> None:
        """Per pixel: reference z, inclination, error and their cell, put in order of distance bin.

        The normal of pixel i is normals[index[i]] (a per-pixel array and 0, 1, 2, ... or a
        renderer's per-triangle table and the hit triangles). Its ray is dirs[i] or, in the pinhole
        kernel, built from its column's and row's products (cols, rows: `_axis_products`). Two
        passes: the distance bin of every pixel with depth and a hit (kk, -1 = none) and their count
        per bin, then, in pixel order, inclination bin (sj, -1 = out of the grid) and error (se)
        each at its place in its distance bin's run (a counting sort without a scatter pass of its
        own). After it, start[k] is the end of bin k's run and its start start[k - 1] (0 for
        k = 0)."""
        n = depth.shape[0]
        no_depth = 0
        no_hit = 0
        evaluated = 0
        binned = 0
        unmeasured = 0
        for k in range(nd + 1):
            start[k] = 0
        for i in range(n):
            raw = depth[i]
            hit = np.isfinite(t_hit[i])
            if raw == 0:
                no_depth += 1
            if not hit:
                no_hit += 1
            kk[i] = -1
            if raw == 0 or not hit:
                continue
            evaluated += 1
            k = bin_index(t_hit[i], d_lo, d_step, nd)
            kk[i] = k
            if k >= 0:
                start[k + 1] += 1
        for k in range(nd):
            start[k + 1] += start[k]
        r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
        r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
        r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
        w = cols.shape[0] if pinhole else max(n, 1)
        b0 = b1 = b2 = 0.0
        for v in range(n // w):
            if pinhole:  # this row's products (per-pixel rays: one pass over all pixels)
                b0, b1, b2 = rows[v, 0], rows[v, 1], rows[v, 2]
            for u in range(w):
                i = v * w + u
                k = kk[i]
                if k < 0:
                    continue
                z_ref = t_hit[i]
                q = start[k]
                start[k] = q + 1
                se[q] = depth[i] * depth_scale - z_ref
                sj[q] = -1
                m = index[i]
                nx, ny, nz = normals[m, 0], normals[m, 1], normals[m, 2]
                nn = np.sqrt(nx * nx + ny * ny + nz * nz)
                if not nn > 0.0:  # NaN: surface nobody measured (the renderer's mask); 0: degenerate
                    unmeasured += nn != nn
                    continue
                if pinhole:
                    dx, dy, dz = _dir_sum(cols[u, 0], cols[u, 1], cols[u, 2], b0, b1, b2, r02, r12, r22)
                else:
                    dx, dy, dz = _world_dir(r00, r01, r02, r10, r11, r12, r20, r21, r22, dirs[i, 0],
                                            dirs[i, 1], dirs[i, 2])
                c = abs(nx * dx + ny * dy + nz * dz) * inv_norm[i] / nn
                # the inclination bin as `_inclination_bin`, its first guess from `inclination_guess`'s
                # table over c instead of a polynomial arccos. A cell holding at most one edge (all
                # cells above ~0.6 deg at 0.1 deg bins) settles the bin with one comparison, without a
                # branch (0.94x the pass's time against walking the edges from the guess); a cell with
                # more is stored as -1 - bin and walks the edges. NaN has no bin. Written out here: as
                # a call (even inlined by numba) it took 2.3x as long, the arrays' reference counts
                # per pixel.
                if not (c <= cos_edges[0] and c >= cos_edges[ni]):
                    if c > 1.0 and cos_edges[0] >= 1.0:  # rounding above 1 means 0 degrees
                        c = 1.0
                    else:
                        continue
                g = np.int64(guess[int(min(c, 1.0) * (guess.shape[0] - 1))])
                if g >= 0:
                    j = g - np.int64(c > cos_edges[g])
                else:
                    j = -1 - g
                    while j > 0 and c > cos_edges[j]:
                        j -= 1
                    while j < ni - 1 and c <= cos_edges[j + 1]:
                        j += 1
                sj[q] = j
                binned += 1
        stats[0] += n
        stats[1] += no_depth
        stats[2] += no_hit
        stats[3] += evaluated
        stats[4] += binned
        stats[5] += unmeasured

    return _pixel_bins


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _merge_cell(cells: Any, k: int, j: int, nb: float, mb: float, m2b: float) -> None:
    """Chan's merge of a frame's (count, mean, M2) in one cell into a cell-major accumulator."""
    na = cells[k, j, 0]
    if na == 0.0:
        cells[k, j, 0] = nb
        cells[k, j, 1] = mb
        cells[k, j, 2] = m2b
        return
    n = na + nb
    delta = mb - cells[k, j, 1]
    cells[k, j, 0] = n
    cells[k, j, 1] += delta * nb / n
    cells[k, j, 2] += m2b + delta * delta * (na * nb / n)


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _fold_frame(nd: int, ni: int, start: Any, sj: Any, se: Any, row: Any, cells: Any, fcells: Any,
                per_frame: bool, moments: bool, frames: Any, n2: Any, n2_mean: Any, n2_mean2: Any) -> None:
    """A frame's binned pixels (`_pixel_bins`' runs) into the cells, once per cell it touched.

    Why: a frame puts ~2 pixels in each cell it touches, all over a 26 MB grid. Within a distance
    bin's run the pixels are summed per inclination bin in `row` (count, sum and sum of squares
    about a shift, ~20 kB: cache resident), then each touched cell gets one Chan merge of the
    frame's (count, mean, M2) and its frame moment, walking the grid's row forwards. The shift (the
    run's first error: a frame's errors at one distance) keeps the sums of squares exact enough.
    """
    lo = 0
    for k in range(nd):
        hi = start[k]  # after the scatter start[k] is the end of bin k's run
        if hi == lo:
            continue
        shift = se[lo]  # a frame's errors at one distance: sums about one of them stay exact
        jlo = ni
        jhi = 0
        for q in range(lo, hi):
            j = sj[q]
            if j < 0:
                continue
            d = se[q] - shift
            jlo = min(jlo, j)
            jhi = max(jhi, j)
            row[j, 0] += 1.0
            row[j, 1] += d
            row[j, 2] += d * d
        for j in range(jlo, jhi + 1):  # in order: the grid's row is read forwards
            nb = row[j, 0]
            if nb == 0.0:
                continue
            s = row[j, 1]
            mb = shift + s / nb
            m2b = max(row[j, 2] - s * s / nb, 0.0)
            row[j, 0] = 0.0
            row[j, 1] = 0.0
            row[j, 2] = 0.0
            _merge_cell(cells, k, j, nb, mb, m2b)
            if per_frame:
                _merge_cell(fcells, k, j, nb, mb, m2b)
            if moments:
                w = nb * nb
                frames[k, j] += 1
                n2[k, j] += w
                n2_mean[k, j] += w * mb
                n2_mean2[k, j] += w * mb * mb
        lo = hi


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _frame_images(t_hit: Any, normals: Any, rays: Any, depth: Any, depth_scale: float,
                  z_ref: Any, inc: Any, z_meas: Any) -> None:
    for i in range(depth.shape[0]):
        z_meas[i] = depth[i] * depth_scale if depth[i] != 0 else np.nan
        if np.isfinite(t_hit[i]):  # a NaN normal (unmeasured surface): NaN inclination
            z_ref[i] = t_hit[i]
            inc[i] = _inclination_deg(normals[i, 0], normals[i, 1], normals[i, 2],
                                      rays[i, 3], rays[i, 4], rays[i, 5])
        else:
            z_ref[i] = np.nan
            inc[i] = np.nan


GUESS_CELLS = 65536  # table cells over cos(inclination) in [0, 1]: 0.1 deg bins hold >= 1 above 0.5 deg


def inclination_guess(cos_e: NDArray[np.float64]) -> NDArray[np.int16] | NDArray[np.int32]:
    """Per table cell q (c in [q, q + 1) / GUESS_CELLS) the inclination bin g of its lowest c, the
    largest bin of the cell. Where the cell holds at most one edge, c's bin is g or, past edge g,
    g - 1 (one comparison in `_pixel_bins`); elsewhere (several edges in the cell, or g clipped to
    the grid) -1 - g, for the walk along the exact edges."""
    key = (cos_e.size, float(cos_e[0]), float(cos_e[-1]))
    hit = _GUESS_CACHE.get(key)
    if hit is None:
        ni = cos_e.size - 1
        c = np.arange(GUESS_CELLS + 1) / GUESS_CELLS
        raw = np.searchsorted(-cos_e, -c, side="right") - 1  # largest edge index e with cos_e[e] >= c
        j = np.clip(raw, 0, max(ni - 1, 0))
        c_next = np.append(c[1:], np.inf)  # the cell's upper end (open)
        one_step = (j == 0) | (cos_e[np.maximum(j - 1, 0)] >= c_next)  # edge j - 1 above the cell
        fast = (raw == j) & one_step
        j = np.where(fast, j, -1 - j)
        hit = j.astype(np.int16 if ni < 2**15 else np.int32)
        _GUESS_CACHE[key] = hit
    return hit


def cos_edges(grid: Grid) -> NDArray[np.float64]:
    """Cosines of the inclination edges (decreasing), cached on the grid's edge array.

    In long double, rounded once to float64: the C library's double cos (and numpy's) picks an
    FMA or an AVX-512 variant by the CPU and rounds the last bit differently now and then, which
    would move a bin edge, and a pixel on it, from one CPU to another; the long double cos has one
    implementation (where long double is double, e.g. on Windows, the plain cos is used)."""
    e = grid.inclination_edges_deg
    key = (e.size, float(e[0]), float(e[-1]))
    hit = _COS_CACHE.get(key)
    if hit is None:
        hit = np.cos(np.radians(e.astype(np.longdouble))).astype(np.float64)
        _COS_CACHE[key] = hit
    return hit


_COS_CACHE: dict[tuple[int, float, float], NDArray[np.float64]] = {}
_GUESS_CACHE: dict[tuple[int, float, float], Any] = {}

# unmeasured_surface: pixels within the grid's distance range whose hit triangle is reference
# surface nobody scanned (`reference.unmeasured_triangles`), left out of the grid
STAT_NAMES = ("pixels", "no_depth", "no_hit", "evaluated", "binned", "unmeasured_surface")
_NO_MOMENTS = FrameMoments.zeros((1, 1))  # a stand-in the pass does not touch (moments not kept)


@dataclass
class FrameImages:
    """Per-pixel maps of one frame (paper Fig. 8), HxW float32, NaN where undefined: the reference
    where the ray meets no surface, the inclination also where the surface met was not scanned
    (`FrameRenderer.mark_unmeasured`: those pixels are not in the grid)."""

    measured_m: F32
    reference_m: F32
    inclination_deg: F32

    @property
    def error_m(self) -> F32:
        return self.measured_m - self.reference_m

    @property
    def unmeasured(self) -> NDArray[np.bool_]:
        """Pixels whose ray meets reference surface nobody scanned (left out of the grid)."""
        return np.asarray(np.isfinite(self.reference_m) & np.isnan(self.inclination_deg))


@numba.njit(cache=True, nogil=True)
def _split_cells(cells: Any, count: Any, mean: Any, m2: Any) -> None:
    """A cell-major accumulator into a grid's three arrays (what `to_grid` copies), zeroing it."""
    nd, ni = count.shape
    for k in range(nd):
        for j in range(ni):
            count[k, j] = np.int64(cells[k, j, 0])
            mean[k, j] = cells[k, j, 1]
            m2[k, j] = cells[k, j, 2]
            cells[k, j, 0] = 0.0
            cells[k, j, 1] = 0.0
            cells[k, j, 2] = 0.0


@dataclass
class CellAccumulator:
    """Count, mean and M2 of a grid's cells side by side (cell-major, count as float).

    Why: a frame touches ~130 k cells of a 26 MB grid; with the three numbers of a cell in one
    cache line a cell's update reads one line instead of three. The pass merges each frame into
    its cells with Chan's formula (one merge per touched cell, `_fold_frame`), so the cells equal
    a per-pixel Welford of the same samples up to float rounding (~1e-17 m in a mean).
    """

    grid: Grid  # the bins (its arrays are not used)
    cells: F64  # (distance bins, inclination bins, 3)

    @classmethod
    def for_grid(cls, grid: Grid) -> CellAccumulator:
        return cls(grid, np.zeros((*grid.count.shape, 3)))

    def reset(self) -> None:
        self.cells[:] = 0.0

    def take_grid(self, grid: Grid) -> Grid:
        """`to_grid` into the arrays of `grid` (same bins, reused: no fresh pages, one pass), leaving
        this accumulator zeroed for the next chunk; returns `grid`."""
        _split_cells(self.cells, grid.count, grid.mean, grid.m2)
        return grid

    def to_grid(self) -> Grid:
        g = self.grid.like()
        g.count[:] = self.cells[..., 0].astype(np.int64)
        g.mean[:] = self.cells[..., 1]
        g.m2[:] = self.cells[..., 2]
        return g


class FrameRenderer:
    """Reference z-depth and hit normal of every pixel centre of a posed frame, and the fused
    per-pixel pass on top (`bin_frame`, `images`). Subclasses fill `cast`."""

    name = "renderer"
    n_triangles = 0  # of the mesh (the ids of `cast_indexed` and of `mark_unmeasured`)

    def __init__(self, intr: Intrinsics) -> None:
        self.intr = intr
        self.dirs = pixel_rays(intr).reshape(-1, 3)
        self.inv_norm = (1.0 / np.linalg.norm(self.dirs.astype(np.float64), axis=1)).astype(np.float32)
        # a pinhole's rays from per-column and per-row products (`_axis_products`); a lens's per pixel
        self._axes = pinhole_axes(intr) if not intr.has_distortion else None
        w, h = (intr.width, intr.height) if self._axes is not None else (0, 0)
        self._cols, self._rows = np.empty((w, 3)), np.empty((h, 3))
        self.rays = np.empty((self.dirs.shape[0], 6), dtype=np.float32)
        self._scratch: tuple[NDArray[Any], ...] | None = None
        self._identity = np.zeros(0, np.int32)
        self.unmeasured: NDArray[np.bool_] | None = None
        self._unmeasured_ids: NDArray[np.int64] | None = None
        # the mesh's planes in float64, by the index `cast_indexed` hands the pass (None: the
        # renderer's float32 hits are used as they are)
        self.planes: TrianglePlanes | None = None

    def mark_unmeasured(self, mask: NDArray[np.bool_] | None) -> None:
        """Triangles of reference surface nobody scanned (`reference.unmeasured_triangles`, by the
        mesh's triangle id): a hit on one keeps its depth (it hides what lies behind it) and gets a
        NaN normal, so the pass leaves the pixel out of the grid and counts it."""
        self.unmeasured = None if mask is None or not np.any(mask) else np.asarray(mask, dtype=bool)
        self._unmeasured_ids = None if self.unmeasured is None else np.flatnonzero(self.unmeasured)

    def _blank_unmeasured(self, ids: NDArray[Any], normals: NDArray[np.float32]) -> None:
        """Per-pixel normals (hit triangle `ids`, negative or out of range = miss) to NaN where
        the hit triangle is unmeasured."""
        if self.unmeasured is None:
            return
        ids = np.asarray(ids).reshape(-1).astype(np.int64)
        on = (ids >= 0) & (ids < self.unmeasured.shape[0])
        on[on] = self.unmeasured[ids[on]]
        normals.reshape(-1, 3)[on] = np.nan

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """(t_hit (inf = miss), unit normals) of every pixel for a camera-to-reference pose (the rays
        are `fill_rays(self.rays, ...)`'s; a ray caster leaves them in `self.rays`, the rasteriser
        does not need them)."""
        raise NotImplementedError

    def cast_indexed(self, pose: F64) -> tuple[F32, NDArray[np.int32], F32]:
        """`cast` for the per-pixel pass: (t_hit, index, table), pixel i's normal table[index[i]]
        (here the pixels' own; the rasteriser hands its per-triangle table and the hit triangles)."""
        t_hit, normals = self.cast(pose)
        n = t_hit.shape[0]
        if self._identity.shape[0] != n:
            self._identity = np.arange(n, dtype=np.int32)
        return t_hit, self._identity, normals

    def describe(self) -> dict[str, Any]:
        """What result.json records about the renderer."""
        return {"renderer": self.name}

    def bin_frame(self, pose: F64, depth: NDArray[Any], depth_scale: float, cells: CellAccumulator,
                  stats: NDArray[np.int64], frame_cells: CellAccumulator | None = None,
                  moments: FrameMoments | None = None) -> None:
        """Render one frame and merge its errors into `cells` (and `frame_cells`), one Chan merge per
        cell it touches; the frame's cell means into `moments` (frames as clusters, for the standard
        error of a cell mean)."""
        t_hit, index, normals = self.cast_indexed(pose)
        if self.planes is not None:  # the same triangles, depth in float64 (`hit_refine`)
            refine_depths(t_hit, index, self.planes, self.dirs, pose)
        fc = frame_cells if frame_cells is not None else cells
        d_lo, d_step, nd, _, _, ni = cells.grid.bins
        n = self.dirs.shape[0]
        sc = self._scratch
        if sc is None or sc[3].shape[0] != nd + 1 or sc[4].shape[0] != ni:
            sc = (np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n), np.empty(nd + 1, np.int64),
                  np.zeros((ni, 4)))
            self._scratch = sc
        kk, sj, se, start, row = sc
        rot = np.ascontiguousarray(np.asarray(pose, dtype=np.float64)[:3, :3])
        flat = np.ascontiguousarray(depth).ravel()
        if flat.shape[0] != n:  # the kernels walk the intrinsics' pixels: others would go unread
            raise ValueError(f"depth of {flat.shape[0]} pixels for a "
                             f"{self.intr.width}x{self.intr.height} view")
        ce = cos_edges(cells.grid)
        if self._axes is not None:
            _axis_products(rot, *self._axes, self._cols, self._rows)
        pixel_bins_kernel(self._axes is not None)(
            t_hit, index, normals, self.dirs, self._cols, self._rows, rot, self.inv_norm, flat,
            float(depth_scale), d_lo, d_step, nd, ce, inclination_guess(ce), ni, kk, sj, se, start, stats)
        fm = moments if moments is not None else _NO_MOMENTS
        _fold_frame(nd, ni, start, sj, se, row, cells.cells, fc.cells, frame_cells is not None,
                    moments is not None, fm.frames, fm.n2, fm.n2_mean, fm.n2_mean2)

    def images(self, pose: F64, depth: NDArray[Any], depth_scale: float) -> FrameImages:
        """The per-pixel maps of one frame (for figures and tests, not the hot loop)."""
        t_hit, normals = self.cast(pose)
        pose = np.asarray(pose, dtype=np.float64)
        fill_rays(self.rays, pose[:3, 3].copy(), pose[:3, :3].copy(), self.dirs)
        n = self.dirs.shape[0]
        z_ref = np.empty(n, np.float32)
        inc = np.empty(n, np.float32)
        z_meas = np.empty(n, np.float32)
        _frame_images(t_hit, normals, self.rays, np.ascontiguousarray(depth).ravel(), float(depth_scale),
                      z_ref, inc, z_meas)
        shape = (self.intr.height, self.intr.width)
        return FrameImages(z_meas.reshape(shape), z_ref.reshape(shape), inc.reshape(shape))


class MeshCaster(FrameRenderer):
    """Open3D ray casting (`RaycastingScene.cast_rays`) of every pixel: the reference renderer."""

    name = "raycast"

    def __init__(self, mesh: Any, intr: Intrinsics, nthreads: int = 0) -> None:
        super().__init__(intr)
        o3d = open3d()

        if isinstance(mesh, (str, Path)):
            mesh = o3d.io.read_triangle_mesh(str(mesh))
        if isinstance(mesh, o3d.geometry.TriangleMesh):
            self.planes = TrianglePlanes(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
            mesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
        else:
            self.planes = TrianglePlanes(mesh.vertex.positions.numpy(), mesh.triangle.indices.numpy())
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)
        self.n_triangles = int(mesh.triangle.indices.shape[0])
        self.nthreads = int(nthreads)
        self._rays_t = o3d.core.Tensor.from_numpy(self.rays)
        self._hit_ids = np.zeros(0, np.int32)
        self._table = self.planes.table

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """Cast all pixels of a camera with camera-to-reference pose (4x4 rigid); (t_hit, normals)."""
        pose = np.asarray(pose, dtype=np.float64)
        fill_rays(self.rays, pose[:3, 3].copy(), pose[:3, :3].copy(), self.dirs)
        ans = self.scene.cast_rays(self._rays_t, nthreads=self.nthreads)
        normals = ans["primitive_normals"].numpy()
        ids = ans["primitive_ids"].numpy()
        self._blank_unmeasured(ids, normals)
        hit = ids < self.n_triangles  # a miss is Open3D's INVALID_ID (2^32 - 1)
        self._hit_ids = np.where(hit, ids, -1).astype(np.int32)
        return ans["t_hit"].numpy(), normals

    def cast_indexed(self, pose: F64) -> tuple[F32, NDArray[np.int32], F32]:
        """(t_hit, hit triangle ids, the per-triangle normals from float64 vertices): the table the
        rasteriser hands too, so both renderers bin alike in any frame (`hit_refine`)."""
        t_hit, _ = self.cast(pose)
        return t_hit, self._hit_ids, self._table

    def mark_unmeasured(self, mask: NDArray[np.bool_] | None) -> None:
        super().mark_unmeasured(mask)
        if self.planes is not None:
            self._table = self.planes.with_unmeasured(self._unmeasured_ids)
