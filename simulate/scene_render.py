"""Ray casting of a scene into per-pixel truth: z-depth, normal, inclination, albedo, edges; colour and IR.

Rays go through pixel centres at integer (u, v) (librealsense convention; Open3D's own
create_rays_pinhole adds 0.5, so the rays are built here, by `core.raster.fill_rays`). Directions
have z = 1 in the camera frame, so the hit parameter t of RaycastingScene is the z-depth itself.
A `SceneRaster` (the scene's mesh rasterised, `core.raster`) gives the same hits as Open3D's ray
casting for pinhole views at a fraction of the cost; `simulate scan` renders its frames with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.raster import MeshRaster, clip_polygon, fill_rays, pinhole_axes, world_direction
from depthstation.simulate.effects.base import PixelContext
from depthstation.simulate.scene import BLACK_ALBEDO, WHITE_ALBEDO, Scene

F32 = NDArray[np.float32]
AMBIENT = 0.3  # share of diffuse room light, independent of the surface orientation
DIFFUSE = 0.6  # light from near the camera (the operator's side), Lambertian
EXPOSURE = 1.15
EDGE_JUMP = 0.03  # relative z jump between neighbours that counts as a depth edge


@dataclass
class GeometryMaps:
    """Ground truth of one view. NaN / -1 where a ray hits nothing."""

    z_m: F32  # HxW z-depth
    normal: F32  # HxWx3 unit normal in the camera frame, facing the camera
    inclination_deg: F32  # HxW angle between ray and normal, [0, 90]
    albedo: F32  # HxW reflectance 0..1
    surface: NDArray[np.int32]  # HxW index into scene.surfaces, -1 = no hit
    points_world: F32  # HxWx3 hit points in the world (= board) frame
    edge_distance_px: F32  # HxW distance to the nearest depth edge (0.5 next to it; inf if none)
    intrinsics: Intrinsics
    cam_to_world: NDArray[np.float64]
    cos_inc: F32 | None = None  # HxW cosine of the inclination (0 where nothing is hit)

    def context(self, baseline_m: float, time_s: float = 0.0, temperature_c: float = 40.0,
                stereo: Intrinsics | None = None, fx_ref: float | None = None) -> PixelContext:
        """Effect context of this view (depth camera).

        `stereo`: the stereo imager's own intrinsics when the rendered depth is aligned to another
        camera; pixel positions and the focal length then go to the effects in its pixels.
        `fx_ref`: the camera's depth focal length in its 1280-wide mode (`CameraPreset.reference_fx`;
        None: the D455's), what the unit's errors stated in px are scaled against.
        """
        h, w = self.z_m.shape
        v, u = _pixel_grid(h, w)
        i = self.intrinsics
        edge = self.edge_distance_px
        if stereo is not None:
            u = (stereo.ppx + (u - i.ppx) * (stereo.fx / i.fx)).astype(np.float32)
            v = (stereo.ppy + (v - i.ppy) * (stereo.fy / i.fy)).astype(np.float32)
            edge = (edge * (stereo.fx / i.fx)).astype(np.float32)
            i = stereo
        return PixelContext(z_m=self.z_m, inclination_deg=self.inclination_deg, u=u, v=v,
                            albedo=self.albedo, time_s=time_s, temperature_c=temperature_c,
                            edge_distance_px=edge, fx=i.fx, ppx=i.ppx, ppy=i.ppy,
                            baseline_m=baseline_m,
                            **({} if fx_ref is None else {"fx_ref": float(fx_ref)}))


@lru_cache(maxsize=8)
def _pixel_grid(h: int, w: int) -> tuple[F32, F32]:
    """(v, u) pixel coordinates of an h x w image as float32 maps, made once; read-only."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    v.setflags(write=False)
    u.setflags(write=False)
    return v, u


@lru_cache(maxsize=8)
def _pixel_rays(intr: Intrinsics) -> F32:
    """`pixel_rays` of a stream, computed once (every view of a sequence needs them); read-only."""
    d = pixel_rays(intr)
    d.setflags(write=False)
    return d


def camera_rays(intr: Intrinsics, cam_to_world: NDArray[Any]) -> F32:
    """HxWx6 world rays (origin, direction with camera-frame z = 1) through the pixel centres."""
    pose = np.asarray(cam_to_world, dtype=np.float64)
    rays = np.empty((intr.height, intr.width, 6), dtype=np.float32)
    fill_rays(rays.reshape(-1, 6), np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]),
              _pixel_rays(intr).reshape(-1, 3))
    return rays


class SceneRaster:
    """The scene's surfaces as one rasterised mesh (`core.raster.MeshRaster`): for a pinhole view
    the hits Open3D's ray casting gives (geometry id = surface index), for a view with lens
    distortion the rays are cast by an Open3D scene built when first needed."""

    def __init__(self, scene: Scene) -> None:
        verts, tris, off = [], [], 0
        for s in scene.surfaces:
            verts.append(np.asarray(s.vertices, dtype=np.float64))
            tris.append(np.asarray(s.triangles, dtype=np.int64) + off)
            off += len(s.vertices)
        self.scene = scene
        self.raster = MeshRaster(np.concatenate(verts), np.concatenate(tris))
        # per triangle rank (`cast_indexed`'s ids), the surface it belongs to
        self.surface_of = np.repeat(np.arange(len(scene.surfaces), dtype=np.int64),
                                    [len(t) for t in tris]).astype(np.uint32)[self.raster.perm]
        self._rc: Any = None

    def raycasting_scene(self) -> Any:
        """Open3D's scene of the same surfaces, built when first needed (views with lens distortion,
        whose rays are not a pinhole grid)."""
        if self._rc is None:
            self._rc = self.scene.raycasting_scene()
        return self._rc

    def cast_indexed(self, intr: Intrinsics,
                     cam_to_world: NDArray[Any]) -> tuple[F32, NDArray[np.int32], F32]:
        """Pinhole view only: t_hit (inf = miss) and hit triangle's rank (-1 = miss; `surface_of`
        and the table take it) per pixel, and the unit normal per triangle rank (valid for the ranks
        returned): no rays, no per-pixel normals to copy."""
        n = intr.width * intr.height
        t = np.empty(n, np.float32)
        ids = np.empty(n, np.int32)
        self.raster.render(intr, cam_to_world, t, ids, ranks=True)
        return t, ids, self.raster.normal_table()


def _cast(rc: Any, rays: F32) -> dict[str, NDArray[Any]]:
    """t_hit, geometry_ids and primitive_normals of `rays` by Open3D's ray casting."""
    if isinstance(rc, SceneRaster):
        rc = rc.raycasting_scene()
    import open3d

    o3d: Any = open3d
    res = rc.cast_rays(o3d.core.Tensor(rays))
    return {k: res[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_normals")}


def edge_distance(z: F32, jump: float = EDGE_JUMP) -> F32:
    """Distance (px) of every pixel to the nearest depth discontinuity (0.5 for pixels touching one)."""
    img = np.empty(z.shape, np.uint8)
    if not _edge_image(np.ascontiguousarray(z, dtype=np.float32), np.float32(jump), img):
        return np.full(z.shape, np.inf, dtype=np.float32)
    dist = np.asarray(cv2.distanceTransform(img, cv2.DIST_L2, 5), dtype=np.float32)
    dist += np.float32(0.5)
    return dist


@njit(cache=True, nogil=True)
def _edge_image(z: Any, jump: Any, out: Any) -> bool:  # pragma: no cover
    """out = 0 on both pixels of every neighbour pair (row or column) whose z differs by more than
    `jump` times the nearer one (no depth counts as 1e6 m), 255 elsewhere; whether any edge exists."""
    h, w = z.shape
    far = np.float32(1e6)
    out[:] = 255
    found = False
    for v in range(h):
        for u in range(w):
            a = z[v, u]
            if not np.isfinite(a):
                a = far
            if u + 1 < w:
                b = z[v, u + 1]
                if not np.isfinite(b):
                    b = far
                if abs(b - a) > jump * min(a, b):
                    out[v, u] = 0
                    out[v, u + 1] = 0
                    found = True
            if v + 1 < h:
                b = z[v + 1, u]
                if not np.isfinite(b):
                    b = far
                if abs(b - a) > jump * min(a, b):
                    out[v, u] = 0
                    out[v + 1, u] = 0
                    found = True
    return found


@njit(inline="always")
def _miss(i: int, z: Any, cos_inc: Any, gid: Any, albedo: Any, n_c: Any, pts: Any,
          vectors: bool) -> None:  # pragma: no cover - compiled
    z[i] = np.nan
    cos_inc[i] = 0.0
    gid[i] = -1
    albedo[i] = np.nan
    if vectors:
        for k in range(3):
            n_c[i, k] = 0.0
            pts[i, k] = np.nan


@njit(inline="always")
def _facing(m0: Any, m1: Any, m2: Any, rot: Any, x: Any, y: Any) -> Any:  # pragma: no cover - compiled
    """The world normal (m0, m1, m2) in the camera frame, turned to face the camera, and the
    cosine of its angle with the camera-frame ray (x, y, 1), clipped to [0, 1] (float32)."""
    nc0 = m0 * rot[0, 0] + m1 * rot[1, 0] + m2 * rot[2, 0]
    nc1 = m0 * rot[0, 1] + m1 * rot[1, 1] + m2 * rot[2, 1]
    nc2 = m0 * rot[0, 2] + m1 * rot[1, 2] + m2 * rot[2, 2]
    dot = nc0 * x + nc1 * y + nc2
    if dot > 0:  # face the camera
        nc0, nc1, nc2, dot = -nc0, -nc1, -nc2, -dot
    return nc0, nc1, nc2, np.float32(min(max(-dot / np.sqrt(x * x + y * y + 1.0), 0.0), 1.0))


@njit(cache=True, nogil=True)
def _geometry_maps(t_hit: Any, gids: Any, normals: Any, rays: Any, dirs: Any, rot: Any,
                   surface_albedo: Any, z: Any, n_c: Any, cos_inc: Any, gid: Any, pts: Any,
                   albedo: Any, vectors: bool) -> None:  # pragma: no cover
    """Per pixel: z-depth, cosine of the inclination, surface index and the surface's albedo, and
    (`vectors`) the normal in the camera frame turned to face the camera and the world hit point
    (NaN/-1, cosine 0 on a miss)."""
    for i in range(t_hit.shape[0]):
        t = t_hit[i]
        if not np.isfinite(t):
            _miss(i, z, cos_inc, gid, albedo, n_c, pts, vectors)
            continue
        g = gids[i]
        gid[i] = g
        z[i] = t
        nc0, nc1, nc2, cos_inc[i] = _facing(normals[i, 0], normals[i, 1], normals[i, 2], rot,
                                            dirs[i, 0], dirs[i, 1])
        albedo[i] = surface_albedo[g]
        if vectors:
            n_c[i, 0], n_c[i, 1], n_c[i, 2] = nc0, nc1, nc2
            for k in range(3):
                pts[i, k] = rays[i, k] + rays[i, 3 + k] * t


@njit(cache=True, nogil=True)
def _raster_geometry_maps(t_hit: Any, ids: Any, tri_normals: Any, surface_of: Any, xs: Any, ys: Any,
                          origin: Any, rot: Any, surface_albedo: Any, z: Any, n_c: Any, cos_inc: Any,
                          gid: Any, pts: Any, albedo: Any, vectors: bool) -> None:  # pragma: no cover
    """`_geometry_maps` of a rasterised pinhole view, from hit triangles and the per-triangle normal
    table: each pixel's ray is built here with `fill_rays`' arithmetic, so every map holds the
    same floats as from a ray array and per-pixel normals, without writing and reading them."""
    w = xs.shape[0]
    o0, o1, o2 = np.float32(origin[0]), np.float32(origin[1]), np.float32(origin[2])
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    one = np.float32(1.0)
    for row in range(ys.shape[0]):
        y = ys[row]
        for col in range(w):
            i = row * w + col
            k = ids[i]
            if k < 0:
                _miss(i, z, cos_inc, gid, albedo, n_c, pts, vectors)
                continue
            t = t_hit[i]
            g = surface_of[k]
            gid[i] = g
            z[i] = t
            x = xs[col]
            nc0, nc1, nc2, cos_inc[i] = _facing(tri_normals[k, 0], tri_normals[k, 1], tri_normals[k, 2], rot,
                                                x, y)
            albedo[i] = surface_albedo[g]
            if vectors:
                n_c[i, 0], n_c[i, 1], n_c[i, 2] = nc0, nc1, nc2
                dx, dy, dz = world_direction(r00, r01, r02, r10, r11, r12, r20, r21, r22, x, y, one)
                pts[i, 0] = o0 + dx * t
                pts[i, 1] = o1 + dy * t
                pts[i, 2] = o2 + dz * t


def render_geometry(scene: Scene, intr: Intrinsics, cam_to_world: NDArray[Any],
                    rc: Any = None, edges: bool = True, inclination: bool = True,
                    vectors: bool = True) -> GeometryMaps:
    """Cast one ray per pixel centre and return the per-pixel truth of the view (`rc` None: the
    scene rasterised, `SceneRaster`; an Open3D `RaycastingScene` casts the rays itself).

    For shading, which needs no more than `cos_inc`, surface and albedo: `inclination` False leaves
    `inclination_deg` NaN, `vectors` False leaves `normal` and `points_world` NaN (read-only, no
    memory), unless board faces need their hit points for the print."""
    rc = rc if rc is not None else SceneRaster(scene)
    pose = np.asarray(cam_to_world, dtype=np.float64)
    h, w = intr.height, intr.width
    vectors = vectors or any(s.board_face for s in scene.surfaces)
    z = np.empty((h, w), np.float32)
    cos_inc = np.empty((h, w), np.float32)
    gid = np.empty((h, w), np.int32)
    albedo = np.empty((h, w), np.float32)
    if vectors:
        n_c = np.empty((h, w, 3), np.float32)
        pts = np.empty((h, w, 3), np.float32)
        flat_nc, flat_pts = n_c.reshape(-1, 3), pts.reshape(-1, 3)
    else:
        n_c = pts = np.broadcast_to(np.float32(np.nan), (h, w, 3))
        flat_nc = flat_pts = np.zeros((0, 3), np.float32)  # the kernels leave them alone
    surface_albedo = _surface_albedo(scene)
    rot = np.ascontiguousarray(pose[:3, :3])
    if isinstance(rc, SceneRaster) and not intr.has_distortion:
        t, ids, tri_normals = rc.cast_indexed(intr, pose)
        xs, ys = pinhole_axes(intr)
        _raster_geometry_maps(t, ids, tri_normals, rc.surface_of, xs, ys, np.ascontiguousarray(pose[:3, 3]),
                              rot, surface_albedo, z.reshape(-1), flat_nc, cos_inc.reshape(-1),
                              gid.reshape(-1), flat_pts, albedo.reshape(-1), vectors)
    else:
        rays = camera_rays(intr, pose)
        res = _cast(rc, rays)
        _geometry_maps(res["t_hit"].reshape(-1), res["geometry_ids"].reshape(-1).astype(np.int64),
                       res["primitive_normals"].reshape(-1, 3), rays.reshape(-1, 6),
                       _pixel_rays(intr).reshape(-1, 3), rot, surface_albedo, z.reshape(-1),
                       flat_nc, cos_inc.reshape(-1), gid.reshape(-1), flat_pts, albedo.reshape(-1), vectors)
    if inclination:  # float32 degrees of the float32 cosine (numpy's vectorised arccos)
        inc = np.arccos(cos_inc)
        np.degrees(inc, out=inc)
        inc[gid < 0] = np.nan
    else:
        inc = np.full((h, w), np.nan, np.float32)
    for i, s in enumerate(scene.surfaces):
        if s.board_face:
            m = gid == i
            if m.any():
                albedo[m] = scene.board_albedo(pts[m, 0], pts[m, 1])
    edist = edge_distance(z) if edges else np.full(z.shape, np.inf, dtype=np.float32)
    return GeometryMaps(z, n_c, inc, albedo, gid, pts, edist, intr, pose, cos_inc)


def _surface_albedo(scene: Scene) -> F32:
    """Albedo per surface (NaN for board faces: their print is looked up per hit point)."""
    return np.array([np.nan if s.board_face else s.albedo for s in scene.surfaces], np.float32)


@njit(cache=True, nogil=True)
def _shade(albedo: Any, surface: Any, cos_inc: Any, tints: Any, out: Any) -> None:  # pragma: no cover
    """Linear radiance (0..1) of Lambertian surfaces lit by room light and a light near the camera:
    out = albedo (A + D cos) tint E per pixel, float32 (no hit, or NaN albedo: 0; tint of no hit:
    the table's last row)."""
    amb, dif, exp_ = np.float32(AMBIENT), np.float32(DIFFUSE), np.float32(EXPOSURE)
    last = tints.shape[0] - 1
    for i in range(albedo.shape[0]):
        a = albedo[i]
        if np.isnan(a):
            a = np.float32(0.0)
        k = surface[i] if surface[i] >= 0 else last
        s = a * (amb + dif * cos_inc[i])
        for c in range(3):
            out[i, c] = s * tints[k, c] * exp_


def render_color_linear(scene: Scene, intr: Intrinsics, cam_to_world: NDArray[Any], rc: Any = None,
                        psf_sigma_px: float = 0.0) -> F32:
    """HxWx3 linear radiance of a view; the board print carries its exact pixel-area coverage.

    Every pixel integrates the image over its footprint (a box filter, as a sensor pixel does):
    the plate face and each dark region of the print (black squares, ChArUco marker cells) are
    projected as polygons (a plane maps to the image by a homography, so straight edges stay
    straight) and their exact area inside each pixel square is rasterised (`polygon_coverage`).
    Sub-pixel samples would instead put every edge on a 1/S px grid, a static corner bias that
    tilts the board's PnP pose by up to a degree. Off the plate the pixel keeps its centre ray;
    along the plate outline the uncovered part takes the colour of a neighbour off the plate.
    `psf_sigma_px` > 0 adds a Gaussian optical blur (lens + demosaicing PSF) in linear light.
    """
    if intr.has_distortion:
        # the print's exact coverage is a pinhole construction: render the ideal image, then let
        # the lens bend it (each distorted pixel samples the pinhole image along its own ray)
        ideal = render_color_linear(scene, intr.pinhole(), cam_to_world, rc, psf_sigma_px)
        d = _pixel_rays(intr)
        map_u = (d[..., 0] * intr.fx + intr.ppx).astype(np.float32)
        map_v = (d[..., 1] * intr.fy + intr.ppy).astype(np.float32)
        return np.asarray(cv2.remap(ideal, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                          dtype=np.float32)
    g = render_geometry(scene, intr, cam_to_world, rc, edges=False, inclination=False, vectors=False)
    tints = np.array([s.tint for s in scene.surfaces] + [(0.0, 0.0, 0.0)], dtype=np.float32)
    assert g.cos_inc is not None
    cos = g.cos_inc
    img = np.empty((intr.height, intr.width, 3), np.float32)
    _shade(g.albedo.reshape(-1), g.surface.reshape(-1), cos.reshape(-1), tints, img.reshape(-1, 3))
    board_ids = [i for i, s in enumerate(scene.surfaces) if s.board_face]
    if board_ids and scene.board is not None:
        img = _board_print(scene, intr, g, board_ids, img)
    if psf_sigma_px > 0:

        k = 2 * int(np.ceil(3.5 * psf_sigma_px)) + 1
        img = np.asarray(cv2.GaussianBlur(img, (k, k), psf_sigma_px, borderType=cv2.BORDER_REPLICATE),
                         dtype=np.float32)
    return np.asarray(img, dtype=np.float32)


def _board_print(scene: Scene, intr: Intrinsics, g: GeometryMaps, board_ids: list[int], img: F32) -> F32:
    """Replace the board face's pixels by their area-exact mix of plate white and print black."""

    board = scene.board
    assert board is not None
    pose = g.cam_to_world
    world_to_cam = np.asarray(np.linalg.inv(pose), dtype=np.float64)
    w, h = board.size_m
    m = board.plate_margin_m
    plate = np.array([[-m, -m, w + m, h + m]])
    dark = dark_rectangles(scene)
    cov_plate = polygon_coverage(_rect_quads(plate, world_to_cam), intr)
    if not cov_plate.any():
        return img
    cov_dark = polygon_coverage(_rect_quads(dark, world_to_cam), intr) if len(dark) else 0.0 * cov_plate
    cov_dark = np.minimum(cov_dark, cov_plate)
    on_face = np.isin(g.surface, board_ids)
    # the print only changes the plate's box: outside it the image stays as shaded (the mix below
    # is exactly `img` where neither the plate's area nor a face hit touches a pixel)
    act = (cov_plate > 0) | on_face
    rows, cols = np.flatnonzero(act.any(axis=1)), np.flatnonzero(act.any(axis=0))
    box = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    # shading of the face depends on the ray only (room light + light at the camera), at the centre
    x = ((np.arange(intr.width) - intr.ppx) / intr.fx)[box[1]]
    y = ((np.arange(intr.height) - intr.ppy) / intr.fy)[box[0]]
    r = pose[:3, :3]
    dz = y[:, None] * r[2, 1] + (x[None, :] * r[2, 0] + r[2, 2])
    cos_face = np.abs(dz) / np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    k = EXPOSURE * (AMBIENT + DIFFUSE * cos_face)
    cp, cd = cov_plate[box], cov_dark[box]
    albedo = WHITE_ALBEDO * (cp - cd) + BLACK_ALBEDO * cd
    tint = np.asarray(scene.surfaces[board_ids[0]].tint, dtype=np.float64)
    face = (albedo * k)[..., None] * tint
    # what lies beyond the plate's outline: the centre colour of a neighbour that misses the face
    bg = img.copy()
    # pixels of the outline (few): each takes the first neighbour off the face, in this order
    # (indices wrap at the image border, as np.roll's would)
    tv, tu = np.nonzero(on_face & (cov_plate < 1.0))
    hgt, wid = on_face.shape
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (1, -1), (-1, 1)):
        if not tv.size:
            break
        sv, su = (tv - dv) % hgt, (tu - du) % wid
        take = ~on_face[sv, su]
        bg[tv[take], tu[take]] = img[sv[take], su[take]]
        tv, tu = tv[~take], tu[~take]
    out = np.array(img, dtype=np.float32)
    out[box] = face + (1.0 - cp)[..., None] * bg[box]
    return out


def dark_rectangles(scene: Scene) -> NDArray[np.float64]:
    """Kx4 (x0, y0, x1, y1) board-frame rectangles that make up the print's dark regions.

    Plain board: its black squares. ChArUco: the texture's dark texels merged into rectangles
    (runs per row, stacked while the next row repeats them), the same print the depth albedo uses.
    """
    board = scene.board
    assert board is not None
    s = board.square_length_m
    if scene.texture is None:
        cols, rows = np.meshgrid(np.arange(board.squares_x), np.arange(board.squares_y))
        c, r = cols.ravel(), rows.ravel()
        black = board.is_black((c + 0.5) * s, (r + 0.5) * s)
        c, r = c[black], r[black]
        return np.stack([c * s, r * s, (c + 1) * s, (r + 1) * s], axis=1).astype(np.float64)

    mask = scene.texture < 0.5 * (BLACK_ALBEDO + WHITE_ALBEDO)
    ty, tx = mask.shape
    w, h = board.size_m
    rects: list[tuple[int, int, int, int]] = []
    open_: dict[tuple[int, int], int] = {}  # run (c0, c1) -> first row
    for row in range(ty + 1):
        runs: set[tuple[int, int]] = set()
        if row < ty:
            line = np.concatenate([[False], mask[row], [False]])
            d = np.flatnonzero(np.diff(line.astype(np.int8)))
            runs = {(int(a), int(b)) for a, b in zip(d[::2], d[1::2], strict=True)}
        for run in [k for k in open_ if k not in runs]:
            rects.append((run[0], open_.pop(run), run[1], row))
        for run in runs:
            open_.setdefault(run, row)
    a = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    return a * np.array([w / tx, h / ty, w / tx, h / ty])


def _rect_quads(rects: NDArray[np.float64], world_to_cam: NDArray[np.float64]) -> NDArray[np.float64]:
    """Kx4x3 camera-frame corners of board-plane (z = 0) rectangles, in one winding order."""
    x0, y0, x1, y1 = rects.T
    xs = np.stack([x0, x1, x1, x0], axis=1)
    ys = np.stack([y0, y0, y1, y1], axis=1)
    pts = np.stack([xs, ys, np.zeros_like(xs)], axis=2)
    return np.ascontiguousarray(pts @ world_to_cam[:3, :3].T + world_to_cam[:3, 3])


def polygon_coverage(quads_cam: NDArray[np.float64], intr: Intrinsics,
                     near_m: float = 1e-3) -> NDArray[np.float64]:
    """HxW exact area fraction of each pixel square [u +- 0.5] x [v +- 0.5] covered by the quads.

    Quads are planar (camera frame), disjoint and of one winding; each is clipped to z >= near,
    projected (pinhole, no distortion), clipped to the image and rasterised by signed-area
    accumulation (the box-filter rasteriser of font renderers): exact up to float rounding.
    """
    acc = _rasterize_quads(np.ascontiguousarray(quads_cam, dtype=np.float64), float(intr.fx), float(intr.fy),
                          float(intr.ppx), float(intr.ppy), int(intr.width), int(intr.height), float(near_m))
    cov = np.abs(np.cumsum(acc[:, :intr.width], axis=1))
    return np.minimum(cov, 1.0)


def encode_srgb(linear: F32) -> NDArray[np.uint8]:
    """Camera response: gamma 1/2.2 to 8 bit (no noise): 255 x^(1/2.2) + 0.5 truncated, x clipped
    to [0, 1], as numpy evaluates it in float32, read from a table (`_srgb_table`)."""
    lin = np.ascontiguousarray(linear, dtype=np.float32)
    out = np.empty(lin.shape, np.uint8)
    lo, thr = _srgb_table()
    _encode_srgb(lin.reshape(-1).view(np.uint32), lo, thr, out.reshape(-1))
    return out


def _srgb_reference(x: NDArray[np.float32]) -> NDArray[np.uint8]:
    """The response by its formula (numpy, float32): what the table reproduces."""
    return np.clip(255.0 * np.power(np.clip(x, 0, 1), 1 / 2.2) + 0.5, 0, 255).astype(np.uint8)


_SRGB_SHIFT = 12  # float32 bits >> 12: buckets of 2^11 per octave, at most one step of the response each


@lru_cache(maxsize=1)
def _srgb_table() -> tuple[NDArray[np.uint8], NDArray[np.uint32]]:
    """Per bucket of float32 bit patterns in [0, 1]: the response at its first value and the first
    bit pattern where it steps up (the bucket's end if it does not), found by bisection of the
    formula itself. The response rises by less than 0.06 counts per bucket, so one step at most."""
    n = (int(np.float32(1.0).view(np.uint32)) >> _SRGB_SHIFT) + 1
    first = np.arange(n, dtype=np.int64) << _SRGB_SHIFT
    last = first + (1 << _SRGB_SHIFT) - 1

    def at(bits: NDArray[np.int64]) -> NDArray[np.int64]:
        return _srgb_reference(bits.astype(np.uint32).view(np.float32)).astype(np.int64)
    lo_v, hi_v = at(first), at(last)
    if np.any(hi_v - lo_v > 1):
        raise RuntimeError("sRGB table: more than one step of the response in a bucket")
    a, b = first.copy(), last + 1  # invariant: at(a) == lo, at(b) > lo (b = last + 1: no step)
    steps = hi_v > lo_v
    while True:
        todo = steps & (b - a > 1)
        if not todo.any():
            break
        mid = (a + b) // 2
        up = at(mid) > lo_v
        b = np.where(todo & up, mid, b)
        a = np.where(todo & ~up, mid, a)
    thr = np.where(steps, b, last + 1).astype(np.uint32)
    return lo_v.astype(np.uint8), thr


@njit(cache=True, nogil=True)
def _encode_srgb(bits: Any, lo: Any, thr: Any, out: Any) -> None:  # pragma: no cover
    """The table's response of float32 values given as their bits (negative, NaN: 0; above 1: 255's)."""
    one = np.uint32(0x3F800000)
    sign = np.uint32(0x80000000)
    top = lo[lo.shape[0] - 1]
    for i in range(bits.shape[0]):
        b = bits[i]
        if b >= sign:  # negative (and -0, negative NaN)
            out[i] = 0
        elif b >= one:  # 1 and above, inf; NaN
            out[i] = top if b <= np.uint32(0x7F800000) else 0
        else:
            k = b >> _SRGB_SHIFT
            out[i] = lo[k] + (b >= thr[k])


class NoiseBank:
    """Sensor noise for 8-bit images: a few Gaussian fields a bit larger than a frame, read at random offsets.

    Drawing 2.7 M normals per 1280x720x3 frame costs ~30 ms; a bank of fields read at random
    (row, column) offsets gives per-frame noise with the same statistics at copy speed.
    """

    def __init__(self, shape: tuple[int, ...], sigma: float, rng: np.random.Generator,
                 fields: int = 4, pad: int = 64) -> None:
        self.shape = shape
        self.pad = pad
        big = (shape[0] + pad, shape[1] + pad, *shape[2:])
        self.fields = [np.clip(np.rint(sigma * rng.standard_normal(big, dtype=np.float32)), -127, 127)
                       .astype(np.int8) for _ in range(fields)]
        self.rng = rng

    def apply(self, img: NDArray[np.uint8], rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
        g = rng or self.rng
        f = self.fields[int(g.integers(len(self.fields)))]
        r = int(g.integers(self.pad))
        c = int(g.integers(self.pad))
        out = img.astype(np.int16)
        out += f[r:r + self.shape[0], c:c + self.shape[1]]
        np.clip(out, 0, 255, out=out)
        return out.astype(np.uint8)


# ---- exact box-filter rasteriser (numba) -------------------------------------------------------

@njit(cache=True, nogil=True)
def _line(acc: NDArray[np.float64], h: int, x0: float, y0: float, x1: float,
          y1: float) -> None:  # pragma: no cover
    """Add a directed edge's signed area to the accumulation buffer (cells [x, x+1) x [y, y+1)).

    After a prefix sum along each row, the buffer holds the signed area of the polygon inside
    every cell (font-rs' accumulation rasteriser). Coordinates lie in [0, W] x [0, H].
    """
    if y0 == y1:
        return
    d_sign = 1.0
    if y0 > y1:
        d_sign = -1.0
        x0, y0, x1, y1 = x1, y1, x0, y0
    dxdy = (x1 - x0) / (y1 - y0)
    x = x0
    ys = int(np.floor(y0))
    ye = min(h, int(np.ceil(y1)))
    for y in range(ys, ye):
        dy = min(y + 1.0, y1) - max(float(y), y0)
        xnext = x + dxdy * dy
        d = dy * d_sign
        xa, xb = (x, xnext) if x < xnext else (xnext, x)
        xaf0 = np.floor(xa)
        xai = int(xaf0)
        xbc = np.ceil(xb)
        xbi = int(xbc)
        if xbi <= xai + 1:
            xmf = 0.5 * (x + xnext) - xaf0
            acc[y, xai] += d - d * xmf
            acc[y, xai + 1] += d * xmf
        else:
            s = 1.0 / (xb - xa)
            xaf = xa - xaf0
            a0 = 0.5 * s * (1.0 - xaf) * (1.0 - xaf)
            xbf = xb - xbc + 1.0
            am = 0.5 * s * xbf * xbf
            acc[y, xai] += d * a0
            if xbi == xai + 2:
                acc[y, xai + 1] += d * (1.0 - a0 - am)
            else:
                a1 = s * (1.5 - xaf)
                acc[y, xai + 1] += d * (a1 - a0)
                for xi in range(xai + 2, xbi - 1):
                    acc[y, xi] += d * s
                a2 = a1 + (xbi - xai - 3) * s
                acc[y, xbi - 1] += d * (1.0 - a2 - am)
            acc[y, xbi] += d * am
        x = xnext


@njit(cache=True, nogil=True)
def _rasterize_quads(quads: NDArray[np.float64], fx: float, fy: float, ppx: float, ppy: float,
                     w: int, h: int, near: float) -> NDArray[np.float64]:  # pragma: no cover
    """Accumulation buffer (H x W+2) of camera-frame quads: near-clip, project, clip, rasterise."""
    acc = np.zeros((h, w + 2))
    cx = np.empty(16)
    cy = np.empty(16)
    cz = np.empty(16)
    px = np.empty(32)
    py = np.empty(32)
    ox = np.empty(32)
    oy = np.empty(32)
    for q in range(quads.shape[0]):
        # clip to z >= near in 3-D (a homography is only a polygon map in front of the camera)
        n = 0
        for i in range(4):
            j = (i + 1) % 4
            zi, zj = quads[q, i, 2], quads[q, j, 2]
            if zi >= near:
                cx[n], cy[n], cz[n] = quads[q, i, 0], quads[q, i, 1], zi
                n += 1
            if (zi >= near) != (zj >= near):
                t = (near - zi) / (zj - zi)
                cx[n] = quads[q, i, 0] + t * (quads[q, j, 0] - quads[q, i, 0])
                cy[n] = quads[q, i, 1] + t * (quads[q, j, 1] - quads[q, i, 1])
                cz[n] = near
                n += 1
        if n < 3:
            continue
        # pixel u covers [u - 0.5, u + 0.5): shift by 0.5 so cells start at integers
        for i in range(n):
            px[i] = fx * cx[i] / cz[i] + ppx + 0.5
            py[i] = fy * cy[i] / cz[i] + ppy + 0.5
        n = clip_polygon(px, py, n, 0, 0.0, True, ox, oy)
        if n >= 3:
            n = clip_polygon(px, py, n, 0, float(w), False, ox, oy)
        if n >= 3:
            n = clip_polygon(px, py, n, 1, 0.0, True, ox, oy)
        if n >= 3:
            n = clip_polygon(px, py, n, 1, float(h), False, ox, oy)
        if n < 3:
            continue
        for i in range(n):
            j = (i + 1) % n
            _line(acc, h, px[i], py[i], px[j], py[j])
    return acc
