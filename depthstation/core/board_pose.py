"""A board's pose: from its corners (the paper's EPnP), in the depth camera frame, and the figures
the paper reads off it (DESIGN §2): distance (z-depth of the board centre) and inclination (ray to
the centre against the normal).

Shared by the acquisition (guidance, stillness), the checkerboard study, the simulated camera (its
truth) and the tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BoardPose:
    """Board-to-depth-camera pose: p_depth = R @ p_board + t, plus what the operator is shown.

    `azimuth_deg` is the inclination signed by side: positive when the camera stands to the
    operator's left of the board normal (the board normal has a positive x in the camera frame).
    It is invariant to OpenCV's 180-degree corner-order ambiguity.
    """

    R: FloatArray
    t: FloatArray
    corners_px: FloatArray  # N x 2 in the colour image
    distance_m: float
    inclination_deg: float
    azimuth_deg: float
    center_px: tuple[float, float]  # board centre projected into the depth image

    @property
    def normal(self) -> FloatArray:
        """Board normal in the depth frame, pointing towards the camera."""
        n = -self.R[:, 2]
        center = self.R @ np.zeros(3) + self.t
        return n if float(np.dot(n, center)) < 0 else -n

    def center_in_camera(self, board: Board) -> FloatArray:
        """The board centre in the depth camera frame."""
        return self.R @ board.center + self.t

    def stillness_points(self, board: Board) -> FloatArray:
        """The board centre, then the grid's 4 outer corners, in the depth camera frame (5 x 3): what
        the stillness checks compare. The centre catches steps and turns; the corners catch a walk
        round the board while facing it (which leaves the centre in place and turns the board by
        the walked angle: 3.4 degrees move a corner 2 cm), and they stay well determined where the
        camera's own position is not (EPnP's tilt of a board facing the camera jitters by half a
        degree at 2.5 m, 2.5 cm of camera position, but 3 mm at a corner)."""
        w, h = board.size_m
        pts = np.array([board.center, [0.0, 0.0, 0.0], [w, 0.0, 0.0], [w, h, 0.0], [0.0, h, 0.0]])
        return np.asarray(pts @ self.R.T + self.t, dtype=np.float64)

    @property
    def camera_position(self) -> FloatArray:
        """Depth camera centre in the board frame (for stillness checks)."""
        return -self.R.T @ self.t


def pose_metrics(board: Board, r: FloatArray, t: FloatArray) -> tuple[float, float, float]:
    """(distance_m, inclination_deg, azimuth_deg) of a board-to-depth-camera pose (DESIGN §2)."""
    c = r @ board.center + t
    n = r[:, 2]
    if float(np.dot(n, c)) > 0:  # make the normal point towards the camera
        n = -n
    cos = abs(float(np.dot(c, n))) / float(np.linalg.norm(c))
    inc = float(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))))
    # side: project the normal onto the camera's x-z plane and take its angle to the ray
    ray_h = np.array([c[0], 0.0, c[2]])
    n_h = np.array([n[0], 0.0, n[2]])
    cross_y = float(np.cross(-ray_h, n_h)[1])
    sign = 1.0 if cross_y <= 0 else -1.0
    if abs(cross_y) < 1e-12:
        sign = 1.0 if n[0] >= 0 else -1.0
    return float(c[2]), inc, sign * inc


@dataclass(frozen=True)
class PnPPose:
    """Board-to-camera transform from corners (p_cam = R p_board + t) and its reprojection RMS (px)."""

    matrix: NDArray[np.float64]  # 4x4
    reprojection_px: float


def _solve(obj: NDArray[np.float64], img: NDArray[np.float64], intr: Intrinsics, flag: int,
           refine: bool) -> tuple[Any, Any, float] | None:
    k, dist = intr.K, intr.opencv_distortion()
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=flag)
    if not ok:
        return None
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return rvec, tvec, rms


def solve_board_pose(object_points: NDArray[Any], image_points: NDArray[Any], intr: Intrinsics,
                     refine: bool = True, fallback_px: float = 0.0) -> PnPPose | None:
    """EPnP pose (the paper's method) refined by Levenberg-Marquardt; None when it fails or the board
    lies behind the camera.

    EPnP on a plane can land in a wrong minimum at steep views; IPPE, the planar solver, is tried
    too and the better fit kept whenever EPnP reprojects above `fallback_px` (default: always;
    0.1 ms). A wrong minimum need not look bad: at 5 m / 60 deg (6 px squares) EPnP + LM settled
    at 0.9 px RMS and 1.2 deg of tilt while the right pose reprojects at 0.01 px.
    """
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    img = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    best = _solve(obj, img, intr, cv2.SOLVEPNP_EPNP, refine)
    if best is None or best[2] > fallback_px:
        ippe = _solve(obj, img, intr, cv2.SOLVEPNP_IPPE, refine)
        if ippe is not None and (best is None or ippe[2] < best[2]):
            best = ippe
    if best is None:
        return None
    rvec, tvec, rms = best
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(rvec)[0]
    m[:3, 3] = tvec.reshape(3)
    if m[2, 3] <= 0:
        return None
    return PnPPose(m, rms)
