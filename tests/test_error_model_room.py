"""The error-model tests' own world (no tests here): a numpy ray cast of an empty box room, walks of
a pinhole camera in it, and a known depth error field b(z, theta) + noise sigma(z, theta) added to
the true z-depth. Independent of the simulator and of the scan study's casting on purpose: the
study and `correct` must find what this file put in.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import look_at
from depthstation.evaluate.scan.trajectory import write_tum

ROOM = np.array([6.0, 5.0, 2.8])          # the box [0, ROOM]
UNITS = 1e-4                              # depth counts of 0.1 mm
MAX_THETA_DEG = 78.0                      # beyond: no depth (a stereo camera's grazing limit)
MAX_Z_M = 5.0
# the known field: b = B_OFFSET + B_DISP z^2 + B_INCL z^2 tan(theta); sigma = S0 + S2 z^2
B_OFFSET, B_DISP, B_INCL = 0.002, 0.0015, 0.0015
S0, S2 = 0.0005, 0.0008
DEVICE = {"name": "Intel RealSense D455", "serial_number": "TEST0001", "firmware_version": "5.16.0.1",
          "depth_units_m": UNITS, "baseline_m": 0.095}


def bias_m(z: NDArray[np.float64], theta_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    return B_OFFSET + B_DISP * z ** 2 + B_INCL * z ** 2 * np.tan(np.radians(theta_deg))


def sigma_m(z: NDArray[np.float64]) -> NDArray[np.float64]:
    return S0 + S2 * z ** 2


def intrinsics(width: int = 160, height: int = 120) -> Intrinsics:
    f = 100.0 * width / 160
    return Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)


def info(width: int = 160, height: int = 120) -> StreamInfo:
    return StreamInfo(depth_intrinsics=intrinsics(width, height), color_intrinsics=None, depth_units_m=UNITS,
                      baseline_m=0.095, fps=30.0, device=dict(DEVICE))


def cast(intr: Intrinsics, pose: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True z-depth (m) and inclination (deg) of every pixel of a camera (camera-to-world `pose`)
    inside the box: the nearest of the six walls along each ray."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    d_cam = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones_like(u)], axis=-1)
    d = d_cam @ pose[:3, :3].T
    o = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (ROOM - o) / d
        t_lo = (0.0 - o) / d
    t_axis = np.where(d > 0, t_hi, t_lo)
    t_axis = np.where(np.isfinite(t_axis) & (t_axis > 0), t_axis, np.inf)
    axis = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, axis[..., None], axis=-1)[..., 0]   # z-depth: d_cam has z = 1
    cos = np.abs(np.take_along_axis(d, axis[..., None], axis=-1)[..., 0]) / np.linalg.norm(d, axis=-1)
    return t, np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


@dataclass
class Walk:
    info: StreamInfo
    stamps_ns: list[int]
    poses: list[NDArray[np.float64]]
    depth: list[NDArray[np.uint16]]   # with the known error
    truth: list[NDArray[np.uint16]]   # the true z-depth in the same units (no error)


def walk(radius: float, height: float, start_deg: float, frames: int = 24, *, seed: int = 0,
         width: int = 160, height_px: int = 120, error: bool = True) -> Walk:
    """A circle around the room's centre looking sideways and down (walls at every inclination, the
    floor at grazing angles), the known error added."""
    si = info(width, height_px)
    intr = si.depth_intrinsics
    rng = np.random.default_rng(seed)
    c = np.array([3.0, 2.5])
    stamps, poses, depth, truth = [], [], [], []
    for k in range(frames):
        phi = np.radians(start_deg + 360.0 * k / frames)
        eye = np.array([*(c + radius * np.array([np.cos(phi), np.sin(phi)])), height])
        yaw = phi + np.radians(70.0)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.35])
        pose = look_at(eye, target)
        z, th = cast(intr, pose)
        ok = np.isfinite(z) & (z < MAX_Z_M) & (th < MAX_THETA_DEG)
        zm = z + (bias_m(z, th) + sigma_m(z) * rng.standard_normal(z.shape) if error else 0.0)
        d = np.where(ok, np.rint(zm / UNITS), 0).astype(np.uint16)
        stamps.append(1_700_000_000_000_000_000 + k * 33_333_333)
        poses.append(pose)
        depth.append(d)
        truth.append(np.where(ok, np.rint(z / UNITS), 0).astype(np.uint16))
    return Walk(si, stamps, poses, depth, truth)


def write_walk(w: Walk, folder: Path, *, color: bool = True) -> tuple[Path, Path]:
    """sequence.mcap (the station's writer; a grey colour image when asked) and trajectory.txt."""
    folder.mkdir(parents=True, exist_ok=True)
    frames = []
    for k, d in enumerate(w.depth):
        rgb = None
        if color:
            g = (np.clip(d.astype(np.float64) * UNITS / MAX_Z_M, 0, 1) * 255).astype(np.uint8)
            rgb = np.repeat(g[..., None], 3, axis=-1)
        frames.append(FrameSet(k, w.stamps_ns[k], d, rgb))
    si = w.info
    if color:
        si = StreamInfo(depth_intrinsics=si.depth_intrinsics, color_intrinsics=si.depth_intrinsics,
                        depth_units_m=UNITS, depth_aligned_to_color=True, baseline_m=0.095, fps=30.0,
                        device=dict(DEVICE))
    seq = write_mcap(folder / "sequence.mcap", si, frames, {"device": dict(DEVICE)}, compression="lz4")
    assert seq == len(frames)
    traj = write_tum(folder / "trajectory.txt", [t * 1e-9 for t in w.stamps_ns], w.poses)
    return folder / "sequence.mcap", traj


def write_room_mesh(path: Path) -> Path:
    """The box as a triangle mesh (inward faces), walls subdivided so no triangle spans a view."""
    from depthstation.core.lazy_open3d import open3d

    o3d = open3d()
    box = o3d.geometry.TriangleMesh.create_box(*ROOM)
    box.triangles = o3d.utility.Vector3iVector(np.asarray(box.triangles)[:, ::-1].copy())
    box = box.subdivide_midpoint(3)
    box.compute_vertex_normals()
    o3d.io.write_triangle_mesh(str(path), box)
    return path


def wall_distance(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance of points inside (or near) the box to its nearest wall: the reference surface."""
    p = np.asarray(points, dtype=np.float64)
    return np.min(np.abs(np.concatenate([p, ROOM - p], axis=-1)), axis=-1)
