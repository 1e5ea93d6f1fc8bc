"""A cloud reference measured against its points: per triangle of the cloud's Poisson mesh, a plane
fitted to the scanned points around it, used only where the points support it.

Why: the Poisson mesh of a sparse TLS scan with holes is a guess between and across the points; a
grid against it is partly the meshing's error (a 1074 x 345 scan of a room: mean -12 mm, spread
122 mm against 0.0 / 23 mm on the true surface). The mesh still says which surface a pixel's ray
meets first (the rasteriser or ray caster finds the triangle); the reference depth then comes from
the points: the ray is intersected with the plane fitted to the triangle's k nearest points, and
the inclination is that plane's. Fitting once per triangle, not per pixel, keeps the study at the
mesh study's speed: the per-pixel work is the float64 plane intersection the mesh path does anyway
(`hit_refine`), with other planes.

A triangle is supported when (reason codes, counted per pixel in the summary):
- `sparse`: at least `min_points` points lie within `radius_spacings` local point spacings of its
  centroid, they spread in two directions, and their centre lies within one spacing of it (a hole
  or the edge of one has points on one side only);
- `rough`: their plane fits them within `rough_factor` times the cloud's typical residual (an edge,
  a corner, clutter: no plane there);
- `mesh_off`: the triangle lies within the surface gap of that plane (the mesh, and so the
  visibility it gives, is confirmed by the points).
Pixels seeing an unsupported triangle keep its depth for visibility and are left out of the grid.

Each supported triangle carries the standard uncertainty of its plane at the triangle,
rms / sqrt(n) * sqrt(1 + rho^2 / r^2): the fit residual over the points' count, grown by how far
(rho) the triangle lies from the points' centre against their spread r (the point spacing's part).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import EvaluationError
from depthstation.core.grid import Grid
from depthstation.evaluate.scan.hit_refine import TrianglePlanes, refine_depths
from depthstation.evaluate.scan.raycast import F32, F64, FrameRenderer

POINT_FITS = "reference_points.npz"
REFERENCE_MODES = ("points", "mesh")
OK, SPARSE, ROUGH, MESH_OFF, EDGE = 0, 1, 2, 3, 4
REASONS = ("sparse", "rough", "mesh_off", "edge")  # codes 1, 2, 3, 4
PIXEL_NAMES = tuple(f"reference_{r}" for r in REASONS)  # summary.json pixels: left out, by reason
MIN_NOISE_M = 0.0005  # the rough rule's floor: a noise-free cloud still has 0.5 mm of slack
EDGE_SPACINGS = 2.0  # pixels this many point spacings from a jump of the reference are left out
EDGE_MAX_PX = 8  # the edge search's reach in pixels at most (near the camera)
BLOCK = 65536  # triangles per k-NN query block (bounded memory)


@dataclass(frozen=True)
class PointParams:
    """How a triangle's plane is fitted and when the points support it (module docstring)."""

    k: int = 16
    min_points: int = 6
    radius_spacings: float = 3.0
    centre_spacings: float = 0.5
    rough_factor: float = 3.0
    gap_m: float = 0.01

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class PointFits:
    """Per triangle (the mesh's order): the fitted plane (unit normal, n . p = offset, float64),
    why it is not used (0 = used), its standard uncertainty (m) and its points' count."""

    normal: NDArray[np.float64]
    offset: NDArray[np.float64]
    reason: NDArray[np.int8]
    sigma: NDArray[np.float64]
    points: NDArray[np.int16]
    edge_gap_m: float = 0.01  # a neighbour pixel's hit this far off a pixel's plane: an edge
    edge_reach_m: float = 0.0  # how far from an edge a pixel is left out (2 point spacings)

    def save(self, path: Path) -> Path:
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, normal=self.normal, offset=self.offset, reason=self.reason, sigma=self.sigma,
                 points=self.points, edge_gap_m=self.edge_gap_m, edge_reach_m=self.edge_reach_m)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: Path, triangles: int | None = None) -> PointFits:
        try:
            with np.load(path) as z:
                fits = cls(z["normal"], z["offset"], z["reason"], z["sigma"], z["points"],
                           float(z["edge_gap_m"]), float(z["edge_reach_m"]))
        except (OSError, ValueError, KeyError) as exc:
            raise EvaluationError(f"{path}: cannot read the reference's point fits ({exc}); delete it and "
                                  "run again") from exc
        if triangles is not None and fits.reason.shape != (triangles,):
            raise EvaluationError(f"{path}: point fits for {fits.reason.shape[0]} triangles, the mesh has "
                                  f"{triangles} (delete the folder's reference_mesh.ply and run again)")
        return fits

    def planes(self) -> TrianglePlanes:
        out = TrianglePlanes.__new__(TrianglePlanes)
        out.normal = np.ascontiguousarray(self.normal)
        out.offset = np.ascontiguousarray(self.offset)
        out.table = np.ascontiguousarray(self.normal.astype(np.float32))
        return out

    def summary(self) -> dict[str, Any]:
        ok = self.reason == OK
        n = len(self.reason)
        return {"triangles": n, "supported": int(ok.sum()),
                **{f"triangles_{r}": int(np.count_nonzero(self.reason == c))
                   for c, r in enumerate(REASONS, 1)},
                "median_sigma_m": float(np.median(self.sigma[ok])) if ok.any() else None,
                "p95_sigma_m": float(np.percentile(self.sigma[ok], 95)) if ok.any() else None,
                "median_points": float(np.median(self.points[ok])) if ok.any() else None}


def point_spacing(points: NDArray[np.float64], tree: Any) -> NDArray[np.float64]:
    """Each point's distance to its nearest other point (the scan's local spacing)."""
    d, _ = tree.query(points, k=2)
    return np.asarray(d[:, 1], dtype=np.float64)


def fit_triangles(vertices: NDArray[np.float64], triangles: NDArray[np.int64], points: NDArray[np.float64],
                  params: PointParams = PointParams(),
                  unmeasured: NDArray[np.bool_] | None = None) -> tuple[PointFits, dict[str, Any]]:
    """The plane of the points around every triangle, and whether they support it (module docstring).
    `unmeasured`: triangles the mesh checks already found off the points (counted as mesh_off)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nt = len(tri)
    k = int(min(params.k, len(pts)))
    normal = np.zeros((nt, 3))
    offset = np.zeros(nt)
    rms = np.full(nt, np.inf)
    sigma = np.full(nt, np.inf)
    count = np.zeros(nt, np.int16)
    reason = np.full(nt, SPARSE, np.int8)
    mesh_off = np.zeros(nt)
    if nt == 0 or k < 3:
        return PointFits(normal, offset, reason, sigma, count), {"noise_floor_m": None}
    tree = cKDTree(pts)
    spacing = point_spacing(pts, tree)
    for lo in range(0, nt, BLOCK):
        hi = min(nt, lo + BLOCK)
        t = tri[lo:hi]
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        centre = (a + b + c) / 3.0
        reach = np.sqrt(np.max(np.stack([((p - centre) ** 2).sum(1) for p in (a, b, c)]), axis=0))
        dist, near = tree.query(centre, k=k)
        s_loc = np.median(spacing[near], axis=1)
        w = (dist <= params.radius_spacings * s_loc[:, None]).astype(np.float64)
        n = w.sum(1)
        p = pts[near]
        nn = np.maximum(n, 1.0)
        mu = np.einsum("ik,ikj->ij", w, p) / nn[:, None]
        x = (p - mu[:, None, :]) * w[..., None]
        cov = np.einsum("ikj,ikl->ijl", x, x) / nn[:, None, None]
        lam, vec = np.linalg.eigh(cov)  # ascending
        nrm = vec[:, :, 0]
        tri_n = np.cross(b - a, c - a)
        nrm = np.where((np.einsum("ij,ij->i", nrm, tri_n) < 0)[:, None], -nrm, nrm)
        d_off = np.einsum("ij,ij->i", nrm, mu)
        lam = np.maximum(lam, 0.0)
        r_fit = np.sqrt(lam[:, 0] * nn / np.maximum(n - 3.0, 1.0))  # unbiased residual
        along = centre - mu
        rho = np.sqrt(np.maximum((along ** 2).sum(1) - np.einsum("ij,ij->i", along, nrm) ** 2, 0.0))
        spread2 = np.maximum(lam[:, 1], 1e-12)
        sig = r_fit / np.sqrt(nn) * np.sqrt(1.0 + (rho + reach) ** 2 / spread2)
        supported = ((n >= params.min_points) & (rho <= params.centre_spacings * s_loc)
                     & (np.sqrt(lam[:, 1]) >= 0.5 * s_loc))
        heights = np.stack([np.einsum("ij,ij->i", nrm, q) for q in (a, b, c)])
        vert_off = np.max(np.abs(heights - d_off), axis=0)
        sl = slice(lo, hi)
        normal[sl], offset[sl], rms[sl], sigma[sl] = nrm, d_off, r_fit, sig
        count[sl] = n.astype(np.int16)
        r = np.full(hi - lo, OK, np.int8)
        r[~supported] = SPARSE
        reason[sl] = r
        mesh_off[sl] = vert_off
    fitted = reason != SPARSE
    floor = float(np.median(rms[fitted])) if fitted.any() else 0.0
    limit = params.rough_factor * max(floor, MIN_NOISE_M)
    reason[fitted & (rms > limit)] = ROUGH
    if params.gap_m > 0:  # the mesh within the points' noise of their plane, and never beyond the gap
        reason[(reason == OK) & (mesh_off > min(params.gap_m, limit))] = MESH_OFF
    if unmeasured is not None and params.gap_m > 0:
        reason[(reason == OK) & np.asarray(unmeasured, dtype=bool)] = MESH_OFF
    fits = PointFits(normal, offset, reason, np.where(reason == OK, sigma, np.inf), count,
                     params.gap_m if params.gap_m > 0 else float("inf"),
                     max(EDGE_SPACINGS * float(np.median(spacing)), 0.05))
    info = {"noise_floor_m": floor, "rough_limit_m": limit,
            "median_spacing_m": float(np.median(spacing)), **fits.summary()}
    return fits, info


@numba.njit(cache=True, nogil=True)
def _mark_edges(t: Any, index: Any, normal: Any, offset: Any, reason: Any, dirs: Any, rot: Any, origin: Any,
                w: int, h: int, gap: float, sentinel: int, drop: Any, reach_px: float,
                max_px: int) -> None:  # pragma: no cover - numba
    """Pixels near a jump of the reference to the sentinel row: within reach_px / z pixels (`reach`
    metres at the pixel's depth z, at most max_px) along its row or column of a pixel without a hit,
    of one with a neighbour whose hit lies more than `gap` off its plane, or of the frame's border.
    At a silhouette, a reference whose edge is a point spacing off (an unscanned side, Poisson's
    rounding) sends a grazing ray past the object to the floor behind it, or onto it, a decimetre of
    error that no fit residual shows. Linear in the pixels: the jumps first, then their distance
    along rows and columns (`drop` holds the jumps, then the result)."""
    n = w * h
    for i in range(n):  # the jumps
        m = index[i]
        jump = m < 0 or not np.isfinite(t[i])
        if not jump and m < sentinel and reason[m] == 0:
            nx, ny, nz, off = normal[m, 0], normal[m, 1], normal[m, 2], offset[m]
            v, u = i // w, i % w
            for e in range(4):
                uu = u + (1 if e == 0 else -1 if e == 1 else 0)
                vv = v + (1 if e == 2 else -1 if e == 3 else 0)
                if uu < 0 or uu >= w or vv < 0 or vv >= h:
                    continue
                j = vv * w + uu
                tj = t[j]
                if index[j] < 0 or not np.isfinite(tj):
                    continue  # that pixel is a jump itself
                x, y, z = float(dirs[j, 0]), float(dirs[j, 1]), float(dirs[j, 2])
                px = origin[0] + tj * (rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z)
                py = origin[1] + tj * (rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z)
                pz = origin[2] + tj * (rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z)
                if abs(nx * px + ny * py + nz * pz - off) > gap:
                    jump = True
                    break
        drop[i] = jump
    dist = np.empty(n, np.int32)  # pixels to the nearest jump (or border) along the row or column
    for v in range(h):
        last = -1  # the border left of the row
        for u in range(w):
            i = v * w + u
            if drop[i]:
                last = u
            dist[i] = u - last
        last = w
        for u in range(w - 1, -1, -1):
            i = v * w + u
            if drop[i]:
                last = u
            dist[i] = min(dist[i], last - u)
    for u in range(w):
        last = -1
        for v in range(h):
            i = v * w + u
            if drop[i]:
                last = v
            dist[i] = min(dist[i], v - last)
        last = h
        for v in range(h - 1, -1, -1):
            i = v * w + u
            if drop[i]:
                last = v
            dist[i] = min(dist[i], last - v)
    for i in range(n):
        m = index[i]
        if m < 0 or m >= sentinel or reason[m] != 0 or not np.isfinite(t[i]):
            continue
        r = min(max(int(np.ceil(reach_px / t[i])), 1), max_px)
        if dist[i] <= r:
            index[i] = sentinel


@numba.njit(cache=True, nogil=True)
def _tally(kk: Any, start: Any, sj: Any, index: Any, reason: Any, sigma: Any, counts: Any, u_count: Any,
           u_sum: Any, ni: int) -> None:  # pragma: no cover - numba
    """After the per-pixel pass (`raycast.pixel_bins_kernel`: kk per pixel, sj in each distance
    bin's run, start[k] the end of run k): per reason, the pixels within the grid's range left out
    for their reference; per binned cell, the count and sum of its pixels' reference sigma."""
    nd = start.shape[0] - 1
    pos = np.empty(nd, np.int64)
    pos[0] = 0
    for k in range(1, nd):
        pos[k] = start[k - 1]
    for i in range(kk.shape[0]):
        k = kk[i]
        if k < 0:
            continue
        q = pos[k]
        pos[k] = q + 1
        m = index[i]
        r = reason[m]
        if r > 0:
            counts[r - 1] += 1
            continue
        j = sj[q]
        if j < 0:
            continue
        c = k * ni + j
        u_count[c] += 1.0
        u_sum[c] += sigma[m]


@dataclass
class ReferenceCells:
    """Per grid cell, the pixels binned and the sum of their reference sigma (flat, C order)."""

    shape: tuple[int, int]
    count: NDArray[np.float64]
    total: NDArray[np.float64]

    @classmethod
    def zeros(cls, shape: tuple[int, int]) -> ReferenceCells:
        return cls(shape, np.zeros(shape[0] * shape[1]), np.zeros(shape[0] * shape[1]))

    def merge(self, other: ReferenceCells | None) -> ReferenceCells:
        if other is not None:
            self.count += other.count
            self.total += other.total
        return self

    def u_m(self) -> NDArray[np.float64]:
        """Mean reference sigma per cell (NaN in cells without pixels)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(self.count > 0, self.total / self.count, np.nan)
        return out.reshape(self.shape)

    def __getstate__(self) -> dict[str, Any]:  # to a worker's parent: the cells with pixels only
        cells = np.flatnonzero(self.count)
        return {"shape": self.shape, "cells": cells, "count": self.count[cells], "total": self.total[cells]}

    def __setstate__(self, state: dict[str, Any]) -> None:
        size = state["shape"][0] * state["shape"][1]
        self.shape = tuple(state["shape"])
        self.count, self.total = np.zeros(size), np.zeros(size)
        self.count[state["cells"]] = state["count"]
        self.total[state["cells"]] = state["total"]


class PointFitRenderer(FrameRenderer):
    """A mesh renderer (rasteriser or ray caster) whose hits are measured against the point fits:
    the triangle's fitted plane gives the depth and the normal, unsupported triangles leave their
    pixels out (counted per reason), and each binned pixel's reference sigma is kept per cell."""

    def __init__(self, inner: FrameRenderer, fits: PointFits) -> None:
        super().__init__(inner.intr)
        self.inner = inner
        self.name = inner.name
        self.n_triangles = inner.n_triangles
        self.fits = fits
        perm = getattr(getattr(inner, "raster", None), "perm", None)  # the rasteriser's rank -> id
        planes = fits.planes()
        # by the inner renderer's index, one more row (the sentinel) for pixels at a reference edge
        reason = fits.reason if perm is None else fits.reason[perm]
        self._reason = np.ascontiguousarray(np.append(reason, np.int8(EDGE)))
        sigma = fits.sigma if perm is None else fits.sigma[perm]
        self._sigma = np.ascontiguousarray(np.append(sigma, np.inf))
        mine = planes if perm is None else planes.reordered(perm)
        inner.planes = mine
        inner.mark_unmeasured(fits.reason != OK)  # NaN normals: the pass leaves those pixels out
        self._planes = mine
        table = mine.table.copy()
        table[reason != OK] = np.nan
        self._table = np.ascontiguousarray(np.vstack([table, np.full((1, 3), np.nan, np.float32)]))
        self.unmeasured = inner.unmeasured
        self.edge_gap_m = fits.edge_gap_m
        self.edge_reach_m = fits.edge_reach_m
        self._index = np.zeros(0, np.int32)
        self._drop = np.zeros(0, np.bool_)
        self._cells: ReferenceCells | None = None

    def cast_indexed(self, pose: F64) -> tuple[F32, NDArray[np.int32], F32]:
        """(z-depth on the fitted planes, the inner renderer's index with pixels at a reference
        edge sent to the sentinel row, the fitted normals with NaN rows for unsupported ones)."""
        t_hit, index, _ = self.inner.cast_indexed(pose)
        refine_depths(t_hit, index, self._planes, self.dirs, pose)
        p = np.asarray(pose, dtype=np.float64)
        if self._drop.shape[0] != index.shape[0]:
            self._drop = np.zeros(index.shape[0], np.bool_)
        _mark_edges(t_hit, index, self._planes.normal, self._planes.offset, self._reason, self.dirs,
                    np.ascontiguousarray(p[:3, :3]), np.ascontiguousarray(p[:3, 3]), self.intr.width,
                    self.intr.height, self.edge_gap_m, self._reason.shape[0] - 1, self._drop,
                    self.edge_reach_m * self.intr.fx, EDGE_MAX_PX)
        self._index = index
        return t_hit, index, self._table

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """(z-depth on the fitted planes, their normals; NaN where left out) per pixel."""
        t_hit, index, table = self.cast_indexed(pose)
        t = np.array(t_hit, dtype=np.float32, copy=True)
        idx = np.asarray(index).reshape(-1)
        normals = np.where((idx >= 0)[:, None], table[np.maximum(idx, 0)], np.float32(np.nan))
        return t, np.ascontiguousarray(normals, dtype=np.float32)

    def bin_frame(self, pose: F64, depth: NDArray[Any], depth_scale: float, cells: Any,
                  stats: NDArray[np.int64], frame_cells: Any = None, moments: Any = None) -> None:
        super().bin_frame(pose, depth, depth_scale, cells, stats, frame_cells, moments)
        assert self._scratch is not None
        kk, sj, _, start, _ = self._scratch
        shape = cells.grid.count.shape
        if self._cells is None or self._cells.shape != shape:
            self._cells = ReferenceCells.zeros(shape)
        counts = np.zeros(len(REASONS), np.int64)
        _tally(kk, start, sj, self._index, self._reason, self._sigma, counts, self._cells.count,
               self._cells.total, shape[1])
        if stats.shape[0] >= 6 + len(REASONS):
            stats[6:6 + len(REASONS)] += counts

    def take_reference_cells(self) -> ReferenceCells | None:
        """The cells' reference sigma since the last take (this chunk's), and start afresh."""
        out, self._cells = self._cells, None
        return out

    def describe(self) -> dict[str, Any]:
        return {**self.inner.describe(), "reference_mode": "points",
                "rule": "depth and normal of the plane fitted to the scanned points around the hit triangle; "
                        "pixels whose triangle the points do not support are left out (pixels.reference_*)"}

    def sibling(self) -> PointFitRenderer:
        """Another renderer over the same prepared mesh and fits (for another thread)."""
        sib = getattr(self.inner, "sibling", None)
        if sib is None:
            raise TypeError("only a rasteriser has siblings")
        other = PointFitRenderer.__new__(PointFitRenderer)
        FrameRenderer.__init__(other, self.intr)
        other.inner = sib()
        other.name, other.n_triangles, other.fits = self.name, self.n_triangles, self.fits
        other._reason, other._sigma, other._table = self._reason, self._sigma, self._table
        other._planes, other.unmeasured = self._planes, other.inner.unmeasured
        other.edge_gap_m, other.edge_reach_m = self.edge_gap_m, self.edge_reach_m
        other._index = np.zeros(0, np.int32)
        other._drop = np.zeros(0, np.bool_)
        other._cells = None
        return other


def with_point_fits(renderer: FrameRenderer, path: Path) -> PointFitRenderer:
    """`renderer` measuring against the point fits kept in `path` (`POINT_FITS`)."""
    return PointFitRenderer(renderer, PointFits.load(Path(path), renderer.n_triangles))


def reference_u_into(grid: Grid, cells: ReferenceCells | None) -> None:
    """The cells' reference uncertainty onto the grid (its U95 takes it in)."""
    if cells is not None and cells.shape == grid.count.shape:
        grid.reference_u_m = cells.u_m()
