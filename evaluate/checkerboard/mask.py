"""The board's depth pixels: depth rays intersected with the board plane from the colour pose.

No manual masking: every depth pixel whose ray meets the reference plane inside the square grid
(shrunk by a margin) belongs to the board. The pose is carried from the colour camera to the depth
camera through the depth-to-colour extrinsics, so aligned and unaligned recordings work alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, ray_planes

OTHER, BLACK, WHITE = 0, 1, 2


@dataclass(frozen=True)
class BoardMask:
    """Board pixels inside a bounding box of the depth image, with their square colour."""

    v0: int
    u0: int
    inside: NDArray[np.bool_]        # h x w (box), on the grid within the margin
    colour: NDArray[np.uint8]        # h x w: OTHER (square edge band, marker), BLACK, WHITE
    z_ref_m: NDArray[np.float32]     # h x w: z-depth of the reference plane along each pixel's ray
    ray_x: NDArray[np.float32]       # h x w: x / z of each box pixel's ray (lens distortion inverted)
    ray_y: NDArray[np.float32]       # h x w: y / z of each box pixel's ray

    @property
    def box(self) -> tuple[slice, slice]:
        h, w = self.inside.shape
        return slice(self.v0, self.v0 + h), slice(self.u0, self.u0 + w)


def board_to_depth(board_to_color: NDArray[np.float64],
                   depth_to_color: NDArray[np.float64]) -> NDArray[np.float64]:
    """Board pose in the depth camera: T_depth<-board = inv(T_color<-depth) T_color<-board."""
    return np.asarray(np.linalg.inv(depth_to_color) @ board_to_color, dtype=np.float64)


def board_mask(pose: NDArray[np.float64], intr: Intrinsics, board: Board, margin_m: float = 0.01,
               edge_band: float | None = None) -> BoardMask | None:
    """Depth pixels on the board seen from `pose` (board -> depth camera, 4x4).

    `edge_band` (fraction of a square) around square borders, and ChArUco markers, are left out
    of the black/white classes, which should hold pure colours; they stay in the board mask.
    Default: 10% of a square, or for ChArUco 20% of the white strip around a marker.
    Returns None when the board is not in front of the camera or not in the image.
    """
    r, t = pose[:3, :3], pose[:3, 3]
    w_m, h_m = board.size_m
    outline = np.array([[margin_m, margin_m, 0], [w_m - margin_m, margin_m, 0],
                        [w_m - margin_m, h_m - margin_m, 0], [margin_m, h_m - margin_m, 0]])
    cam = outline @ r.T + t
    if np.any(cam[:, 2] <= 1e-6):
        return None
    u0, u1, v0, v1 = _box(cam, intr)
    if u1 <= u0 or v1 <= v0:
        return None
    xs, ys = ray_planes(intr)
    rx, ry = xs[v0:v1, u0:u1], ys[v0:v1, u0:u1]
    # Ray p = s (rx, ry, 1) meets the plane n.(p - t) = 0 at s = n.t / n.(rx, ry, 1).
    n = r[:, 2]
    denom = n[0] * rx + n[1] * ry + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = float(n @ t) / denom
    # Board coordinates of the hit: x = e_x.(p - t), y = e_y.(p - t).
    ex, ey = r[:, 0], r[:, 1]
    bx = s * (ex[0] * rx + ex[1] * ry + ex[2]) - float(ex @ t)
    by = s * (ey[0] * rx + ey[1] * ry + ey[2]) - float(ey @ t)
    inside = (s > 0) & board.inside(bx, by, margin_m)
    sq = board.square_length_m
    charuco = board.type == "charuco" and bool(board.marker_length_m)
    if edge_band is None:
        edge_band = 0.2 * (1 - (board.marker_length_m or 0.0) / sq) / 2 if charuco else 0.1
    fx_, fy_ = bx / sq, by / sq
    fx_ -= np.floor(fx_)
    fy_ -= np.floor(fy_)
    pure = (fx_ > edge_band) & (fx_ < 1 - edge_band) & (fy_ > edge_band) & (fy_ < 1 - edge_band)
    black = board.is_black(bx, by)
    colour = np.zeros(inside.shape, dtype=np.uint8)
    colour[inside & pure & black] = BLACK
    white = inside & pure & ~black
    if charuco:
        half = float(board.marker_length_m or 0.0) / sq / 2 + edge_band
        in_marker = (np.abs(fx_ - 0.5) < half) & (np.abs(fy_ - 0.5) < half)
        white &= ~in_marker
    colour[white] = WHITE
    return BoardMask(v0, u0, inside, colour, s.astype(np.float32),
                     rx.astype(np.float32), ry.astype(np.float32))


def _box(cam: NDArray[np.float64], intr: Intrinsics) -> tuple[int, int, int, int]:
    """Pixel box (u0, u1, v0, v1) of the board's outline `cam` (four corners, camera frame),
    through the lens when it has one: its edges bow, so they are projected at 33 points each."""
    if intr.has_distortion:
        f = np.linspace(0.0, 1.0, 33)[:, None]
        edges = np.concatenate([cam[i] + f * (cam[(i + 1) % 4] - cam[i]) for i in range(4)])
        uv, _ = cv2.projectPoints(edges, np.zeros(3), np.zeros(3), intr.K, intr.opencv_distortion())
        u, v = uv[:, 0, 0], uv[:, 0, 1]
        slack = 1
    else:
        u = cam[:, 0] / cam[:, 2] * intr.fx + intr.ppx
        v = cam[:, 1] / cam[:, 2] * intr.fy + intr.ppy
        slack = 0
    return (max(int(np.floor(u.min())) - slack, 0), min(int(np.ceil(u.max())) + 1 + slack, intr.width),
            max(int(np.floor(v.min())) - slack, 0), min(int(np.ceil(v.max())) + 1 + slack, intr.height))
