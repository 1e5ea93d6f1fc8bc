"""A board on a wall rendered exactly (colour by homography, depth by ray-plane intersection).

For the checkerboard tests and benchmark only (moved out of evaluate/): known pose, an exactly
known z noise (sigma = k z^2) and z bias, no camera physics and no open3d. The simulated D455
(`simulate/`) covers the physical case; this stays because it lets a test set noise and bias
directly and runs where open3d is absent.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import look_at


def board_image(board: Board, px_per_m: float) -> NDArray[np.uint8]:
    """Grey image of the printed board (squares, ChArUco markers, white plate margin)."""
    s = board.square_length_m
    m = board.plate_margin_m
    sq = round(s * px_per_m)
    mp = round(m * px_per_m)
    if board.type == "charuco":
        from depthstation.evaluate.checkerboard.detection import charuco_legacy

        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, str(board.dictionary)))
        cb = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), s,
                                    float(board.marker_length_m or 0.0), dictionary)
        cb.setLegacyPattern(charuco_legacy(board))
        grid = np.asarray(cb.generateImage((board.squares_x * sq, board.squares_y * sq)), dtype=np.uint8)
    else:
        r, c = np.mgrid[0:board.squares_y * sq, 0:board.squares_x * sq] // sq
        black = ((r + c) % 2 == 0) == board.first_square_black
        grid = np.where(black, 0, 255).astype(np.uint8)
    return np.pad(grid, mp, constant_values=255)


def pose_for(board: Board, distance_m: float, inclination_deg: float,
             azimuth_deg: float = 0.0) -> NDArray[np.float64]:
    """Board -> camera pose: camera looking at the board centre from `distance_m` (z-depth of the
    centre) with the board normal `inclination_deg` away from the viewing ray."""
    a = np.radians(inclination_deg)
    az = np.radians(azimuth_deg)
    c = board.center
    direction = np.array([np.sin(a) * np.cos(az), np.sin(a) * np.sin(az), -np.cos(a)])
    eye = c + distance_m * direction
    cam_to_board = look_at(eye, c, (0.0, -1.0, 0.0))
    return np.asarray(np.linalg.inv(cam_to_board), dtype=np.float64)


def render_color(board: Board, pose: NDArray[np.float64], intr: Intrinsics,
                 px_per_m: float = 2000.0, wall: int = 110, supersample: int = 4) -> NDArray[np.uint8]:
    """RGB image of the board (board -> camera `pose`) on a grey wall, area-averaged (no aliasing)."""
    img = board_image(board, px_per_m)
    m = board.plate_margin_m
    s = np.array([[1 / px_per_m, 0, 0.5 / px_per_m - m], [0, 1 / px_per_m, 0.5 / px_per_m - m],
                  [0, 0, 1]])
    fine = intr.scaled(intr.width * supersample, intr.height * supersample)
    h = fine.K @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]]) @ s
    big = cv2.warpPerspective(img, h, (fine.width, fine.height), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=wall)
    out = cv2.resize(big, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    return np.repeat(np.asarray(out, dtype=np.uint8)[..., None], 3, axis=2)


def render_depth_m(board: Board, pose: NDArray[np.float64], intr: Intrinsics,
                   wall_offset_m: float = 0.03) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """True z-depth per pixel of the board plane (plate) and of a wall behind it; plate mask."""
    rx = (np.arange(intr.width) - intr.ppx) / intr.fx
    ry = (np.arange(intr.height) - intr.ppy) / intr.fy
    n, t = pose[:3, 2], pose[:3, 3]
    dot = n[0] * rx[None, :] + n[1] * ry[:, None] + n[2]
    z = float(n @ t) / dot
    bx = z * (pose[0, 0] * rx[None, :] + pose[1, 0] * ry[:, None] + pose[2, 0]) - float(pose[:3, 0] @ t)
    by = z * (pose[0, 1] * rx[None, :] + pose[1, 1] * ry[:, None] + pose[2, 1]) - float(pose[:3, 1] @ t)
    plate = board.inside(bx, by, -board.plate_margin_m)
    z_wall = float(n @ t + wall_offset_m) / dot
    return np.where(plate, z, z_wall), plate


def still_frames(board: Board, pose_color: NDArray[np.float64], info: StreamInfo, count: int, *,
                 noise_rel: float = 0.001, bias_m: float = 0.0, seed: int = 0,
                 t0_ns: int = 1_700_000_000_000_000_000) -> Iterator[FrameSet]:
    """Frames of a still camera: z-depth noise sigma = noise_rel * z^2 (per metre), plus a z bias.

    `pose_color` is board -> colour camera; the depth camera sees it through the extrinsics.
    """
    rng = np.random.default_rng(seed)
    assert info.color_intrinsics is not None
    color = render_color(board, pose_color, info.color_intrinsics)
    d2c = np.eye(4) if info.depth_aligned_to_color else info.depth_to_color.matrix
    pose_depth = np.linalg.inv(d2c) @ pose_color
    z, _ = render_depth_m(board, pose_depth, info.depth_intrinsics)
    for k in range(count):
        zk = z + bias_m + rng.standard_normal(z.shape) * noise_rel * z * z
        counts = np.clip(np.rint(zk / info.depth_units_m), 0, 65535).astype(np.uint16)
        yield FrameSet(k, t0_ns + k * 33_333_333, counts, color.copy(), metadata={"temperature_c": 40.0})
