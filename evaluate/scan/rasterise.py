"""The study's reference depth by rasterising the mesh (`core.raster`), and the choice of renderer.

Why: every frame is a pinhole view, so projecting the triangles onto the pixel grid (frustum
culled clusters, a z-buffer, the reference arithmetic for each candidate pixel) gives what Open3D's
ray casting gives for the same rays, bit for bit, at a fraction of its cost (benchmarks/bench_scan.py).
Open3D ray casting stays the reference (`--renderer raycast`), and takes over for streams with
lens distortion, whose rays are not a pinhole grid.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics
from depthstation.core.errors import InputError
from depthstation.core.lazy_open3d import open3d
from depthstation.core.raster import MeshRaster, arithmetic_report
from depthstation.evaluate.scan.hit_refine import TrianglePlanes
from depthstation.evaluate.scan.raycast import F32, F64, FrameRenderer, MeshCaster

RENDERERS = ("raster", "raycast")
DEFAULT_RENDERER = "raster"
DISTORTION_FALLBACK = "lens distortion: the pixel rays are not a pinhole grid, so they are ray cast"


def mesh_arrays(mesh: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """(vertices, triangles) of a mesh file or an Open3D mesh (legacy or tensor)."""
    if isinstance(mesh, (str, Path)):
        mesh = open3d().io.read_triangle_mesh(str(mesh))
    if hasattr(mesh, "vertex"):
        return (mesh.vertex.positions.numpy().astype(np.float64),
                mesh.triangle.indices.numpy().astype(np.int64))
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles).astype(np.int64)


class MeshRasteriser(FrameRenderer):
    """The mesh rasterised into each posed frame (`core.raster.MeshRaster`); one thread."""

    name = "raster"

    def __init__(self, mesh: Any, intr: Intrinsics, raster: MeshRaster | None = None,
                 planes: TrianglePlanes | None = None) -> None:
        super().__init__(intr)
        if raster is None:
            vertices, triangles = mesh_arrays(mesh)
            raster = MeshRaster(vertices, triangles)
            planes = TrianglePlanes(vertices, triangles, raster.perm)  # by rank
        self.raster = raster
        self.planes = planes
        self._table = None if planes is None else planes.table
        self.n_triangles = raster.n_triangles
        self._unmeasured_ranks: NDArray[np.int32] | None = None  # `_unmeasured_ids`' ranks
        n = self.dirs.shape[0]
        self._t = np.empty(n, np.float32)
        self._ids = np.empty(n, np.int32)
        self._normals = np.empty((n, 3), np.float32)

    def cast(self, pose: F64) -> tuple[F32, F32]:
        """(t_hit, normals) as Open3D would cast them; the arrays are reused by the next frame."""
        pose = np.asarray(pose, dtype=np.float64)
        self.raster.render(self.intr, pose, self._t, self._ids, self._normals)
        self._blank_unmeasured(self._ids, self._normals)
        return self._t, self._normals

    def cast_indexed(self, pose: F64) -> tuple[F32, NDArray[np.int32], F32]:
        """(t_hit, hit triangles' ranks, per-rank normals): the pass reads each pixel's normal from
        the table, so no per-pixel normal array is gathered (7 MB written and read per frame)."""
        raster = self.raster
        raster.render(self.intr, np.asarray(pose, dtype=np.float64), self._t, self._ids, None, ranks=True,
                      table=self._table is None)
        if self._table is not None:  # normals from float64 vertices, unmeasured rows NaN (`hit_refine`)
            return self._t, self._ids, self._table
        table = raster.normal_table()
        um = self._unmeasured_ranks
        if um is not None and self.unmeasured is not None:  # the winners' normals were just written
            if um.size <= self._ids.size // 4:
                table[um] = np.nan
            else:  # many unmeasured triangles: only those hit this frame (a pass over the pixels)
                hit = self._ids[self._ids >= 0]
                table[hit[self.unmeasured[raster.perm[hit]]]] = np.nan
        return self._t, self._ids, table

    def mark_unmeasured(self, mask: NDArray[np.bool_] | None) -> None:
        super().mark_unmeasured(mask)
        um = self._unmeasured_ids
        self._unmeasured_ranks = None if um is None else self.raster.rank[um]
        if self.planes is not None:
            self._table = self.planes.with_unmeasured(self._unmeasured_ranks)

    def describe(self) -> dict[str, Any]:
        return {"renderer": self.name, **arithmetic_report()}

    def sibling(self) -> MeshRasteriser:
        """Another renderer over the same prepared mesh (for another thread)."""
        other = MeshRasteriser(None, self.intr, self.raster.sibling(), self.planes)
        other.mark_unmeasured(self.unmeasured)
        return other


class _FallbackCaster(MeshCaster):
    """Ray casting where the rasteriser was asked for but cannot serve (lens distortion)."""

    def describe(self) -> dict[str, Any]:
        return {"renderer": self.name, "requested": "raster", "reason": DISTORTION_FALLBACK}


def check_renderer(name: str) -> str:
    if name not in RENDERERS:
        raise InputError(None, f"unknown renderer {name!r} (known: {', '.join(RENDERERS)})")
    return name


def make_renderer(name: str, mesh: Any, intr: Intrinsics, nthreads: int = 0,
                  unmeasured: NDArray[np.bool_] | None = None) -> FrameRenderer:
    """The renderer `name` ('raster' or 'raycast') over `mesh` for frames of `intr`;
    `nthreads`: Open3D's ray-casting threads (0 = all); `unmeasured`: per triangle, surface
    nobody scanned (`FrameRenderer.mark_unmeasured`)."""
    check_renderer(name)
    renderer: FrameRenderer
    if name == "raster":
        renderer = (MeshRasteriser(mesh, intr) if not intr.has_distortion
                    else _FallbackCaster(mesh, intr, nthreads))
    else:
        renderer = MeshCaster(mesh, intr, nthreads)
    renderer.mark_unmeasured(unmeasured)
    return renderer
