"""A small known world for tests and benchmarks: a box room with a round table, a walk around the
table, and depth frames from an analytic renderer with a known bias/noise signature.

Why analytic: the truth (z-depth, inclination) comes from exact ray/box and ray/cylinder
intersections, independent of the Open3D mesh path the study uses, so a wrong pixel convention,
a wrong depth definition or a sign error in the study shows up as a mismatch.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import look_at
from depthstation.core.lazy_open3d import open3d

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Room:
    """Axis-aligned room [0, size] (z up) and a vertical cylinder table with a top disk."""

    size_m: tuple[float, float, float] = (6.0, 5.0, 2.8)
    table_center_m: tuple[float, float] = (3.0, 2.5)
    table_radius_m: float = 0.6
    table_height_m: float = 0.75

    def mesh(self, segments: int = 256, subdivide_walls: int = 0) -> Any:
        """Open3D TriangleMesh (legacy) of walls (inward normals), floor, ceiling and table."""
        o3d = open3d()

        sx, sy, sz = self.size_m
        box = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
        box.triangles = o3d.utility.Vector3iVector(np.asarray(box.triangles)[:, ::-1].copy())
        if subdivide_walls:
            box = box.subdivide_midpoint(subdivide_walls)
        cx, cy = self.table_center_m
        r, h = self.table_radius_m, self.table_height_m
        ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        ring = np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], axis=-1)
        verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.full(segments, h)],
                                [[cx, cy, h]]])
        tris = []
        for i in range(segments):
            j = (i + 1) % segments
            tris += [[i, j, segments + j], [i, segments + j, segments + i],
                     [2 * segments, segments + i, segments + j]]
        table = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                          o3d.utility.Vector3iVector(np.asarray(tris)))
        mesh = box + table
        mesh.compute_triangle_normals()
        return mesh

    def intersect(self, origin: F64, dirs: F64) -> tuple[F64, F64]:
        """Exact first hit of rays (origin, dirs Nx3) with room and table: (t, unit normals)."""
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        size = np.asarray(self.size_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(d > 0, size, 0.0)
            t_axes = np.where(d != 0, (bound - o) / d, np.inf)
        axis = np.argmin(t_axes, axis=1)
        t = t_axes[np.arange(d.shape[0]), axis]
        n = np.zeros_like(d)
        n[np.arange(d.shape[0]), axis] = -np.sign(d[np.arange(d.shape[0]), axis])
        cx, cy = self.table_center_m
        r, h = self.table_radius_m, self.table_height_m
        px, py = o[0] - cx, o[1] - cy
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2 * (px * d[:, 0] + py * d[:, 1])
        c = px * px + py * py - r * r
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            tc = (-b - np.sqrt(disc)) / (2 * a)
        zc = o[2] + tc * d[:, 2]
        side = (disc > 0) & (tc > 0) & (zc >= 0) & (zc <= h) & (tc < t)
        t = np.where(side, tc, t)
        hx, hy = px + tc * d[:, 0], py + tc * d[:, 1]
        n[side] = np.stack([hx[side] / r, hy[side] / r, np.zeros(side.sum())], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = (h - o[2]) / d[:, 2]
        tx, ty = px + tt * d[:, 0], py + tt * d[:, 1]
        top = (d[:, 2] < 0) & (tt > 0) & (tx * tx + ty * ty <= r * r) & (tt < t)
        t = np.where(top, tt, t)
        n[top] = [0.0, 0.0, 1.0]
        return t, n


def walk_around_table(room: Room, frames: int, radius_m: float = 1.8, height_m: float = 1.5,
                      laps: float = 1.0, pitch_down: float = 0.35) -> F64:
    """Camera-to-world poses (OpenCV axes) on a circle around the table, looking where it walks."""
    cx, cy = room.table_center_m
    poses = np.empty((frames, 4, 4))
    for k in range(frames):
        a = 2 * np.pi * laps * k / frames
        eye = np.array([cx + radius_m * np.cos(a), cy + radius_m * np.sin(a), height_m])
        tangent = np.array([-np.sin(a), np.cos(a), 0.0])
        inward = np.array([-np.cos(a), -np.sin(a), 0.0])
        target = eye + tangent + 0.35 * inward + np.array([0.0, 0.0, -pitch_down])
        poses[k] = look_at(eye, target, (0.0, 0.0, 1.0))
    return poses


@dataclass(frozen=True)
class ErrorModel:
    """Known signature: z_meas = scale z + a z^2 + b (inc/90)^2 + N(0, (s z^2)^2); no depth beyond
    the limits. `scale` != 1 is what a registration with scale absorbs (paper: 0.98288)."""

    scale: float = 1.0
    a_per_m: float = 0.002
    b_m: float = 0.004
    sigma_per_m: float = 0.0015
    max_inclination_deg: float = 86.0
    max_z_m: float = 5.8
    min_z_m: float = 0.3

    def bias_m(self, z_m: F64, inclination_deg: F64) -> F64:
        return (self.scale - 1.0) * z_m + self.a_per_m * z_m**2 + self.b_m * (inclination_deg / 90.0) ** 2

    def sigma_m(self, z_m: F64) -> F64:
        return self.sigma_per_m * z_m**2


def render_truth(room: Room, intr: Intrinsics, pose: F64) -> tuple[F64, F64]:
    """True z-depth and inclination (HxW) through integer pixel centres (DESIGN §2)."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    dc = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones_like(u)], -1).reshape(-1, 3)
    dw = dc @ pose[:3, :3].T
    t, n = room.intersect(pose[:3, 3], dw)
    cos = np.abs((n * dw).sum(1)) / np.linalg.norm(dw, axis=1)
    inc = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    shape = (intr.height, intr.width)
    return t.reshape(shape), inc.reshape(shape)


def measure(z_true: F64, inc: F64, model: ErrorModel, depth_units_m: float,
            rng: np.random.Generator) -> NDArray[np.uint16]:
    """z16 depth counts: truth + bias + Gaussian noise, rounded; 0 where the model drops out."""
    z = z_true + model.bias_m(z_true, inc) + rng.normal(0.0, 1.0, z_true.shape) * model.sigma_m(z_true)
    counts = np.rint(z / depth_units_m)
    drop = ((inc > model.max_inclination_deg) | (z_true > model.max_z_m) | (z_true < model.min_z_m)
            | ~np.isfinite(counts) | (counts <= 0) | (counts > 65535))
    return np.where(drop, 0, counts).astype(np.uint16)


@dataclass
class SyntheticSequence:
    """An in-memory, picklable frame source (FrameSource protocol) with its truth poses."""

    info: StreamInfo
    depth: list[NDArray[np.uint16]]
    timestamps_ns: list[int]
    poses: F64
    name: str = "synthetic"
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def frame_count(self) -> int | None:
        return len(self.depth)

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        stop = len(self.depth) if limit is None else min(len(self.depth), start + limit)
        for i in range(start, stop):
            yield FrameSet(index=i, timestamp_ns=self.timestamps_ns[i], depth=self.depth[i])


def make_sequence(frames: int = 24, width: int = 160, height: int = 120, *, room: Room = Room(),
                  model: ErrorModel = ErrorModel(), depth_units_m: float = 1e-4, seed: int = 0,
                  hfov_deg: float = 87.0, t0_ns: int = 1_700_000_000_000_000_000) -> SyntheticSequence:
    """Render the walk: truth from the analytic room, errors from `model`."""
    fx = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    intr = Intrinsics(width, height, fx, fx, (width - 1) / 2 + 0.3, (height - 1) / 2 - 0.2)
    info = StreamInfo(depth_intrinsics=intr, color_intrinsics=None, depth_units_m=depth_units_m, fps=30.0)
    poses = walk_around_table(room, frames)
    rng = np.random.default_rng(seed)
    depth = []
    for pose in poses:
        z, inc = render_truth(room, intr, pose)
        depth.append(measure(z, inc, model, depth_units_m, rng))
    stamps = [t0_ns + round(k * 1e9 / 30) for k in range(frames)]
    return SyntheticSequence(info, depth, stamps, poses,
                             metadata={"model": model.__dict__, "room": room.__dict__})


def write_tum_folder(seq: SyntheticSequence, out: Path) -> Path:
    """The sequence as a TUM RGB-D folder (depth/*.png, depth.txt, camera.json)."""
    out = Path(out)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp filename"]
    for fs in seq.frames():
        name = f"depth/{fs.timestamp_ns / 1e9:.6f}.png"
        assert fs.depth is not None
        cv2.imwrite(str(out / name), fs.depth)
        lines.append(f"{fs.timestamp_ns / 1e9:.6f} {name}")
    (out / "depth.txt").write_text("\n".join(lines) + "\n")
    cam = {**seq.info.depth_intrinsics.to_dict(), "depth_units_m": seq.info.depth_units_m}
    (out / "camera.json").write_text(json.dumps(cam, indent=2))
    return out
