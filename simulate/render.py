"""Ray casting of a scene into per-pixel truth: z-depth, normal, inclination, albedo, edges; colour and IR.

Rays go through pixel centres at integer (u, v) (librealsense convention; Open3D's own
create_rays_pinhole adds 0.5, so the rays are built here). Directions have z = 1 in the camera
frame, so the hit parameter t of RaycastingScene is the z-depth itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.camera import Intrinsics
from simulate.effects.base import PixelContext
from simulate.scene import Scene

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

    def context(self, baseline_m: float, time_s: float = 0.0, temperature_c: float = 40.0) -> PixelContext:
        """Effect context of this view (depth camera)."""
        h, w = self.z_m.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        i = self.intrinsics
        return PixelContext(z_m=self.z_m, inclination_deg=self.inclination_deg, u=u, v=v,
                            albedo=self.albedo, time_s=time_s, temperature_c=temperature_c,
                            edge_distance_px=self.edge_distance_px, fx=i.fx, ppx=i.ppx, ppy=i.ppy,
                            baseline_m=baseline_m)


def camera_rays(intr: Intrinsics, cam_to_world: NDArray[Any], sub: tuple[float, float] = (0.0, 0.0)) -> F32:
    """HxWx6 rays (origin, direction with camera-frame z = 1) through pixel centres + `sub` px."""
    pose = np.asarray(cam_to_world, dtype=np.float64)
    x = ((np.arange(intr.width) + sub[0] - intr.ppx) / intr.fx).astype(np.float32)
    y = ((np.arange(intr.height) + sub[1] - intr.ppy) / intr.fy).astype(np.float32)
    r = pose[:3, :3].astype(np.float32)
    rays = np.empty((intr.height, intr.width, 6), dtype=np.float32)
    rays[..., :3] = pose[:3, 3]
    for k in range(3):  # world direction = R @ (x, y, 1), separable in x and y
        rays[..., 3 + k] = y[:, None] * r[k, 1] + (x[None, :] * r[k, 0] + r[k, 2])
    return rays


def _cast(rc: Any, rays: F32) -> dict[str, NDArray[Any]]:
    import open3d

    o3d: Any = open3d
    res = rc.cast_rays(o3d.core.Tensor(rays))
    return {k: res[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_normals")}


def edge_distance(z: F32, jump: float = EDGE_JUMP) -> F32:
    """Distance (px) of every pixel to the nearest depth discontinuity (0.5 for pixels touching one)."""
    import cv2

    zz = np.where(np.isfinite(z), z, np.float32(1e6))
    edge = np.zeros(z.shape, dtype=bool)
    dx = np.abs(np.diff(zz, axis=1)) > jump * np.minimum(zz[:, 1:], zz[:, :-1])
    dy = np.abs(np.diff(zz, axis=0)) > jump * np.minimum(zz[1:, :], zz[:-1, :])
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    edge[1:, :] |= dy
    edge[:-1, :] |= dy
    if not edge.any():
        return np.full(z.shape, np.inf, dtype=np.float32)
    dist = cv2.distanceTransform(np.where(edge, 0, 255).astype(np.uint8), cv2.DIST_L2, 5)
    return (dist + 0.5).astype(np.float32)


def render_geometry(scene: Scene, intr: Intrinsics, cam_to_world: NDArray[Any],
                    rc: Any = None, edges: bool = True) -> GeometryMaps:
    """Cast one ray per pixel centre and return the per-pixel truth of the view."""
    rc = rc if rc is not None else scene.raycasting_scene()
    pose = np.asarray(cam_to_world, dtype=np.float64)
    rays = camera_rays(intr, pose)
    res = _cast(rc, rays)
    t = res["t_hit"]
    hit = np.isfinite(t)
    gid = np.where(hit, res["geometry_ids"].astype(np.int32), np.int32(-1))
    z = np.where(hit, t, np.float32(np.nan)).astype(np.float32)
    # normals into the camera frame: n_c = R^T n_w
    n_c = res["primitive_normals"] @ pose[:3, :3].astype(np.float32)
    x = ((np.arange(intr.width) - intr.ppx) / intr.fx).astype(np.float32)
    y = ((np.arange(intr.height) - intr.ppy) / intr.fy).astype(np.float32)
    dot = n_c[..., 0] * x[None, :] + n_c[..., 1] * y[:, None] + n_c[..., 2]
    flip = dot > 0  # face the camera
    n_c[flip] *= -1
    ray_len = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    cos = np.abs(dot) / ray_len
    inc = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))).astype(np.float32)
    inc[~hit] = np.nan
    zt = np.where(hit, t, np.float32(0.0))
    pts = rays[..., :3] + rays[..., 3:] * zt[..., None]
    pts[~hit] = np.nan
    albedo = np.full(z.shape, np.nan, dtype=np.float32)
    for i, s in enumerate(scene.surfaces):
        m = gid == i
        if not m.any():
            continue
        albedo[m] = scene.board_albedo(pts[m, 0], pts[m, 1]) if s.board_face else s.albedo
    edist = edge_distance(z) if edges else np.full(z.shape, np.inf, dtype=np.float32)
    return GeometryMaps(z, n_c, inc, albedo, gid, pts, edist, intr, pose)


def _shade(albedo: NDArray[Any], tint: NDArray[Any], cos_inc: NDArray[Any]) -> F32:
    """Linear radiance (0..1) of Lambertian surfaces lit by room light and a light near the camera."""
    return np.asarray((albedo * (AMBIENT + DIFFUSE * cos_inc))[..., None] * tint * EXPOSURE, dtype=np.float32)


def render_color_linear(scene: Scene, intr: Intrinsics, cam_to_world: NDArray[Any], rc: Any = None,
                        supersample: int = 3) -> F32:
    """HxWx3 linear radiance of a view; the board print is antialiased by S x S subsamples per pixel.

    Pixels whose centre or neighbour sees the board face are resampled analytically on the board
    plane (z = 0 of the board frame); the rest keep their centre sample.
    """
    g = render_geometry(scene, intr, cam_to_world, rc, edges=False)
    tints = np.array([s.tint for s in scene.surfaces] + [(0.0, 0.0, 0.0)], dtype=np.float32)
    cos = np.cos(np.radians(np.nan_to_num(g.inclination_deg, nan=90.0)))
    alb = np.nan_to_num(g.albedo, nan=0.0)
    img = _shade(alb, tints[g.surface], cos)
    board_ids = [i for i, s in enumerate(scene.surfaces) if s.board_face]
    if not board_ids or scene.board is None or supersample <= 1:
        return img
    import cv2

    on_board = np.isin(g.surface, board_ids)
    near = cv2.dilate(on_board.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    vv, uu = np.nonzero(near)
    if vv.size == 0:
        return img
    pose = g.cam_to_world
    origin = pose[:3, 3]
    if abs(origin[2]) < 1e-9:
        return img
    b = scene.board
    w, h = b.size_m
    m = b.plate_margin_m
    # the board face's shading depends on the ray only: take it at the pixel centre
    dc = np.stack([(uu - intr.ppx) / intr.fx, (vv - intr.ppy) / intr.fy, np.ones(uu.size)], axis=1)
    dw0 = dc @ pose[:3, :3].T
    k = EXPOSURE * (AMBIENT + DIFFUSE * np.abs(dw0[:, 2]) / np.sqrt(np.sum(dw0 * dw0, axis=1)))
    sum_a = np.zeros(vv.size)
    n_off = np.zeros(vv.size)
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    r = pose[:3, :3]
    for dy in offs:
        for dx in offs:
            xs = (uu + dx - intr.ppx) / intr.fx
            ys = (vv + dy - intr.ppy) / intr.fy
            dwx = r[0, 0] * xs + r[0, 1] * ys + r[0, 2]
            dwy = r[1, 0] * xs + r[1, 1] * ys + r[1, 2]
            dwz = r[2, 0] * xs + r[2, 1] * ys + r[2, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -origin[2] / dwz
            px = origin[0] + dwx * t
            py = origin[1] + dwy * t
            on = (t > 0) & (px >= -m) & (px <= w + m) & (py >= -m) & (py <= h + m)
            sum_a += np.where(on, scene.board_albedo(px, py), 0.0)
            n_off += ~on
    centre = img[vv, uu].astype(np.float64)
    acc = (sum_a * k)[:, None] + n_off[:, None] * centre
    img[vv, uu] = (acc / supersample**2).astype(np.float32)
    return img


def encode_srgb(linear: F32) -> NDArray[np.uint8]:
    """Camera response: gamma 1/2.2 to 8 bit (no noise)."""
    return np.clip(255.0 * np.power(np.clip(linear, 0, 1), 1 / 2.2) + 0.5, 0, 255).astype(np.uint8)


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
