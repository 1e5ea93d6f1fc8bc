"""Camera poses: standpoints of a protocol plan (exact distance and inclination) and a walk round a table."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.errors import InputError
from depthstation.core.geometry import (
    inclination_deg,
    look_at,
    matrix_to_quaternion,
    rodrigues,
)
from depthstation.core.tum import read_tum_poses

Pose = NDArray[np.float64]


def standpoint_pose(board: Board, distance_m: float, inclination_deg_: float, side: str = "left",
                    roll_deg: float = 0.0) -> Pose:
    """Depth-camera-to-board pose whose standpoint distance and inclination come out exactly.

    The optical axis goes through the board centre, so the centre's z-depth is `distance_m` and
    the ray to it makes `inclination_deg_` with the board normal (DESIGN §2). The camera swings
    round the board's vertical axis (board y, pointing down); 'left' puts it on the board's -x side.
    """
    if distance_m <= 0 or not 0 <= inclination_deg_ < 90:
        raise InputError(None, f"standpoint needs distance > 0 and inclination in [0, 90), got "
                               f"{distance_m} m, {inclination_deg_} deg")
    c = board.center
    a = np.radians(inclination_deg_)
    sign = -1.0 if side == "left" else 1.0
    eye = c + distance_m * np.array([sign * np.sin(a), 0.0, -np.cos(a)])
    pose = look_at(eye, c, up=(0.0, -1.0, 0.0))
    if roll_deg:

        pose[:3, :3] = pose[:3, :3] @ rodrigues(np.array([0.0, 0.0, np.radians(roll_deg)]))
    return pose


def standpoint_truth(board: Board, cam_to_board: NDArray[Any]) -> tuple[float, float]:
    """(distance_m, inclination_deg) of the board centre seen from a depth-camera pose."""
    pose = np.asarray(cam_to_board, dtype=np.float64)
    board_to_cam = np.linalg.inv(pose)
    c_cam = board_to_cam[:3, :3] @ board.center + board_to_cam[:3, 3]
    n_cam = board_to_cam[:3, :3] @ np.array([0.0, 0.0, -1.0])
    return float(c_cam[2]), float(inclination_deg(c_cam, n_cam))


def walk_around(center: NDArray[Any] = (0.0, -0.75, 0.0), radius_m: float = 2.0,  # type: ignore[assignment]
                eye_height_m: float = 1.5, speed_m_s: float = 0.3, fps: float = 30.0,
                frames: int | None = None, turns: float = 1.0, bob_m: float = 0.03) -> list[Pose]:
    """Camera-to-world poses of a slow walk round a table (y down, floor at y = 0).

    The operator carries the camera at `eye_height_m`, looks at `center`, walks at `speed_m_s`
    along a circle with a small vertical bob; `frames` defaults to one full turn at `fps`.
    """
    centre = np.asarray(center, dtype=np.float64)
    if frames is None:
        frames = round(turns * 2 * np.pi * radius_m / speed_m_s * fps)
    if frames < 1:
        raise InputError(None, "trajectory needs at least one frame")
    poses = []
    for k in range(frames):
        t = k / fps
        phi = speed_m_s * t / radius_m
        eye = np.array([centre[0] + radius_m * np.cos(phi),
                        -eye_height_m + bob_m * np.sin(2 * np.pi * 0.9 * t),
                        centre[2] + radius_m * np.sin(phi)])
        poses.append(look_at(eye, centre, up=(0.0, -1.0, 0.0)))
    return poses


def write_tum(path: Path, stamps_s: NDArray[Any], poses: list[Pose] | NDArray[Any]) -> Path:
    """TUM trajectory text, as ORB-SLAM3 writes it: `timestamp tx ty tz qx qy qz qw` (camera-to-world)."""
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world, metres, seconds)"]
    for t, p in zip(np.asarray(stamps_s, dtype=np.float64), poses, strict=True):
        q = matrix_to_quaternion(np.asarray(p)[:3, :3])
        tr = np.asarray(p)[:3, 3]
        lines.append(f"{t:.9f} " + " ".join(f"{x:.6f}" for x in tr) + " "
                     + " ".join(f"{x:.9f}" for x in q))
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


def read_tum(path: Path) -> tuple[NDArray[np.float64], list[Pose]]:
    """Time stamps (s) and camera-to-world poses of a TUM trajectory (`core.tum.read_tum_poses`, the
    reader the scan study uses: a file one takes the other takes), at least two of them."""
    p = Path(path)
    stamps, poses = read_tum_poses(p)
    if len(poses) < 2:
        raise InputError(p, f"trajectory holds {len(poses)} pose(s); a sequence needs 2 or more (its frame "
                            "rate comes from their times)")
    return stamps, list(poses)
