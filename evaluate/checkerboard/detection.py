"""Board corners in a colour image: plain chessboard (fast check + cornerSubPix + X-junction model
fit, `corners.py`) or ChArUco (cv2 5 API)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.errors import InputError
from depthstation.evaluate.checkerboard.corners import refine_xjunctions

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)


@dataclass(frozen=True)
class Detection:
    """Corners found in one image: pixel positions (OpenCV: integer = pixel centre) and board points."""

    image_points: NDArray[np.float64]   # N x 2, colour pixels
    object_points: NDArray[np.float64]  # N x 3, board frame (metres)
    ids: NDArray[np.int64]              # corner ids, x fastest (Board.corner_points order)
    markers: int = 0                    # ArUco markers seen (ChArUco only)


def to_gray(color_rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Grey image from RGB (or pass a grey image through)."""
    if color_rgb.ndim == 2:
        return color_rgb
    return np.asarray(cv2.cvtColor(color_rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def charuco_legacy(board: Board) -> bool:
    """OpenCV's legacy ChArUco pattern flag that gives `board.first_square_black`.

    OpenCV >= 4.6 puts a black square at the top-left; its legacy pattern (pre 4.6) differs only
    for an even number of rows, where the top-left square is white.
    """
    return (not board.first_square_black) and board.squares_y % 2 == 0


class BoardDetector:
    """Detects one board type repeatedly; the OpenCV objects are built once."""

    def __init__(self, board: Board, subpix: bool = True, model_fit: bool = True) -> None:
        self.board = board
        self.subpix = subpix
        # plain boards: cornerSubPix's phase-dependent bias (~0.05 px, static for a still camera)
        # removed by an X-junction model fit (~0.01 px); ChArUco corners keep OpenCV's refinement
        # (a marker can reach into the fit window)
        self.model_fit = model_fit and subpix and board.type == "checkerboard"
        self._corners = board.corner_points()
        self._slow_misses = 0
        self._last: NDArray[np.float32] | None = None  # plain board: corners of the last detection
        self._charuco: cv2.aruco.CharucoDetector | None = None
        self._charuco_other: cv2.aruco.CharucoDetector | None = None
        if board.type == "charuco":
            self._charuco = self._make_charuco(charuco_legacy(board))
            if board.squares_y % 2 == 0:
                self._charuco_other = self._make_charuco(not charuco_legacy(board))

    def _make_charuco(self, legacy: bool) -> cv2.aruco.CharucoDetector:
        b = self.board
        name = str(b.dictionary)
        if not hasattr(cv2.aruco, name):

            raise InputError(None, f"board.dictionary '{name}' is not an OpenCV ArUco dictionary")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        cb = cv2.aruco.CharucoBoard((b.squares_x, b.squares_y), b.square_length_m,
                                    float(b.marker_length_m or 0.0), dictionary)
        cb.setLegacyPattern(legacy)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # ChArUco corners are refined
        return cv2.aruco.CharucoDetector(cb, cv2.aruco.CharucoParameters(), params)

    def detect(self, color: NDArray[np.uint8]) -> Detection | None:
        """Corners of the board in an RGB (or grey) image, or None when the board is not found."""
        gray = to_gray(color)
        if self.board.type == "charuco":
            return self._detect_charuco(gray)
        return self._detect_chessboard(gray)

    def _detect_chessboard(self, gray: NDArray[np.uint8]) -> Detection | None:
        """Track the last frame's corners when they still sit on the board's X-junctions (a still
        standpoint: ~1 ms instead of 8-100 ms); otherwise search. The fast check comes first (12 ms
        without a board instead of 260 ms); the full search only while it keeps paying off: small,
        steep boards fail the fast check but are found by the full one."""
        if self._last is not None and self.subpix:
            tracked = self._track(gray, self._last)
            if tracked is not None:
                self._last = tracked
                return Detection(self._model_fit(gray, tracked), self._corners,
                                 np.arange(len(tracked), dtype=np.int64))
        self._last = None
        det = self._search_chessboard(gray)
        if det is not None and self.subpix:
            self._last = det.image_points.astype(np.float32)
            det = Detection(self._model_fit(gray, self._last), det.object_points, det.ids)
        return det

    def _model_fit(self, gray: NDArray[np.uint8], pts: NDArray[np.float32]) -> NDArray[np.float64]:
        """cornerSubPix's corners refined by the X-junction fit (each failed fit keeps its input)."""
        out = pts.astype(np.float64)
        if self.model_fit:
            out, _ = refine_xjunctions(gray, out, self._corners)
        return out

    def _track(self, gray: NDArray[np.uint8], last: NDArray[np.float32],
               max_shift_px: float = 2.0, min_contrast: float = 20.0) -> NDArray[np.float32] | None:
        """Corners refined from the last frame's, or None when the board moved or is not there.

        Accepted only when every corner moved less than `max_shift_px` and every refined corner is
        an X-junction: the two diagonal pairs of neighbouring squares differ by `min_contrast` grey
        levels (a blank or moved image fails that even where cornerSubPix does not move).
        """
        half = self._half_window(last)
        refined = cv2.cornerSubPix(gray, last.reshape(-1, 1, 2).copy(), (half, half), (-1, -1),
                                   _SUBPIX_CRITERIA)
        pts = np.asarray(refined, dtype=np.float32).reshape(-1, 2)
        if not np.all(np.isfinite(pts)) or np.max(np.hypot(*(pts - last).T)) > max_shift_px:
            return None
        cols, rows = self.board.inner_corners
        grid = pts.reshape(rows, cols, 2).astype(np.float64)
        dx = np.asarray(np.gradient(grid, axis=1))  # one corner step along the board's x (px)
        dy = (np.asarray(np.gradient(grid, axis=0)) if rows > 1
              else np.stack([-dx[..., 1], dx[..., 0]], axis=-1))
        h, w = gray.shape

        def grey(offset: NDArray[np.float64]) -> NDArray[np.float64]:
            q = np.rint(grid + offset / 4.0).astype(np.int64)
            u = np.clip(q[..., 0], 0, w - 1)
            v = np.clip(q[..., 1], 0, h - 1)
            return gray[v, u].astype(np.float64)

        same = grey(dx + dy) + grey(-dx - dy)
        other = grey(dx - dy) + grey(dy - dx)
        if float(np.min(np.abs(same - other))) / 2.0 < min_contrast:
            return None
        return pts

    @staticmethod
    def _half_window(pts: NDArray[np.float32]) -> int:
        spacing = float(np.min(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
        return int(np.clip(spacing / 4.0, 2, 11))

    def _search_chessboard(self, gray: NDArray[np.uint8]) -> Detection | None:
        base = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(gray, self.board.inner_corners,
                                                   flags=base | cv2.CALIB_CB_FAST_CHECK)
        if (not found or corners is None) and self._slow_misses < 3:
            found, corners = cv2.findChessboardCorners(gray, self.board.inner_corners, flags=base)
            self._slow_misses = 0 if found else self._slow_misses + 1
        if not found or corners is None:
            return None
        pts = corners.reshape(-1, 2).astype(np.float32)
        if self.subpix:
            half = self._half_window(pts)
            refined = cv2.cornerSubPix(gray, pts.reshape(-1, 1, 2), (half, half), (-1, -1),
                                       _SUBPIX_CRITERIA)
            pts = np.asarray(refined, dtype=np.float32).reshape(-1, 2)
        ids = np.arange(len(pts), dtype=np.int64)
        return Detection(pts.astype(np.float64), self._corners, ids)

    def _detect_charuco(self, gray: NDArray[np.uint8]) -> Detection | None:
        assert self._charuco is not None
        corners, ids, _, marker_ids = self._charuco.detectBoard(gray)
        markers = 0 if marker_ids is None else len(marker_ids)
        if ids is None or len(ids) < 6:
            return None
        idx = np.asarray(ids, dtype=np.int64).reshape(-1)
        pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        return Detection(pts, self._corners[idx], idx, markers)

    def other_pattern_matches(self, color: NDArray[np.uint8]) -> bool:
        """Whether OpenCV's other ChArUco pattern (legacy flag flipped) finds the board here."""
        if self._charuco_other is None:
            return False
        _, ids, _, _ = self._charuco_other.detectBoard(to_gray(color))
        return ids is not None and len(ids) >= 6

    def markers_seen(self, color: NDArray[np.uint8]) -> int:
        """ArUco markers of the board's dictionary in the image (a hint when no corner is found)."""
        if self._charuco is None:
            return 0
        _, _, _, marker_ids = self._charuco.detectBoard(to_gray(color))
        return 0 if marker_ids is None else len(marker_ids)
