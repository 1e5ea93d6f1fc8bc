"""What the study checks of a board pose from its corners: the print's colours against the pose (a
flipped board), the pose's tilt uncertainty and the corner noise it implies. The pose itself is
`depthstation.core.board_pose.solve_board_pose` (EPnP + LM, IPPE fallback)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.board_pose import PnPPose
from depthstation.core.camera_model import Intrinsics
from depthstation.core.geometry import rodrigues
from depthstation.evaluate.checkerboard.detection import Detection, to_gray


def square_contrast(color: NDArray[np.uint8], pose: NDArray[np.float64], intr: Intrinsics,
                    board: Board) -> tuple[float, float]:
    """Mean grey level of the squares the board calls black and of those it calls white.

    Sampled in the strip between a square's edge and its centre marker (ChArUco white squares
    carry a dark marker in the middle), so the two means only agree with the board description
    when the printed colours do.
    """
    gray = to_gray(color).astype(np.float32)
    s = board.square_length_m
    inset = 0.5 - (board.marker_length_m or 0.0) / s / 2 if board.type == "charuco" else 0.5
    frac = inset / 2 if board.type == "charuco" else 0.5
    cols, rows = np.meshgrid(np.arange(board.squares_x), np.arange(board.squares_y))
    x = (cols.ravel() + 0.5) * s
    y = (rows.ravel() + frac) * s
    pts = np.stack([x, y, np.zeros_like(x)], axis=1)
    cam = pts @ pose[:3, :3].T + pose[:3, 3]
    uv, _ = cv2.projectPoints(cam, np.zeros(3), np.zeros(3), intr.K, intr.opencv_distortion())
    uv = np.rint(uv.reshape(-1, 2)).astype(np.int64)
    h, w = gray.shape
    ok = (uv[:, 0] >= 1) & (uv[:, 0] < w - 1) & (uv[:, 1] >= 1) & (uv[:, 1] < h - 1)
    black = board.is_black(x + 1e-9, y + 1e-9)
    vals = np.array([gray[v - 1:v + 2, u - 1:u + 2].mean() if k else np.nan
                     for (u, v), k in zip(uv, ok, strict=True)])
    return float(np.nanmean(vals[black])), float(np.nanmean(vals[~black]))


def flip_board(det: Detection, board: Board) -> Detection:
    """The same plain-chessboard detection with its corner order reversed (board turned by 180 deg)."""
    return Detection(det.image_points[::-1].copy(), det.object_points, det.ids, det.markers)


def pose_jacobian(pose: NDArray[np.float64], object_points: NDArray[np.float64],
                  intr: Intrinsics) -> NDArray[np.float64]:
    """d(projected corners, 2N) / d(p), p = (rotation vector applied in the camera frame,
    translation): what a pose's Cramer-Rao covariance sigma^2 (J^T J)^-1 is built from."""
    obj = np.asarray(object_points, dtype=np.float64)
    k = intr.K
    dist = intr.opencv_distortion()
    cam = obj @ pose[:3, :3].T  # rotated board points (the rotation vector near pi is unstable)
    t0 = pose[:3, 3]

    def project(p: NDArray[np.float64]) -> NDArray[np.float64]:
        pts = cam @ rodrigues(p[:3]).T + t0 + p[3:]
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, dist)
        return np.asarray(uv, dtype=np.float64).reshape(-1)

    eps = 1e-6
    base = project(np.zeros(6))
    jac = np.empty((base.size, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        jac[:, i] = (project(d) - base) / eps
    return jac


def weighted_information(jac: NDArray[np.float64],
                         weights: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """J^T W J of a corners' Jacobian (rows u, v per corner), each corner weighted by how many
    frames saw it (None: every corner once). Why: a ChArUco board partly out of view constrains
    its pose with the corners seen only; all the board's corners made the prediction optimistic."""
    if weights is None:
        return np.asarray(jac.T @ jac, dtype=np.float64)
    w = np.repeat(np.asarray(weights, dtype=np.float64), 2)
    return np.asarray((jac * w[:, None]).T @ jac, dtype=np.float64)


def normal_std_deg(pose: NDArray[np.float64], object_points: NDArray[np.float64], intr: Intrinsics,
                   sigma_px: float, frames: int = 1, weights: NDArray[np.float64] | None = None) -> float:
    """Standard deviation (deg) of the board normal's direction from corner noise (Cramer-Rao).

    Gauss-Newton covariance of the 6-dof pose, sigma^2 (J^T J)^-1 / frames, with J the Jacobian of
    the corners' projections; the normal's 2x2 tangent covariance follows from the rotation part.
    Returned: the larger axis (the worse of the two tilts). For a still camera `frames` frames of
    independent corner noise average like one pose from all corners; a static corner bias (the same
    every frame) does not average and is not in this figure. At 0 deg the reported inclination is
    the folded |tilt| and reads ~1.25 x this on average (Rayleigh). `weights`: how many frames saw
    each of `object_points` (then instead of `frames`).
    """
    jac = pose_jacobian(pose, object_points, intr)
    seen = np.full(len(jac) // 2, float(max(frames, 1))) if weights is None else weights
    try:
        cov = sigma_px**2 * np.linalg.inv(weighted_information(jac, seen))
    except np.linalg.LinAlgError:
        return float("inf")
    # a small rotation w (camera frame, left-multiplied) moves the normal n by w x n
    n = pose[:3, 2]
    cross = np.array([[0.0, n[2], -n[1]], [-n[2], 0.0, n[0]], [n[1], -n[0], 0.0]])  # d(w x n)/dw
    cov_n = cross @ cov[:3, :3] @ cross.T  # rank 2, in the plane orthogonal to n
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(cov_n)[-1]), 0.0))))


def corner_noise_px(pose: PnPPose | NDArray[np.float64], det: Detection, intr: Intrinsics) -> float:
    """Per-coordinate corner noise (px) from the reprojection residuals (2N - 6 degrees of freedom)."""
    m = pose.matrix if isinstance(pose, PnPPose) else pose
    rvec = cv2.Rodrigues(m[:3, :3])[0]
    uv, _ = cv2.projectPoints(det.object_points, rvec, m[:3, 3], intr.K, intr.opencv_distortion())
    res = np.asarray(uv, dtype=np.float64).reshape(-1, 2) - det.image_points
    dof = max(res.size - 6, 1)
    return float(np.sqrt(np.sum(res**2) / dof))
