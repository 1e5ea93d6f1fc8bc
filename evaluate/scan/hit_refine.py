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

    def __init__(self, vertices: NDArray[Any], triangles: NDArray[Any]) -> None:
        v = np.asarray(vertices, dtype=np.float64)
        tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            n = n / norm[:, None]
        n[norm == 0] = 0.0  # a degenerate triangle: no plane; its hits keep the renderer's depth
        self.normal = np.ascontiguousarray(n)
        self.offset = np.ascontiguousarray(np.einsum("ij,ij->i", n, a))
        self.table = np.ascontiguousarray(n.astype(np.float32))

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
