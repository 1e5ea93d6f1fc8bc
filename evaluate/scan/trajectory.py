"""TUM trajectories (`timestamp tx ty tz qx qy qz qw`, what ORB-SLAM3 writes) and time matching."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.geometry import matrix_to_quaternion
from depthstation.core.tum import read_tum_poses


@dataclass(frozen=True)
class Trajectory:
    """Camera-to-world poses (4x4) at time stamps in seconds, sorted by time."""

    timestamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]  # N x 4 x 4, p_world = T @ p_camera

    def __len__(self) -> int:
        return int(self.timestamps_s.size)

    def _nearest(self, t_s: float) -> int | None:
        """Index of the pose stamp nearest to t_s (None without poses)."""
        ts = self.timestamps_s
        i = int(np.searchsorted(ts, t_s))
        best = None
        for j in (i - 1, i):
            if 0 <= j < ts.size and (best is None or abs(ts[j] - t_s) < abs(ts[best] - t_s)):
                best = j
        return best

    def match(self, t_s: float, tolerance_s: float) -> NDArray[np.float64] | None:
        """Pose whose stamp is nearest to t_s, or None when none lies within the tolerance.

        Nearest rather than interpolated: ORB-SLAM3 stamps its poses with the frame time, so an
        exact match is the normal case and a gap means the tracker lost the frame.
        """
        best = self._nearest(t_s)
        if best is None or abs(self.timestamps_s[best] - t_s) > tolerance_s:
            return None
        return self.poses[best]

    def gap_s(self, t_s: float) -> float:
        """Seconds from t_s to the nearest pose stamp (inf without poses)."""
        best = self._nearest(t_s)
        return float("inf") if best is None else float(abs(self.timestamps_s[best] - t_s))

    def transformed(self, similarity: NDArray[np.float64]) -> Trajectory:
        """Poses in another frame: p' = s R p + t applied to the camera centre; the rotation part
        gets the pure rotation (cameras stay orthonormal, the scale moves only the centres)."""
        s, r, t = decompose_similarity(similarity)
        out = self.poses.copy()
        out[:, :3, :3] = r @ self.poses[:, :3, :3]
        out[:, :3, 3] = (s * (r @ self.poses[:, :3, 3].T)).T + t
        return Trajectory(self.timestamps_s.copy(), out)

    def shifted(self, offset_s: float) -> Trajectory:
        """The same poses with `offset_s` added to every time stamp (the poses' clock onto another)."""
        if not offset_s:
            return self
        return Trajectory(self.timestamps_s + offset_s, self.poses.copy())

    def camera_moved(self, camera_to_given: NDArray[np.float64]) -> Trajectory:
        """Poses of another camera on the same rig: T_world_other = T_world_given @ camera_to_given
        (4x4 rigid, points of the other camera into the given one's frame)."""
        move = np.asarray(camera_to_given, dtype=np.float64)
        return Trajectory(self.timestamps_s.copy(), self.poses @ move)

    def translated(self, offset: NDArray[np.float64]) -> Trajectory:
        """The same poses with `offset` added to every camera centre (float64)."""
        out = self.poses.copy()
        out[:, :3, 3] += np.asarray(offset, dtype=np.float64)
        return Trajectory(self.timestamps_s.copy(), out)


LOCAL_SHIFT_ABOVE_M = 1000.0  # beyond this a float32 coordinate is coarser than 0.06 mm


def local_shift(lo: NDArray[np.float64], hi: NDArray[np.float64],
                above_m: float = LOCAL_SHIFT_ABOVE_M) -> NDArray[np.float64]:
    """The shift (whole metres) to subtract from coordinates with bounds [lo, hi]: their centre when
    it lies farther than `above_m` from the origin on any axis, else zero.

    Why: Open3D casts rays in float32; at y ~ 5e6 m (survey coordinates) its spacing is 0.5 m.
    """
    centre = (np.asarray(lo, dtype=np.float64) + np.asarray(hi, dtype=np.float64)) / 2.0
    if not np.all(np.isfinite(centre)) or np.max(np.abs(centre)) <= above_m:
        return np.zeros(3)
    return np.round(centre)


@dataclass(frozen=True)
class LocalFrames:
    """The shifts subtracted from reference and trajectory coordinates before the study works.

    A similarity M (trajectory -> reference) in the given frames is T(-reference) M T(trajectory)
    between the local ones.
    """

    reference_m: NDArray[np.float64]
    trajectory_m: NDArray[np.float64]

    @property
    def any(self) -> bool:
        return bool(np.any(self.reference_m != 0.0) or np.any(self.trajectory_m != 0.0))

    def to_local(self, m: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.asarray(m, dtype=np.float64).copy()
        out[:3, 3] += out[:3, :3] @ self.trajectory_m - self.reference_m
        return out

    def to_given(self, m: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.asarray(m, dtype=np.float64).copy()
        out[:3, 3] += self.reference_m - out[:3, :3] @ self.trajectory_m
        return out

    def to_dict(self) -> dict[str, list[float]]:
        return {"reference_m": [float(x) for x in self.reference_m],
                "trajectory_m": [float(x) for x in self.trajectory_m]}


def decompose_similarity(m: NDArray[np.float64]) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """4x4 similarity [sR t; 0 1] -> (s, R, t)."""
    m = np.asarray(m, dtype=np.float64)
    a = m[:3, :3]
    s = float(np.cbrt(np.linalg.det(a)))
    if s <= 0:
        raise ValueError("similarity has a non-positive determinant")
    u, _, vt = np.linalg.svd(a / s)
    r = u @ vt
    return s, r, m[:3, 3].copy()


def compose_similarity(s: float, r: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.float64]:
    m = np.eye(4)
    m[:3, :3] = s * np.asarray(r)
    m[:3, 3] = t
    return m


# how a pose file's lines are meant: TUM's (camera-to-world, qx qy qz qw) and the mistakes users'
# files make most (world-to-camera poses, e.g. COLMAP's; the quaternion's w first)
POSE_CONVENTIONS = {
    "tum": "camera-to-world, qx qy qz qw (TUM)",
    "wxyz": "camera-to-world, qw qx qy qz",
    "inverse": "world-to-camera, qx qy qz qw",
    "inverse-wxyz": "world-to-camera, qw qx qy qz (COLMAP's order)",
}


def read_tum(path: Path, convention: str = "tum") -> Trajectory:
    """Read a TUM trajectory (`core.tum.read_tum_poses`: the one reader of the format), its lines
    meant as `convention` says (POSE_CONVENTIONS), as camera-to-world poses."""
    stamps, poses = read_tum_poses(Path(path), wxyz=convention.endswith("wxyz"))
    if convention.startswith("inverse"):
        poses = np.asarray(np.linalg.inv(poses), dtype=np.float64)
    return Trajectory(stamps, poses)


def write_tum(path: Path, timestamps_s: Sequence[float] | NDArray[np.float64],
              poses: Sequence[NDArray[np.float64]] | NDArray[np.float64]) -> Path:
    """Write camera-to-world poses as a TUM trajectory (9 decimals: ns-exact time stamps)."""
    path = Path(path)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(timestamps_s, poses, strict=True):
        T = np.asarray(T)
        q = matrix_to_quaternion(T[:3, :3])
        vals = [*T[:3, 3], *q]
        lines.append(f"{float(t):.9f} " + " ".join(f"{v:.9f}" for v in vals))
    path.write_text("\n".join(lines) + "\n")
    return path
