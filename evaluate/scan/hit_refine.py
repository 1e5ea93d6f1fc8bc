"""A pixel's reference hit refined in float64: the same triangle the renderer hit, its depth and
normal recomputed from the mesh's float64 vertices.

Why: both renderers (Open3D's ray casting, the rasteriser that reproduces it) work in float32.
Their depth and normal then depend on where the scene sits: the same room moved into survey
coordinates (and shifted back by whole metres) gives hits a few micrometres apart and normals
~0.003 deg apart (float32 vertices of 1 cm triangles 5 m from the origin). A sample that close to a
distance or inclination bin edge changes cell, and a cell of a few hundred samples moved by up to
~0.5 mm. From float64 vertices the plane of a triangle and the camera position agree in any frame
to ~1e-9 m, so the refined depth (rounded once to float32) and normal are the same, and a
georeferenced study bins as the local one (`tests/test_scan_tls.py`).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.core.grid import EXACT_MATH

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


class TrianglePlanes:
    """Per-triangle unit normal and plane offset (n . p = d) in float64, and the normals as float32
    (the table the per-pixel pass reads), in a given triangle order."""

    def __init__(self, vertices: NDArray[Any], triangles: NDArray[Any],
                 order: NDArray[Any] | None = None) -> None:
        """`order`: row k is triangle order[k] (as `reordered`, without the mesh-order copy)."""
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        tri = np.ascontiguousarray(triangles).reshape(-1, 3)
        if tri.dtype not in (np.int32, np.int64):
            tri = tri.astype(np.int64)
        rows = (np.arange(len(tri), dtype=np.int64) if order is None
                else np.ascontiguousarray(order, dtype=np.int64))
        self.normal = np.empty((len(rows), 3))
        self.offset = np.empty(len(rows))
        self.table = np.empty((len(rows), 3), np.float32)
        _planes(v, tri, rows, self.normal, self.offset, self.table)

    def reordered(self, order: NDArray[Any]) -> TrianglePlanes:
        """The same planes with row k = triangle order[k] (the rasteriser's ranks)."""
        out = TrianglePlanes.__new__(TrianglePlanes)
        out.normal = np.ascontiguousarray(self.normal[order])
        out.offset = np.ascontiguousarray(self.offset[order])
        out.table = np.ascontiguousarray(self.table[order])
        return out

    def with_unmeasured(self, rows: NDArray[Any] | None) -> F32:
        """The float32 normal table with NaN rows for unmeasured triangles (the pass leaves their
        pixels out and counts them)."""
        if rows is None or len(rows) == 0:
            return self.table
        table = self.table.copy()
        table[np.asarray(rows, dtype=np.int64)] = np.nan
        return table


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _planes(v: Any, tri: Any, rows: Any, normal: Any, offset: Any,
            table: Any) -> None:  # pragma: no cover - numba
    """Row k: unit normal of triangle rows[k] (cross product of b - a and c - a, then divided by
    its length; zero for a degenerate one), its offset n . a and the normal as float32. Why one
    pass: numpy's temporaries and gathers took ~0.5 s of CPU per million triangles at start-up."""
    for k in range(rows.shape[0]):
        s = rows[k]
        ia, ib, ic = tri[s, 0], tri[s, 1], tri[s, 2]
        ax, ay, az = v[ia, 0], v[ia, 1], v[ia, 2]
        ux, uy, uz = v[ib, 0] - ax, v[ib, 1] - ay, v[ib, 2] - az
        wx, wy, wz = v[ic, 0] - ax, v[ic, 1] - ay, v[ic, 2] - az
        nx = uy * wz - uz * wy
        ny = uz * wx - ux * wz
        nz = ux * wy - uy * wx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm == 0.0:  # a degenerate triangle: no plane; its hits keep the renderer's depth
            nx = ny = nz = 0.0
        else:
            nx, ny, nz = nx / norm, ny / norm, nz / norm
        normal[k, 0], normal[k, 1], normal[k, 2] = nx, ny, nz
        offset[k] = (nx * ax + nz * az) + ny * ay  # the order numpy's einsum summed in: same offsets
        table[k, 0], table[k, 1], table[k, 2] = np.float32(nx), np.float32(ny), np.float32(nz)


def refine_depths(t_hit: F32, index: NDArray[np.int32], planes: TrianglePlanes, dirs: F32,
                  pose: F64) -> None:
    """t_hit of every hit pixel (finite, index >= 0) replaced by the z-depth at which its ray
    (camera-frame `dirs`, z = 1) meets the plane of the triangle `index` names, in float64 from
    the camera-to-reference `pose`; rounded once to float32."""
    p = np.asarray(pose, dtype=np.float64)
    _refine(t_hit, index, planes.normal, planes.offset, dirs, np.ascontiguousarray(p[:3, :3]),
            np.ascontiguousarray(p[:3, 3]))


@numba.njit(cache=True, nogil=True, fastmath=EXACT_MATH)
def _refine(t_hit: Any, index: Any, normal: Any, offset: Any, dirs: Any, rot: Any,
            origin: Any) -> None:  # pragma: no cover - numba
    m = normal.shape[0]
    for i in range(t_hit.shape[0]):
        k = index[i]
        if k < 0 or k >= m or not np.isfinite(t_hit[i]):
            continue
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        dx, dy, dz = float(dirs[i, 0]), float(dirs[i, 1]), float(dirs[i, 2])
        wx = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        wy = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        wz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        den = nx * wx + ny * wy + nz * wz
        if den == 0.0:
            continue
        t = (offset[k] - (nx * origin[0] + ny * origin[1] + nz * origin[2])) / den
        if t > 0.0:
            t_hit[i] = np.float32(t)
