"""The reference: a TLS point cloud (meshed by Poisson + low-density trimming, as in the paper) or
a mesh, loaded with Open3D; the mesh made from a cloud is cached next to the results.

Why a mesh: the paper found nearest neighbours in the cloud too imprecise at long range; ray
casting needs a surface, and Poisson's density lets us drop the invented surface far from points.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.lazy_open3d import open3d

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".gltf", ".glb")
MESH_CACHE = "reference_mesh.ply"


@dataclass(frozen=True)
class PoissonParams:
    """Poisson depth (octree levels) and the density quantile below which vertices are removed."""

    depth: int = 9
    density_quantile: float = 0.05
    normal_radius_m: float = 0.05
    normal_max_nn: int = 30

    def to_dict(self) -> dict[str, Any]:
        return {"depth": self.depth, "density_quantile": self.density_quantile,
                "normal_radius_m": self.normal_radius_m, "normal_max_nn": self.normal_max_nn}


def _read_special(path: Path) -> Any:
    """E57 / LAS / LAZ through their optional packages, else a clear error (exit 2)."""
    o3d = open3d()

    suffix = path.suffix.lower()
    if suffix in (".las", ".laz"):
        try:
            import laspy
        except ImportError as exc:
            raise InputError(path, "LAS/LAZ needs the optional package 'laspy' (pip install laspy), "
                                   "or convert the cloud to PLY") from exc
        las = laspy.read(str(path))
        xyz = np.stack([las.x, las.y, las.z], axis=-1).astype(np.float64)
    else:
        try:
            import pye57
        except ImportError as exc:
            raise InputError(path, "E57 needs the optional package 'pye57' (pip install pye57), "
                                   "or convert the cloud to PLY") from exc
        e57 = pye57.E57(str(path))
        parts = []
        for i in range(e57.scan_count):
            d = e57.read_scan(i, ignore_missing_fields=True, transform=True)
            parts.append(np.stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]], axis=-1))
        xyz = np.concatenate(parts).astype(np.float64)
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(xyz)
    return pc


def load_reference(path: Path) -> tuple[str, Any]:
    """('mesh', TriangleMesh) or ('cloud', PointCloud) from the file, by content not only suffix."""
    o3d = open3d()

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "reference not found")
    suffix = path.suffix.lower()
    if suffix in (".e57", ".las", ".laz"):
        return "cloud", _read_special(path)
    if suffix not in CLOUD_SUFFIXES + MESH_SUFFIXES:
        raise InputError(path, f"unknown reference format {suffix!r} (PLY, PCD, XYZ, OBJ, STL, E57, LAS)")
    if suffix in MESH_SUFFIXES:
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) > 0:
            return "mesh", mesh
    cloud = o3d.io.read_point_cloud(str(path))
    if len(cloud.points) == 0:
        raise InputError(path, "reference holds neither triangles nor points")
    return "cloud", cloud


def poisson_mesh(cloud: Any, params: PoissonParams = PoissonParams()) -> tuple[Any, dict[str, Any]]:
    """Poisson surface of the cloud, minus vertices whose density is below the quantile."""
    o3d = open3d()

    if not cloud.has_normals():
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
            radius=params.normal_radius_m, max_nn=params.normal_max_nn))
        cloud.orient_normals_consistent_tangent_plane(10)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=params.depth)
    dens = np.asarray(densities)
    threshold = float(np.quantile(dens, params.density_quantile))
    mesh.remove_vertices_by_mask(dens < threshold)
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise EvaluationError("Poisson reconstruction left no triangles after density trimming")
    mesh.compute_triangle_normals()
    info = {"poisson": params.to_dict(), "density_threshold": threshold,
            "triangles": len(mesh.triangles), "vertices": len(mesh.vertices)}
    return mesh, info


def reference_mesh(path: Path, cache_dir: Path | None,
                   params: PoissonParams = PoissonParams()) -> tuple[Any, Path, dict[str, Any]]:
    """The mesh to cast against and the file it lives in (the input, or the cache for a cloud).

    The cache (`reference_mesh.ply` + `.json`) is reused when source path, size, mtime and Poisson
    parameters match, since Poisson on millions of points takes minutes.
    """
    o3d = open3d()

    path = Path(path)
    st = path.stat() if path.is_file() else None
    key = {"source": str(path.resolve()), "size": st.st_size if st else None,
           "mtime_ns": st.st_mtime_ns if st else None, "poisson": params.to_dict()}
    if cache_dir is not None:
        cached = Path(cache_dir) / MESH_CACHE
        meta = cached.with_suffix(".json")
        if cached.is_file() and meta.is_file():
            try:
                stored = json.loads(meta.read_text())
            except json.JSONDecodeError:
                stored = {}
            if stored.get("key") == key:
                mesh = o3d.io.read_triangle_mesh(str(cached))
                return mesh, cached, {**stored.get("info", {}), "cached": True}
    kind, geom = load_reference(path)
    if kind == "mesh":
        geom.compute_triangle_normals()
        return geom, path, {"kind": "mesh", "triangles": len(geom.triangles),
                            "vertices": len(geom.vertices)}
    mesh, info = poisson_mesh(geom, params)
    info = {"kind": "cloud", "points": len(geom.points), **info}
    if cache_dir is None:
        raise EvaluationError("a reference cloud needs a folder to keep its mesh")
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    cached = Path(cache_dir) / MESH_CACHE
    o3d.io.write_triangle_mesh(str(cached), mesh)
    cached.with_suffix(".json").write_text(json.dumps({"key": key, "info": info}, indent=2))
    return mesh, cached, {**info, "cached": False}


def sample_reference_points(mesh: Any, n: int = 400_000, seed: int = 0) -> Any:
    """Uniform points on the mesh, the target cloud for ICP and the c2c distance."""
    o3d = open3d()

    o3d.utility.random.seed(seed)
    return mesh.sample_points_uniformly(number_of_points=n)
