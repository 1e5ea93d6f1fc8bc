"""Fast live board detection on the colour image and the board pose in the depth camera frame.

A small module of the acquisition's own: guidance needs a pose every frame within a few
milliseconds, with `CALIB_CB_FAST_CHECK` so frames without a board cost ~12 ms instead of ~260 ms
(PERF-NOTES), and must not import the evaluation stack at start-up.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.board import Board
from depthstation.camera import Extrinsics, Intrinsics, StreamInfo, project
from depthstation.geometry import rodrigues

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


def detect_corners(color: NDArray[np.uint8], board: Board, refine: bool = True) -> FloatArray | None:
    """Inner corners (N x 2, OpenCV order) of a plain checkerboard, or None when none is seen.

    The fast detector first; on small images (squares of ~10 px, far away) it fails, so it runs
    again on the image upsampled twice, and the sector-based detector is the last resort.
    """
    import cv2

    gray = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY) if color.ndim == 3 else color
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    pattern = board.inner_corners
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found and gray.shape[1] < 1000:
        big = cv2.resize(gray, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)
        found, corners = cv2.findChessboardCorners(big, pattern, flags=flags)
        if found and corners is not None:
            corners = (corners - 0.5) / 2.0  # pixel centres: u_big = 2 u + 0.5
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        refine = False  # the SB detector is sub-pixel already
    if not found or corners is None:
        return None
    corners = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    if refine:
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def solve_pose(corners_px: FloatArray, board: Board, intr: Intrinsics) -> tuple[FloatArray, FloatArray]:
    """Board-to-colour-camera pose by EPnP (the paper's method), refined by Levenberg-Marquardt."""
    import cv2

    obj = board.corner_points()
    dist = intr.opencv_distortion()
    ok, rvec, tvec = cv2.solvePnP(obj, corners_px.astype(np.float64), intr.K, dist,
                                  flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise ValueError("EPnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, corners_px.astype(np.float64), intr.K, dist, rvec, tvec)
    return rodrigues(rvec.ravel()), tvec.ravel().astype(np.float64)


def board_pose(color: NDArray[np.uint8], board: Board, info: StreamInfo) -> BoardPose | None:
    """Detect the board in the colour image and express its pose in the depth camera frame."""
    intr = info.color_intrinsics
    if intr is None:
        return None
    corners = detect_corners(color, board)
    if corners is None:
        return None
    r_c, t_c = solve_pose(corners, board, intr)
    # colour -> depth: the stream's depth_to_color maps depth points into the colour frame
    to_depth: Extrinsics = Extrinsics() if info.depth_aligned_to_color else info.depth_to_color.inverse()
    r = to_depth.R @ r_c
    t = to_depth.R @ t_c + to_depth.t
    d, inc, az = pose_metrics(board, r, t)
    depth_intr = intr if info.depth_aligned_to_color else info.depth_intrinsics
    c = (r @ board.center + t)[None, :]
    uv = project(depth_intr, c)[0]
    return BoardPose(r, t, corners, d, inc, az, (float(uv[0]), float(uv[1])))


def board_mask(pose: BoardPose, board: Board, intr: Intrinsics, margin_m: float = 0.0) -> NDArray[np.bool_]:
    """Depth pixels that see the board's square grid (shrunk by margin), from the pose alone."""
    import cv2

    w, h = board.size_m
    quad = np.array([[margin_m, margin_m, 0], [w - margin_m, margin_m, 0],
                     [w - margin_m, h - margin_m, 0], [margin_m, h - margin_m, 0]], dtype=np.float64)
    pts = quad @ pose.R.T + pose.t
    mask = np.zeros((intr.height, intr.width), dtype=np.uint8)
    if np.any(pts[:, 2] <= 0):
        return mask.astype(bool)
    uv = project(intr, pts)
    cv2.fillConvexPoly(mask, np.round(uv).astype(np.int32), 1)
    return mask.astype(bool)


def fill_rate(depth: NDArray[Any], mask: NDArray[np.bool_]) -> float:
    """Share of the board's depth pixels that hold a value (0 = no depth); 0 when the mask is empty."""
    n = int(mask.sum())
    if n == 0:
        return 0.0
    return float(np.count_nonzero(depth[mask])) / n
