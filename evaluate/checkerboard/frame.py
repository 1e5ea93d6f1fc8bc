"""One frame of the study: detect, pose, mask the board's depth pixels, reduce them to moments."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.board_pose import PnPPose, solve_board_pose
from depthstation.core.camera_model import StreamInfo, ray_planes
from depthstation.core.frames import FrameSet
from depthstation.evaluate.checkerboard.detection import BoardDetector, Detection
from depthstation.evaluate.checkerboard.dqt import DqtFrame, TemporalStack, centred_roi, frame_metrics
from depthstation.evaluate.checkerboard.errors import BoardMismatchError
from depthstation.evaluate.checkerboard.kernels import board_moments
from depthstation.evaluate.checkerboard.mask import BoardMask, board_mask, board_to_depth
from depthstation.evaluate.checkerboard.metrics import fit_plane_moments, shift_moments
from depthstation.evaluate.checkerboard.pose import flip_board, square_contrast

MIN_CONTRAST = 5.0  # grey levels white minus black below which the colours count as swapped


@dataclass
class FrameResult:
    """Figures of one frame; `status` is 'ok' or why the frame was rejected."""

    index: int
    timestamp_ns: int
    status: str = "ok"
    pose_color: NDArray[np.float64] | None = None   # board -> colour camera, 4x4
    pose_depth: NDArray[np.float64] | None = None   # board -> depth camera, 4x4
    reprojection_px: float = float("nan")
    corners: int = 0
    reference_distance_m: float = float("nan")      # z of the board centre in the depth frame
    board_pixels: int = 0
    valid_pixels: int = 0
    fill_rate: float = float("nan")
    noise_m: float = float("nan")
    noise_black_m: float = float("nan")
    noise_white_m: float = float("nan")
    accuracy_m: float = float("nan")                # against the standpoint's averaged pose
    accuracy_rms_m: float = float("nan")
    accuracy_black_m: float = float("nan")
    accuracy_white_m: float = float("nan")
    accuracy_own_m: float = float("nan")            # against this frame's own pose
    accuracy_own_rms_m: float = float("nan")
    corner_shift_px: float = float("nan")           # median corner motion since the first frame
    origin: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    moments: dict[str, NDArray[np.float64]] = field(default_factory=dict)  # 'all', 'black', 'white'
    temperature_c: float = float("nan")
    corner_ids: NDArray[np.int64] | None = None      # the board corners seen (Board.corner_points order)
    corners_px: NDArray[np.float32] | None = None    # their colour-image positions, N x 2
    dqt: DqtFrame | None = None        # Depth Quality Tool figures on the board mask
    dqt_roi: DqtFrame | None = None    # ... on the centred ROI (`roi`), when asked

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass
class FramePixels:
    """The board's valid depth pixels of one frame (kept for samples and the per-pixel figure)."""

    u: NDArray[np.int32]
    v: NDArray[np.int32]
    z_m: NDArray[np.float32]
    colour: NDArray[np.uint8]


class FrameEvaluator:
    """Evaluates frames of one standpoint with one detector; checks the board colours once."""

    def __init__(self, info: StreamInfo, board: Board, *, refine: bool = True,
                 margin_m: float = 0.01, max_reprojection_px: float = 3.0,
                 min_pixels: int = 50, source: str | None = None, roi: float | None = None) -> None:
        if info.color_intrinsics is None and not info.depth_aligned_to_color:
            self.color_intr = info.depth_intrinsics
        else:
            self.color_intr = info.color_intrinsics or info.depth_intrinsics
        self.info = info
        self.board = board
        self.refine = refine
        self.margin_m = margin_m
        self.max_reprojection_px = max_reprojection_px
        self.min_pixels = min_pixels
        self.source = source
        self.detector = BoardDetector(board, intr=self.color_intr)
        self.depth_to_color = (np.eye(4) if info.depth_aligned_to_color
                               else info.depth_to_color.matrix)
        # plain boards with an even side are not symmetric under a half turn: check every frame
        self._check_every_frame = board.type == "checkerboard" and (
            board.squares_x % 2 == 0 or board.squares_y % 2 == 0)
        self._colours_checked = False
        self._first_corners: dict[int, NDArray[np.float64]] | None = None
        # Depth Quality Tool metrics: disparity lives in the stereo imager's pixels
        self.focal_px = info.stereo.fx
        self.temporal = TemporalStack()
        self.temporal_roi = TemporalStack()
        self.roi = roi
        di = info.depth_intrinsics
        self.roi_box = centred_roi(di.width, di.height, roi) if roi else None
        self.roi_ray = np.array([(di.width / 2 - di.ppx) / di.fx, (di.height / 2 - di.ppy) / di.fy, 1.0])
        self._roi_rays: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]] | None = None

    def _corner_shift(self, det: Detection) -> float:
        """Median image motion of the corners since the first posed frame (camera still or not)."""
        if self._first_corners is None:
            self._first_corners = dict(zip(det.ids.tolist(), det.image_points, strict=True))
            return 0.0
        shifts = [float(np.hypot(*(p - self._first_corners[i])))
                  for i, p in zip(det.ids.tolist(), det.image_points, strict=True)
                  if i in self._first_corners]
        return float(np.median(shifts)) if shifts else float("nan")

    def _check_colours(self, color: NDArray[np.uint8], det: Detection,
                       pose: PnPPose) -> tuple[Detection, PnPPose]:
        black, white = square_contrast(color, pose.matrix, self.color_intr, self.board)
        if white - black >= MIN_CONTRAST or not np.isfinite(white - black):
            self._colours_checked = True
            return det, pose
        if self._check_every_frame:
            flipped = flip_board(det, self.board)
            fpose = solve_board_pose(flipped.object_points, flipped.image_points, self.color_intr,
                                     self.refine)
            if fpose is not None:
                b2, w2 = square_contrast(color, fpose.matrix, self.color_intr, self.board)
                if w2 - b2 >= MIN_CONTRAST:
                    return flipped, fpose
        if abs(white - black) < MIN_CONTRAST:
            return det, pose  # too little contrast to judge (dark image); judged on a later frame
        want = "black" if self.board.first_square_black else "white"
        msg = (f"the board's squares have the opposite colours in the images (squares the board "
               f"description calls black have grey level {black:.0f}, white ones {white:.0f}); "
               f"the description says the top-left square is {want}: set "
               f"first_square_black = {str(not self.board.first_square_black).lower()} "
               "if that is the printed board")
        raise BoardMismatchError(self.source, msg)

    def evaluate(self, fs: FrameSet, keep_pixels: bool = False) -> tuple[FrameResult, FramePixels | None]:
        """Figures of one frame (noise from its own plane fit; accuracy is set per standpoint)."""
        res = FrameResult(fs.index, fs.timestamp_ns)
        temps = fs.metadata.get("temperatures") if fs.metadata else None
        if isinstance(temps, dict) and temps:
            res.temperature_c = float(np.mean([float(v) for v in temps.values()]))
        elif fs.metadata and "temperature_c" in fs.metadata:
            res.temperature_c = float(fs.metadata["temperature_c"])
        if fs.color is None:
            res.status = "no colour image"
            return res, None
        if fs.depth is None:
            res.status = "no depth image"
            return res, None
        det = self.detector.detect(fs.color)
        if det is None:
            if self.board.type == "charuco" and self.detector.other_pattern_matches(fs.color):
                legacy = not self.board.first_square_black
                msg = ("the images show OpenCV's " + ("current" if legacy else "legacy (pre-4.6)")
                       + " ChArUco pattern, the board description the other one: set "
                       f"first_square_black = {str(legacy).lower()}")
                raise BoardMismatchError(self.source, msg)
            res.status = self.detector.rejection or "board not found"
            return res, None
        pose = solve_board_pose(det.object_points, det.image_points, self.color_intr, self.refine)
        if pose is None:
            res.status = "pose failed"
            return res, None
        if self._check_every_frame or not self._colours_checked:
            det, pose = self._check_colours(fs.color, det, pose)
        res.corners = len(det.ids)
        res.corner_ids = np.asarray(det.ids, dtype=np.int64)
        res.corners_px = np.asarray(det.image_points, dtype=np.float32)
        res.corner_shift_px = self._corner_shift(det)
        res.reprojection_px = pose.reprojection_px
        if pose.reprojection_px > self.max_reprojection_px:
            res.status = f"reprojection error above {self.max_reprojection_px:g} px"
            return res, None
        res.pose_color = pose.matrix
        res.pose_depth = board_to_depth(pose.matrix, self.depth_to_color)
        centre = res.pose_depth[:3, :3] @ self.board.center + res.pose_depth[:3, 3]
        res.reference_distance_m = float(centre[2])
        res.origin = centre
        mask = board_mask(res.pose_depth, self.info.depth_intrinsics, self.board, self.margin_m)
        if mask is None:
            res.status = "board outside the depth image"
            return res, None
        return self._depth_figures(res, fs, mask, keep_pixels)

    def _depth_figures(self, res: FrameResult, fs: FrameSet, mask: BoardMask,
                       keep_pixels: bool) -> tuple[FrameResult, FramePixels | None]:
        assert fs.depth is not None
        rows, cols = mask.box
        raw = fs.depth[rows, cols]
        res.board_pixels = int(np.count_nonzero(mask.inside))
        res.valid_pixels, res.moments = board_moments(raw, mask.inside, mask.colour, mask.ray_x,
                                                      mask.ray_y, self.info.depth_units_m, res.origin)
        res.fill_rate = res.valid_pixels / res.board_pixels if res.board_pixels else float("nan")
        if res.valid_pixels < self.min_pixels:
            res.status = "too few depth pixels on the board"
            return res, None
        res.noise_m = fit_plane_moments(res.moments["all"])[2]
        res.noise_black_m = fit_plane_moments(res.moments["black"])[2]
        res.noise_white_m = fit_plane_moments(res.moments["white"])[2]
        self._dqt(res, fs.depth, mask)
        pixels = None
        if keep_pixels:
            vi, ui = np.nonzero(mask.inside & (raw > 0))
            z = raw[vi, ui].astype(np.float32) * np.float32(self.info.depth_units_m)
            colour = mask.colour[vi, ui]
            pixels = FramePixels((ui + mask.u0).astype(np.int32), (vi + mask.v0).astype(np.int32),
                                 z.astype(np.float32), colour)
        return res, pixels

    def _dqt(self, res: FrameResult, depth: NDArray[np.uint16], mask: BoardMask) -> None:
        """The Depth Quality Tool's figures on the board mask (pivot: the board centre's ray) and
        on the centred ROI (pivot: the image centre's, as the DQT)."""
        rows, cols = mask.box
        units, baseline = self.info.depth_units_m, self.info.baseline_m
        about_camera = shift_moments(res.moments["all"], res.origin)  # the study's pass, reused
        res.dqt = frame_metrics(depth[rows, cols], mask.inside, mask.ray_x, mask.ray_y, units,
                                res.board_pixels, self.focal_px, baseline, res.origin / res.origin[2],
                                about_camera)
        if self.temporal.rows is None:
            r, c = np.nonzero(mask.inside)
            self.temporal.start(r + mask.v0, c + mask.u0)
        self.temporal.add(depth)
        if self.roi_box is None:
            return
        x0, y0, x1, y1 = self.roi_box
        if self._roi_rays is None:
            xs, ys = ray_planes(self.info.depth_intrinsics)
            self._roi_rays = (xs[y0:y1, x0:x1], ys[y0:y1, x0:x1], np.ones((y1 - y0, x1 - x0), dtype=bool))
        rx, ry, every = self._roi_rays
        res.dqt_roi = frame_metrics(depth[y0:y1, x0:x1], every, rx, ry, units,
                                    (x1 - x0) * (y1 - y0), self.focal_px, baseline, self.roi_ray)
        if self.temporal_roi.rows is None:
            r, c = np.mgrid[y0:y1, x0:x1]
            self.temporal_roi.start(r.ravel(), c.ravel())
        self.temporal_roi.add(depth)
