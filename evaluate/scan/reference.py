"""The reference: a TLS point cloud (meshed by Poisson + low-density trimming, as in the paper) or
a mesh, loaded with Open3D; the mesh made from a cloud is cached next to the results.

Why a mesh: the paper found nearest neighbours in the cloud too imprecise at long range; ray
casting needs a surface, and Poisson's density lets us drop the invented surface far from points.

Surveyors deliver scans in survey coordinates (x ~ 4e5 m, y ~ 5e6 m). Coordinates are read in
float64 and, when the reference lies far from the origin, moved by a local shift (its bounding-box
centre, whole metres) before anything is meshed, cast or registered: float32 ray casting at 5e6 m
has a 0.5 m spacing. The mesh kept next to the results is the shifted one; the shift is reported.
E57 and LAS/LAZ come through the `[tls]` extra (pye57, laspy with lazrs); their intensity or colour
rides on the cloud (and Poisson carries it to the mesh) for the figures.
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.lazy_open3d import open3d
from depthstation.core.mesh_checks import check_mesh, check_mesh_file
from depthstation.core.run_warnings import warn
from depthstation.evaluate.scan.point_reference import POINT_FITS, PointParams, fit_triangles
from depthstation.evaluate.scan.tls import Scans, check_las, open_e57, read_e57, read_las
from depthstation.evaluate.scan.trajectory import LOCAL_SHIFT_ABOVE_M, local_shift

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".gltf", ".glb")
MESH_CACHE = "reference_mesh.ply"
UNMEASURED_CACHE = "reference_mesh_unmeasured.npy"  # per triangle: surface no scanned point supports


@dataclass(frozen=True)
class PoissonParams:
    """Poisson depth (octree levels) and the density quantile below which vertices are removed.

    `threads`: 1 meshes the same cloud to the same mesh, bit for bit. Open3D's multi-threaded
    Poisson (0: all cores) sums in a varying order, so two runs move the surface by micrometres
    and, at silhouettes, a pixel's hit by millimetres: a study that cannot be repeated exactly.

    `surface_gap_m`: a triangle with a vertex this far off the scanned points' planes is surface
    nobody measured (`unmeasured_triangles`); the study leaves the pixels that see it out (0: keep).
    """

    depth: int = 9
    density_quantile: float = 0.05
    normal_radius_m: float = 0.05
    normal_max_nn: int = 30
    threads: int = 1
    surface_gap_m: float = 0.01

    def to_dict(self) -> dict[str, Any]:
        return {"depth": self.depth, "density_quantile": self.density_quantile,
                "normal_radius_m": self.normal_radius_m, "normal_max_nn": self.normal_max_nn,
                "threads": self.threads, "surface_gap_m": self.surface_gap_m}


def _appearance(rgb: np.ndarray | None, intensity: np.ndarray | None) -> np.ndarray | None:
    """Per-point colour in [0, 1] for the figures: the scan's RGB, else its intensity as grey."""
    if rgb is not None and rgb.size and np.any(rgb > 0):
        rgb = rgb.astype(np.float64)
        return np.clip(rgb / (65535.0 if rgb.max() > 255 else 255.0), 0.0, 1.0)
    if intensity is not None and intensity.size:
        i = intensity.astype(np.float64)
        hi = float(np.percentile(i, 99.5)) or float(i.max()) or 1.0
        return np.repeat(np.clip(i / hi, 0.0, 1.0)[:, None], 3, axis=1)
    return None


def _read_special(path: Path) -> tuple[Any, str | None, Scans | None, dict[str, Any]]:
    """E57 / LAS / LAZ through their optional packages (float64 metres, the scan poses applied,
    intensity or RGB as point colours) and what the file says of its coordinates, else one line
    naming the file (exit 2)."""
    o3d = open3d()

    tls = read_las(path) if path.suffix.lower() in (".las", ".laz") else read_e57(path)
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(tls.xyz)
    look = _appearance(tls.rgb, tls.intensity)
    if look is not None:
        pc.colors = o3d.utility.Vector3dVector(look)
    kind = None if look is None else ("rgb" if tls.rgb is not None and np.any(tls.rgb > 0) else "intensity")
    return pc, kind, tls.scans, tls.coordinates


def say_coordinates(coordinates: dict[str, Any] | None, path: Path) -> None:
    """A LAS in feet converted to metres, or a CRS named without its unit: said on every run (the
    cached mesh too), since every figure of the study scales with it."""
    if not coordinates:
        return
    if coordinates.get("converted_to_metres"):
        c = coordinates
        warn(f"coordinates in {c['horizontal_unit']} ({c['horizontal_unit_from']}), heights in "
             f"{c['vertical_unit']} ({c['vertical_unit_from']}): converted to metres",
             str(path), "reference-units")
    if coordinates.get("unit_note"):
        warn(f"{coordinates['unit_note']}; if that CRS is in feet every distance is off by 3.28x",
             str(path), "reference-units")


def load_reference(path: Path) -> tuple[str, Any]:
    """('mesh', TriangleMesh) or ('cloud', PointCloud) from the file, by content not only suffix."""
    o3d = open3d()

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "reference not found")
    suffix = path.suffix.lower()
    if suffix in (".e57", ".las", ".laz"):
        pc, _, _, coordinates = _read_special(path)
        say_coordinates(coordinates, path)
        return "cloud", pc
    if suffix not in CLOUD_SUFFIXES + MESH_SUFFIXES:
        raise InputError(path, f"unknown reference format {suffix!r} (PLY, PCD, XYZ, OBJ, STL, E57, LAS)")
    check_mesh_file(path)
    if suffix in MESH_SUFFIXES:
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) > 0:
            check_mesh(path, np.asarray(mesh.vertices), np.asarray(mesh.triangles))
            return "mesh", mesh
    cloud = o3d.io.read_point_cloud(str(path))
    if len(cloud.points) == 0:
        raise InputError(path, "reference holds neither triangles nor points")
    return "cloud", drop_nonfinite_points(path, cloud)


def check_reference_file(path: Path) -> None:
    """What can be told of a reference without reading its points (a batch checks every item before
    any runs): a known format, not empty, a PLY's header and its vertex count, a LAS/LAZ's header
    and units, an E57's scans. Bad input naming the file (exit 2)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "reference not found")
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES + MESH_SUFFIXES + (".e57", ".las", ".laz"):
        raise InputError(path, f"unknown reference format {suffix!r} (PLY, PCD, XYZ, OBJ, STL, E57, LAS)")
    if path.stat().st_size == 0:
        raise InputError(path, "reference is empty (0 bytes)")
    if suffix in (".las", ".laz"):
        check_las(path)
    elif suffix == ".e57":
        open_e57(path)
    elif suffix == ".ply":
        check_mesh_file(path)
        with path.open("rb") as f:
            head = f.read(1 << 16)
        end = head.find(b"end_header")
        if end < 0:
            raise InputError(path, "broken PLY header (no end_header in its first 64 kB)")
        counts = {}
        for line in head[:end].decode("ascii", "replace").splitlines():
            words = line.split()
            if len(words) == 3 and words[0] == "element" and words[2].isdigit():
                counts[words[1]] = int(words[2])
        if counts.get("vertex", 0) == 0:
            raise InputError(path, "reference holds neither triangles nor points (its PLY header lists "
                                   "no vertex)")


def drop_nonfinite_points(path: Path, cloud: Any) -> Any:
    """Points without finite coordinates (E57/LAS invalid returns) carry no surface: dropped, said."""
    pts = np.asarray(cloud.points)
    good = np.isfinite(pts).all(axis=1)
    if good.all():
        return cloud
    warn(f"{int((~good).sum())} of {len(pts)} points are not finite numbers (NaN or inf): left out of the "
         "reference", str(path), "reference-nonfinite")
    kept = cloud.select_by_index(np.flatnonzero(good).tolist())
    if len(kept.points) == 0:
        raise InputError(path, "reference holds no point with finite coordinates")
    return kept


def orient_normals(cloud: Any, scans: Scans | None = None, viewpoints: np.ndarray | None = None) -> str:
    """Turn estimated normals towards where the surface was seen from; says how, in words.

    The camera centres of the walk under study (`viewpoints`, in the reference frame): towards
    the nearest one, so every surface faces the cameras whose depth is judged, whatever the file
    format. Else TLS stations (E57 scan poses): each point's normal towards its own scanner. Else
    Open3D's consistent-tangent-plane spanning tree (slow: it grows faster than n^2, and sharp
    room corners can split its orientation), the fallback for a cloud with nothing better.
    """
    o3d = open3d()

    pts = np.asarray(cloud.points)
    normals = np.asarray(cloud.normals).copy()
    if viewpoints is not None and len(viewpoints):
        normals[facing_away(cloud, viewpoints)] *= -1.0
        how = TOWARDS_CAMERAS
    elif scans:
        for start, end, origin in scans:
            flip = np.einsum("ij,ij->i", normals[start:end], origin - pts[start:end]) < 0
            normals[start:end][flip] *= -1.0
        how = "towards the scanner of each E57 scan"
    else:
        cloud.orient_normals_consistent_tangent_plane(10)
        return "consistent tangent plane"
    cloud.normals = o3d.utility.Vector3dVector(normals)
    return how


AWAY_SHARE = 0.2  # of a cloud's given normals facing away from the walk: not oriented, re-oriented
TOWARDS_CAMERAS = "towards the nearest camera centre of the trajectory"


def facing_away(cloud: Any, viewpoints: np.ndarray) -> np.ndarray:
    """Per point, whether its normal faces away from its nearest camera centre."""
    from scipy.spatial import cKDTree

    pts = np.asarray(cloud.points)
    if len(pts) == 0:
        return np.zeros(0, bool)
    _, nearest = cKDTree(viewpoints).query(pts, k=1)
    return np.asarray(np.einsum("ij,ij->i", np.asarray(cloud.normals), viewpoints[nearest] - pts) < 0)


def poisson_mesh(cloud: Any, params: PoissonParams = PoissonParams(), scans: Scans | None = None,
                 viewpoints: np.ndarray | None = None,
                 where: str | None = None) -> tuple[Any, dict[str, Any], np.ndarray]:
    """Poisson surface of the cloud, minus vertices whose density is below the quantile; with
    the triangles that lie off the scanned surface (`unmeasured_triangles`)."""
    o3d = open3d()

    normals = "given"
    if not cloud.has_normals():
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
            radius=params.normal_radius_m, max_nn=params.normal_max_nn))
        normals = orient_normals(cloud, scans, viewpoints)
    elif viewpoints is not None and len(viewpoints):
        # Poisson on normals half of which point out of the room turns surfaces inside out: the
        # grid's mean moved by 40-110 mm with a passing fit check
        flip = facing_away(cloud, viewpoints)
        away = float(np.mean(flip)) if len(flip) else 0.0
        if away > AWAY_SHARE:
            turned = np.asarray(cloud.normals).copy()
            turned[flip] *= -1.0
            cloud.normals = o3d.utility.Vector3dVector(turned)
            normals = f"given, {100 * away:.0f} % facing away from the walk: re-oriented {TOWARDS_CAMERAS}"
            warn(f"{100 * away:.0f} % of the cloud's own normals face away from the nearest camera centre of "
                 f"the walk (normals of no consistent orientation): re-oriented {TOWARDS_CAMERAS} before "
                 "meshing", where, "reference-normals")
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=params.depth, n_threads=params.threads if params.threads > 0 else -1)
    dens = np.asarray(densities)
    threshold = float(np.quantile(dens, params.density_quantile))
    mesh.remove_vertices_by_mask(dens < threshold)
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise EvaluationError("Poisson reconstruction left no triangles after density trimming")
    mesh.compute_triangle_normals()
    vertices = np.asarray(mesh.vertices)
    off = vertex_offsets(vertices, np.asarray(cloud.points), np.asarray(cloud.normals))
    unmeasured = unmeasured_triangles(np.asarray(mesh.triangles), off, params.surface_gap_m)
    info = {"poisson": params.to_dict(), "density_threshold": threshold, "normals": normals,
            "triangles": len(mesh.triangles), "vertices": len(mesh.vertices),
            "surface_to_points": offset_summary(off, params.surface_gap_m or SURFACE_GAP_M),
            "unmeasured": {"triangles": int(np.count_nonzero(unmeasured)),
                           "share": float(np.mean(unmeasured)) if len(unmeasured) else 0.0,
                           "gap_m": params.surface_gap_m,
                           "rule": "a triangle with a vertex more than gap_m off the scanned points' "
                                   "planes (median over its 8 nearest points); the pixels that see one "
                                   "are left out of the grid (pixels.unmeasured_surface)"
                                   if params.surface_gap_m > 0 else "kept (--surface-gap-m 0)"}}
    return mesh, info, unmeasured


SURFACE_GAP_M = 0.01  # a meshed surface this far off the scanned points' planes was not measured


def vertex_offsets(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray, k: int = 8) -> np.ndarray:
    """How far each vertex of the meshed surface lies off the scanned surface: the median over its
    k nearest points of the distance to each point's tangent plane (the cloud's normals). Poisson
    rounds edges and corners and closes holes with surface nobody measured, which the density
    trimming leaves in part (an audit: 1.8 % of a room's pixels in cells 100 mm off, against a
    u95 of 0.5 mm, with no word). On that room this tracks the true deviation (correlation 0.90);
    the median keeps 2-4 mm of scanner noise below the 10 mm gap."""
    from scipy.spatial import cKDTree

    if len(vertices) == 0 or len(points) < k:
        return np.zeros(len(vertices))
    _, near = cKDTree(points).query(vertices, k=k)
    off = np.abs(np.einsum("ikj,ikj->ik", normals[near], vertices[:, None, :] - points[near]))
    return np.asarray(np.median(off, axis=1), dtype=np.float64)


def offset_summary(off: np.ndarray, gap_m: float = SURFACE_GAP_M) -> dict[str, float]:
    """Median, 99th percentile, largest vertex offset and the share of vertices beyond the gap."""
    if len(off) == 0:
        return {"gap_m": gap_m, "median_m": 0.0, "p99_m": 0.0, "max_m": 0.0, "share_beyond_gap": 0.0}
    return {"gap_m": gap_m, "median_m": float(np.median(off)), "p99_m": float(np.percentile(off, 99)),
            "max_m": float(np.max(off)), "share_beyond_gap": float(np.mean(off > gap_m))}


def surface_to_points(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray,
                      k: int = 8) -> dict[str, float]:
    """`offset_summary` of `vertex_offsets`."""
    return offset_summary(vertex_offsets(vertices, points, normals, k))


def unmeasured_triangles(triangles: np.ndarray, vertex_off: np.ndarray, gap_m: float) -> np.ndarray:
    """Per triangle: does a vertex lie more than gap_m off the scanned surface (none when gap_m is 0)?

    Why: a pixel that sees such a triangle compares the camera with surface Poisson invented (a
    rounded corner, a closed hole), not with the scan, and its error is the meshing's. The triangle
    stays in the mesh: it still hides what lies behind it, as the real object did."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if gap_m <= 0 or len(tri) == 0:
        return np.zeros(len(tri), dtype=bool)
    return np.asarray(np.max(vertex_off[tri], axis=1) > gap_m)


def _shift_geometry(geom: Any, kind: str) -> np.ndarray:
    """Move a far-away mesh or cloud to local coordinates (float64); the shift subtracted."""
    pts = np.asarray(geom.vertices if kind == "mesh" else geom.points)
    if pts.size == 0:
        return np.zeros(3)
    shift = local_shift(pts.min(axis=0), pts.max(axis=0))
    if np.any(shift != 0.0):
        geom.translate(-shift)
    return shift


def reference_mesh(path: Path, cache_dir: Path | None, params: PoissonParams = PoissonParams(),
                   viewpoints: np.ndarray | None = None,
                   points: PointParams | None = None) -> tuple[Any, Path, dict[str, Any]]:
    """The mesh to cast against and the file it lives in (the input, or the cache for a cloud or a
    shifted mesh); `info['local_shift_m']` is what was subtracted from the reference's coordinates.
    `viewpoints`: camera centres in the reference's frame, to orient a cloud's normals by.
    `points`: for a cloud, also fit every triangle's plane to the points around it
    (`point_reference`, kept in `reference_points.npz`; `info['point_fits']`).

    The cache (`reference_mesh.ply` + `.json`) is reused when source path, size, mtime and Poisson
    parameters match, since Poisson on millions of points takes minutes.
    """
    o3d = open3d()

    path = Path(path)
    st = path.stat() if path.is_file() else None
    key = {"source": str(path.resolve()), "size": st.st_size if st else None,
           "mtime_ns": st.st_mtime_ns if st else None, "poisson": params.to_dict(),
           "local_shift_above_m": LOCAL_SHIFT_ABOVE_M,
           "tls_in_metres": True,  # meshes cached before LAS/LAZ units were converted are made again
           "viewpoints": None if viewpoints is None else hashlib.sha1(
               np.round(np.asarray(viewpoints, dtype=np.float64), 2).tobytes()).hexdigest(),
           "points": None if points is None else points.to_dict()}
    if cache_dir is not None:
        cached = Path(cache_dir) / MESH_CACHE
        meta = cached.with_suffix(".json")
        if cached.is_file() and meta.is_file():
            try:
                stored = json.loads(meta.read_text())
            except json.JSONDecodeError:
                stored = {}
            info_kept = stored.get("info", {})
            mask_kept = unmeasured_file(cached, info_kept)
            fits_kept = (points is None or info_kept.get("kind") != "cloud"
                         or (Path(cache_dir) / POINT_FITS).is_file())
            if stored.get("key") == key and (mask_kept is None or mask_kept.is_file()) and fits_kept:
                mesh = o3d.io.read_triangle_mesh(str(cached))
                say_coordinates(info_kept.get("coordinates"), path)
                return mesh, cached, {**info_kept, "cached": True}
    scans: Scans | None = None
    coordinates: dict[str, Any] | None = None
    if path.suffix.lower() in (".e57", ".las", ".laz"):
        geom, look, scans, coordinates = _read_special(path)
        kind = "cloud"
        say_coordinates(coordinates, path)
    else:
        kind, geom = load_reference(path)
        look = "rgb" if (geom.has_vertex_colors() if kind == "mesh" else geom.has_colors()) else None
    shift = _shift_geometry(geom, kind)
    if scans is not None:
        scans = [(a, b, o - shift) for a, b, o in scans]
    local_views = None if viewpoints is None else np.asarray(viewpoints, dtype=np.float64) - shift
    unmeasured: np.ndarray | None = None
    if kind == "mesh":
        geom.compute_triangle_normals()
        info: dict[str, Any] = {"kind": "mesh", "triangles": len(geom.triangles),
                                "vertices": len(geom.vertices)}
        if not np.any(shift != 0.0):
            return geom, path, {**info, "local_shift_m": [0.0, 0.0, 0.0], "appearance": look}
        mesh = geom
    else:
        mesh, info, unmeasured = poisson_mesh(geom, params, scans, local_views, str(path))
        info = {"kind": "cloud", "points": len(geom.points), **info}
        if points is not None:
            fits, fit_info = fit_triangles(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                           np.asarray(geom.points), points,
                                           unmeasured if params.surface_gap_m > 0 else None)
            if cache_dir is None:
                raise EvaluationError("a reference cloud needs a folder to keep its point fits")
            Path(cache_dir).mkdir(parents=True, exist_ok=True)
            fits.save(Path(cache_dir) / POINT_FITS)
            info["point_fits"] = {"file": POINT_FITS, "params": points.to_dict(), **fit_info}
            if fit_info["supported"] == 0:
                raise InputError(path, f"the scanned points support none of the {fit_info['triangles']} "
                                       "triangles of their mesh (too few points near each, no plane through "
                                       "them, or the mesh far from them): no surface to measure a camera "
                                       "against (random points, or a cloud far too sparse)")
        if coordinates:
            info["coordinates"] = coordinates
    info.update({"local_shift_m": shift.tolist(), "appearance": look})
    if cache_dir is None:
        raise EvaluationError("a reference cloud (or a far-away mesh) needs a folder to keep its mesh")
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    cached = Path(cache_dir) / MESH_CACHE
    o3d.io.write_triangle_mesh(str(cached), mesh)
    mask = Path(cache_dir) / UNMEASURED_CACHE
    if unmeasured is not None and np.any(unmeasured):
        np.save(mask, unmeasured)
    elif mask.is_file():
        mask.unlink()
    cached.with_suffix(".json").write_text(json.dumps({"key": key, "info": info}, indent=2))
    return mesh, cached, {**info, "cached": False}


def unmeasured_file(mesh_path: Path, info: dict[str, Any]) -> Path | None:
    """The per-triangle mask of surface nobody measured beside a mesh made from a cloud (None: the
    mesh was given, or all of it lies on the scan)."""
    um = info.get("unmeasured")
    if not isinstance(um, dict) or not um.get("triangles"):
        return None
    return Path(mesh_path).parent / UNMEASURED_CACHE


def load_unmeasured(path: Path | None, triangles: int) -> np.ndarray | None:
    """The mask `unmeasured_file` names, checked against the mesh's triangle count."""
    if path is None:
        return None
    try:
        mask = np.load(path)
    except (OSError, ValueError) as exc:
        raise EvaluationError(f"{path}: cannot read the mask of unmeasured reference surface "
                              f"({exc})") from exc
    if mask.dtype != np.bool_ or mask.shape != (triangles,):
        raise EvaluationError(f"{path}: the mask of unmeasured surface has {mask.shape} {mask.dtype} "
                              "entries, "
                              f"the reference mesh {triangles} triangles (delete the folder's "
                              f"{MESH_CACHE} and mesh again)")
    return np.asarray(mask)


def appearance_image(mesh: Any, intr: Intrinsics, pose: np.ndarray) -> np.ndarray | None:
    """What the scanner recorded (RGB, or intensity as grey) on the reference surface each pixel of
    a camera with camera-to-reference `pose` sees; HxWx3 in [0, 1], NaN where no surface. None when
    the reference carries no appearance."""
    o3d = open3d()

    if not mesh.has_vertex_colors():
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    dirs = pixel_rays(intr).reshape(-1, 3).astype(np.float64) @ np.asarray(pose)[:3, :3].T
    rays = np.concatenate([np.broadcast_to(np.asarray(pose)[:3, 3], dirs.shape), dirs], axis=1)
    ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    ids = ans["primitive_ids"].numpy().astype(np.int64)
    uv = ans["primitive_uvs"].numpy().astype(np.float64)
    hit = ids != o3d.t.geometry.RaycastingScene.INVALID_ID
    out = np.full((ids.size, 3), np.nan)
    tri = np.asarray(mesh.triangles)[ids[hit]]
    col = np.asarray(mesh.vertex_colors)
    u, v = uv[hit, 0:1], uv[hit, 1:2]
    out[hit] = (1.0 - u - v) * col[tri[:, 0]] + u * col[tri[:, 1]] + v * col[tri[:, 2]]
    return out.reshape(intr.height, intr.width, 3)


def measured_part(mesh: Any, unmeasured: Path | None, source: Path | None = None) -> Any:
    """The mesh without its triangles of surface nobody scanned (`unmeasured_file`), for the
    registration: fitted to Poisson's own surface, a pose would move every pixel of the study.
    None of it scanned (a random cloud): bad input naming `source`."""
    if unmeasured is None:
        return mesh
    mask = load_unmeasured(unmeasured, len(mesh.triangles))
    if mask is not None and mask.all():
        raise InputError(source, f"every one of the {len(mask)} triangles meshed from the cloud lies off "
                                 "its points (a vertex beyond --surface-gap-m from the points' planes): the "
                                 "cloud shows no surface to measure a camera against (random points, or far "
                                 "too sparse)")
    part = copy.deepcopy(mesh)
    part.remove_triangles_by_mask(mask)
    part.remove_unreferenced_vertices()
    return part


def sample_reference_points(mesh: Any, n: int = 400_000, seed: int = 0) -> Any:
    """Uniform points on the mesh, the target cloud for ICP and the c2c distance."""
    o3d = open3d()

    o3d.utility.random.seed(seed)
    return mesh.sample_points_uniformly(number_of_points=n)
