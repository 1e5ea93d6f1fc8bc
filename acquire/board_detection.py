"""Fast live board detection on the colour image and the board pose in the depth camera frame.

A small module of the acquisition's own: guidance needs a pose every frame within a few
milliseconds, with `CALIB_CB_FAST_CHECK` so frames without a board cost ~12 ms instead of ~260 ms
(PERF-NOTES), and must not import the evaluation stack at start-up.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.board_pose import BoardPose, pose_metrics, solve_board_pose
from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo, project

FloatArray = NDArray[np.float64]


def detect_corners(color: NDArray[np.uint8], board: Board, refine: bool = True) -> FloatArray | None:
    """Inner corners (N x 2, OpenCV order) of a plain checkerboard, or None when none is seen.

    The fast detector first; on small images (squares of ~10 px, far away) it fails, so it runs
    again on the image upsampled twice, and the sector-based detector is the last resort.
    """

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


def board_pose(color: NDArray[np.uint8], board: Board, info: StreamInfo) -> BoardPose | None:
    """Detect the board in the colour image and express its pose in the depth camera frame."""
    intr = info.color_intrinsics
    if intr is None:
        return None
    corners = detect_corners(color, board)
    if corners is None:
        return None
    pnp = solve_board_pose(board.corner_points(), corners, intr)
    if pnp is None:
        return None
    r_c, t_c = pnp.matrix[:3, :3], pnp.matrix[:3, 3]
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
