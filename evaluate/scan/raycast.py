"""Ray casting of posed depth frames against the reference mesh, with the post-processing fused.

Why fused: Open3D casts 6-12 M rays/s on two cores; the per-pixel work around it (rays out,
reference z-depth, inclination from the hit triangle's normal, error, Welford binning) must cost
less than that, so it runs as one numba pass over the frame instead of a dozen numpy temporaries.

Conventions (DESIGN §2): rays go through integer pixel centres (librealsense, not Open3D's +0.5
helpers), their camera-frame direction has z = 1 so Open3D's t_hit is the reference z-depth in the
units of the reference; inclination is the angle between ray and triangle normal folded to
[0, 90] degrees; depth error = measured - reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.grid import _FAST, FrameMoments, Grid, bin_index
from depthstation.core.lazy_open3d import open3d
from depthstation.core.raster import fill_rays

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _inclination_deg(nx: float, ny: float, nz: float, dx: float, dy: float, dz: float) -> float:
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    dd = np.sqrt(dx * dx + dy * dy + dz * dz)
    if nn == 0.0 or dd == 0.0:
        return np.nan
    c = abs(nx * dx + ny * dy + nz * dz) / (nn * dd)
    c = min(c, 1.0)
    return np.degrees(np.arccos(c))


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _welford_cell(cells: Any, k: int, j: int, x: float) -> None:
    """`core.grid.welford_add` on a cell-major (count, mean, M2) array: the same operations."""
    n = cells[k, j, 0] + 1.0
    cells[k, j, 0] = n
    delta = x - cells[k, j, 1]
    mu = cells[k, j, 1] + delta / n
    cells[k, j, 1] = mu
    cells[k, j, 2] += delta * (x - mu)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _fused_bin(t_hit: Any, normals: Any, rays: Any, inv_norm: Any, depth: Any, depth_scale: float,
               cells: Any, fcells: Any, per_frame: bool, d_lo: float, d_step: float, nd: int,
               cos_edges: Any, i_lo: float, i_step: float, ni: int, stats: Any, kk: Any, jj: Any, ee: Any,
               tk: Any, tj: Any, te: Any, start: Any, jstart: Any) -> None:
    """One frame: reference z, inclination, error, Welford into the cells (and the frame's);
    counts into stats.

    stats: [pixels, no_depth, no_hit, evaluated (hit and depth), binned]. inv_norm: 1/|ray| per
    pixel (rotation keeps it, so it is computed once per camera). Why in passes: a frame's
    pixels land on cells all over the grid, and Welford updates in pixel order stalled on cache
    misses. The binned pixels are sorted by cell (a stable two-pass counting sort, inclination bin
    then distance bin, so every cell still sees its pixels in pixel order: the same floats) and
    then added cell after cell, walking the grid's memory forwards. kk, jj, ee, tk, tj, te (one
    per pixel), start (distance bins + 1) and jstart (inclination bins + 1) are scratch.
    """
    n = depth.shape[0]
    no_depth = 0
    no_hit = 0
    evaluated = 0
    binned = 0
    for k in range(nd + 1):
        start[k] = 0
    for j in range(ni + 1):
        jstart[j] = 0
    for i in range(n):
        kk[i] = -1
        raw = depth[i]
        hit = np.isfinite(t_hit[i])
        if raw == 0:
            no_depth += 1
        if not hit:
            no_hit += 1
        if raw == 0 or not hit:
            continue
        evaluated += 1
        z_ref = t_hit[i]
        k = bin_index(z_ref, d_lo, d_step, nd)
        if k < 0:
            continue
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        if nn == 0.0:
            continue
        c = abs(nx * rays[i, 3] + ny * rays[i, 4] + nz * rays[i, 5]) * inv_norm[i] / nn
        j = _inclination_bin(c, cos_edges, i_lo, i_step, ni)
        if j < 0:
            continue
        kk[i] = k
        jj[i] = j
        ee[i] = raw * depth_scale - z_ref
        start[k + 1] += 1
        jstart[j + 1] += 1
        binned += 1
    for j in range(ni):
        jstart[j + 1] += jstart[j]
    for k in range(nd):
        start[k + 1] += start[k]
    for i in range(n):  # by inclination bin (values move with the key: the next pass reads in order)
        if kk[i] >= 0:
            j = jj[i]
            q = jstart[j]
            jstart[j] = q + 1
            tk[q] = kk[i]
            tj[q] = j
            te[q] = ee[i]
    for p in range(binned):  # then by distance bin, into kk, jj, ee
        k = tk[p]
        q = start[k]
        start[k] = q + 1
        kk[q] = k
        jj[q] = tj[p]
        ee[q] = te[p]
    for q in range(binned):
        _welford_cell(cells, kk[q], jj[q], ee[q])
        if per_frame:
            _welford_cell(fcells, kk[q], jj[q], ee[q])
    stats[0] += n
    stats[1] += no_depth
    stats[2] += no_hit
    stats[3] += evaluated
    stats[4] += binned


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _add_frame_moments(kk: Any, jj: Any, ee: Any, binned: int, frames: Any, n2: Any, n2_mean: Any,
                       n2_mean2: Any) -> None:
    """One frame's cell means into the frame-clustered moments (core.grid.FrameMoments).

    kk, jj, ee hold the frame's `binned` pixels sorted by cell (what `_fused_bin` leaves), so a
    cell's pixels are one run: its n_f and mean m_f come without another pass over the grid.
    """
    q = 0
    while q < binned:
        k = kk[q]
        j = jj[q]
        s = 0.0
        r = q
        while r < binned and kk[r] == k and jj[r] == j:
            s += ee[r]
            r += 1
        n = float(r - q)
        m = s / n
        w = n * n
        frames[k, j] += 1
        n2[k, j] += w
        n2_mean[k, j] += w * m
        n2_mean2[k, j] += w * m * m
        q = r


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _frame_images(t_hit: Any, normals: Any, rays: Any, depth: Any, depth_scale: float,
                  z_ref: Any, inc: Any, z_meas: Any) -> None:
    for i in range(depth.shape[0]):
        z_meas[i] = depth[i] * depth_scale if depth[i] != 0 else np.nan
        if np.isfinite(t_hit[i]):
            z_ref[i] = t_hit[i]
            inc[i] = _inclination_deg(normals[i, 0], normals[i, 1], normals[i, 2],
                                      rays[i, 3], rays[i, 4], rays[i, 5])
        else:
            z_ref[i] = np.nan
            inc[i] = np.nan


def cos_edges(grid: Grid) -> NDArray[np.float64]:
    """Cosines of the inclination edges (decreasing), cached on the grid's edge array."""
    e = grid.inclination_edges_deg
    key = (e.size, float(e[0]), float(e[-1]))
    hit = _COS_CACHE.get(key)
    if hit is None:
        hit = np.cos(np.radians(e))
        _COS_CACHE[key] = hit
    return hit


_COS_CACHE: dict[tuple[int, float, float], NDArray[np.float64]] = {}

STAT_NAMES = ("pixels", "no_depth", "no_hit", "evaluated", "binned")


@dataclass
class FrameImages:
    """Per-pixel maps of one frame (paper Fig. 8), HxW float32, NaN where undefined."""

    measured_m: F32
    reference_m: F32
    inclination_deg: F32

    @property
    def error_m(self) -> F32:
        return self.measured_m - self.reference_m


@dataclass
class CellAccumulator:
    """Welford count, mean and M2 of a grid's cells side by side (cell-major, count as float).

    Why: the per-pixel pass lands on cells of a 26 MB grid in an order no cache predicts; with
    the three numbers of a cell in one cache line an update costs one miss instead of three.
    The operations are those of `core.grid.welford_add` in the same order, so `to_grid` gives
    the grid the separate arrays would hold, bit for bit.
    """

    grid: Grid  # the bins (its arrays are not used)
    cells: F64  # (distance bins, inclination bins, 3)

    @classmethod
    def for_grid(cls, grid: Grid) -> CellAccumulator:
        return cls(grid, np.zeros((*grid.count.shape, 3)))

    def reset(self) -> None:
        self.cells[:] = 0.0

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

    def __init__(self, intr: Intrinsics) -> None:
        self.intr = intr
        self.dirs = pixel_rays(intr).reshape(-1, 3)
        self.inv_norm = (1.0 / np.linalg.norm(self.dirs.astype(np.float64), axis=1)).astype(np.float32)
        self.rays = np.empty((self.dirs.shape[0], 6), dtype=np.float32)
        self._scratch: tuple[NDArray[Any], ...] | None = None

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """(t_hit (inf = miss), unit normals) of every pixel for a camera-to-reference pose;
        `self.rays` holds the frame's rays afterwards."""
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """What result.json records about the renderer."""
        return {"renderer": self.name}

    def bin_frame(self, pose: F64, depth: NDArray[Any], depth_scale: float, cells: CellAccumulator,
                  stats: NDArray[np.int64], frame_cells: CellAccumulator | None = None,
                  moments: FrameMoments | None = None) -> None:
        """Render one frame and Welford its errors into `cells` (and `frame_cells`); the frame's
        cell means into `moments` (frames as clusters, for the standard error of a cell mean)."""
        t_hit, normals = self.cast(pose)
        fc = frame_cells if frame_cells is not None else cells
        d_lo, d_step, nd, i_lo, i_step, ni = cells.grid.bins
        n = self.dirs.shape[0]
        sc = self._scratch
        if sc is None or sc[6].shape[0] != nd + 1 or sc[7].shape[0] != ni + 1:
            sc = (np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n), np.empty(n, np.int32),
                  np.empty(n, np.int32), np.empty(n), np.empty(nd + 1, np.int64), np.empty(ni + 1, np.int64))
            self._scratch = sc
        kk, jj, ee, tk, tj, te, start, jstart = sc
        before = int(stats[4])
        _fused_bin(t_hit, normals, self.rays, self.inv_norm, np.ascontiguousarray(depth).ravel(),
                   float(depth_scale), cells.cells, fc.cells, frame_cells is not None, d_lo, d_step, nd,
                   cos_edges(cells.grid), i_lo, i_step, ni, stats, kk, jj, ee, tk, tj, te, start, jstart)
        if moments is not None:
            _add_frame_moments(kk, jj, ee, int(stats[4]) - before, moments.frames, moments.n2,
                               moments.n2_mean, moments.n2_mean2)

    def images(self, pose: F64, depth: NDArray[Any], depth_scale: float) -> FrameImages:
        """The per-pixel maps of one frame (for figures and tests, not the hot loop)."""
        t_hit, normals = self.cast(pose)
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
            mesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)
        self.nthreads = int(nthreads)
        self._rays_t = o3d.core.Tensor.from_numpy(self.rays)

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """Cast all pixels of a camera with camera-to-reference pose (4x4 rigid); (t_hit, normals)."""
        pose = np.asarray(pose, dtype=np.float64)
        fill_rays(self.rays, pose[:3, 3].copy(), pose[:3, :3].copy(), self.dirs)
        ans = self.scene.cast_rays(self._rays_t, nthreads=self.nthreads)
        return ans["t_hit"].numpy(), ans["primitive_normals"].numpy()
