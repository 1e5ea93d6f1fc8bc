"""Board corners in a colour image: plain chessboard (fast check + cornerSubPix + X-junction model
fit, `corners.py`) or ChArUco (cv2 5 API)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics
from depthstation.core.errors import InputError
from depthstation.evaluate.checkerboard.corners import refine_xjunctions

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# A corner is confirmed when it lies on the plane's projection of the other corners: its residual
# against a robust homography fit stays below OUTLIER_FLOOR_PX and OUTLIER_SIGMAS robust standard
# deviations of the frame's residuals. Good corners reproject within 0.01-0.05 px (simulated
# D455, 1-6 m, 0-60 deg; docs/checkerboard-study.md), so 0.5 px is 10-50 of their sigmas, while a
# corner OpenCV put on the wrong junction or an edge (11.7 px at 5.8 m / 45 deg, seed 1) is far
# beyond it.
OUTLIER_FLOOR_PX = 0.5
OUTLIER_SIGMAS = 8.0
UNCONFIRMED = "off the plane of the others"  # in every rejection of a frame for an unconfirmed corner


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


def corner_residuals(image_points: NDArray[np.float64], object_points: NDArray[np.float64],
                     intr: Intrinsics | None = None) -> NDArray[np.float64]:
    """Each corner's distance (px) from the board plane's projection fitted robustly to the corners
    (`plane_fit`); NaN for every corner when fewer than 5 corners or no fit."""
    return plane_fit(image_points, object_points, intr)[0]


def plane_fit(image_points: NDArray[np.float64], object_points: NDArray[np.float64],
              intr: Intrinsics | None = None, trusted: NDArray[np.bool_] | None = None
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(residuals in px, predicted pixel positions N x 2) of the corners against the board plane's
    projection: RANSAC (OpenCV's, seeded: the same answer every run) with the outlier floor as
    its threshold, then least squares on the corners within the outlier bound. A corner's
    prediction is where the others put it. Half the corners may be off: cornerSubPix put 11 of
    24 corners 1.0-1.4 px off on a blurred board at 4.5 m / 60 deg.

    With `intr` the lens is inverted first, so that a plane maps by an exact homography (the
    distortion of a wide board would otherwise read as residuals), and the predictions are
    distorted back; without, the pixels are taken as a pinhole's. `trusted`: fit to these corners
    only (at least 6 of them; else to all). NaN when fewer than 5 corners.
    """
    img = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    obj = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)[:, :2]
    n = len(img)
    nan = (np.full(n, np.nan), np.full((n, 2), np.nan))
    if n < 5:
        return nan
    lens = intr is not None and bool(np.any(intr.opencv_distortion() != 0.0))
    if lens:
        assert intr is not None
        iterated = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)
        img = np.asarray(iterated(img.reshape(-1, 1, 2), intr.K, intr.opencv_distortion(), R=np.eye(3),
                                  P=intr.K, criteria=_UNDISTORT_CRITERIA), dtype=np.float64).reshape(-1, 2)
    use = (np.asarray(trusted, dtype=bool) if trusted is not None and np.count_nonzero(trusted) >= 6
           else np.ones(n, dtype=bool))
    hmat, _ = cv2.findHomography(obj[use], img[use], cv2.RANSAC, OUTLIER_FLOOR_PX, maxIters=2000,
                                 confidence=0.999)
    if hmat is None or not np.all(np.isfinite(hmat)):
        return nan

    def predicted(h: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.column_stack([obj, np.ones(n)]) @ h.T
        return np.asarray(p[:, :2] / p[:, 2:3], dtype=np.float64)

    pred = predicted(hmat)
    res = np.hypot(*(pred - img).T)
    keep = use & (res <= outlier_bound(res[use]))
    if keep.sum() >= 5:
        refit, _ = cv2.findHomography(obj[keep], img[keep], 0)
        if refit is not None and np.all(np.isfinite(refit)):
            pred = predicted(refit)
            res = np.hypot(*(pred - img).T)
    if lens:
        assert intr is not None
        rays = np.column_stack([(pred[:, 0] - intr.ppx) / intr.fx, (pred[:, 1] - intr.ppy) / intr.fy,
                                np.ones(n)])
        uv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intr.K, intr.opencv_distortion())
        pred = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    return np.asarray(res, dtype=np.float64), pred


def outlier_bound(residuals: NDArray[np.float64]) -> float:
    """The residual (px) above which a corner is not confirmed: OUTLIER_SIGMAS standard deviations
    of the corners' noise, at least OUTLIER_FLOOR_PX. The noise is read off the best quarter (the
    lower quartile of a 2-D Gaussian's magnitude is 0.759 sigma), so that up to three quarters of
    the corners may be off without widening the bound."""
    q = float(np.nanpercentile(residuals, 25)) if np.any(np.isfinite(residuals)) else 0.0
    return max(OUTLIER_FLOOR_PX, OUTLIER_SIGMAS * q / 0.7585)


def corner_outliers(image_points: NDArray[np.float64], object_points: NDArray[np.float64],
                    intr: Intrinsics | None = None) -> NDArray[np.bool_]:
    """Corners that disagree with the board plane the others lie on (`corner_residuals`)."""
    res = corner_residuals(image_points, object_points, intr)
    return np.asarray(np.isfinite(res) & (res > outlier_bound(res)), dtype=bool)


def unconfirmed(status: str) -> bool:
    """Whether a frame's status says it was dropped for a corner no detector confirmed."""
    return UNCONFIRMED in status


def charuco_legacy(board: Board) -> bool:
    """OpenCV's legacy ChArUco pattern flag that gives `board.first_square_black`.

    OpenCV >= 4.6 puts a black square at the top-left; its legacy pattern (pre 4.6) differs only
    for an even number of rows, where the top-left square is white.
    """
    return (not board.first_square_black) and board.squares_y % 2 == 0


class BoardDetector:
    """Detects one board type repeatedly; the OpenCV objects are built once."""

    def __init__(self, board: Board, subpix: bool = True, model_fit: bool = True,
                 intr: Intrinsics | None = None) -> None:
        self.board = board
        self.subpix = subpix
        self.intr = intr  # the colour lens: corners are checked against the plane in its undistorted pixels
        # why the last image gave no detection although OpenCV found a board (None: not found)
        self.rejection: str | None = None
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
        self.rejection = None
        if self.board.type == "charuco":
            return self._detect_charuco(gray)
        return self._detect_chessboard(gray)

    def _detect_chessboard(self, gray: NDArray[np.uint8]) -> Detection | None:
        """Track the last frame's corners when they still sit on the board's X-junctions (a still
        standpoint: ~1 ms instead of 8-100 ms); otherwise search. The fast check comes first (12 ms
        without a board instead of 260 ms); the full search only while it keeps paying off: small,
        steep boards fail the fast check but are found by the full one.

        Every corner kept is confirmed: it lies on the plane the other corners span
        (`corner_outliers`). A tracked set that fails is searched afresh; a search that fails is
        redone by OpenCV's sector-based detector (findChessboardCornersSB, which found the corner
        the classic search put 11.7 px off within 0.45 px); when that fails too, the frame is
        dropped (`rejection` says why) rather than carrying a corner no detector confirms."""
        if self._last is not None and self.subpix:
            tracked = self._track(gray, self._last)
            if tracked is not None:
                fitted = self._model_fit(gray, tracked)
                if not np.any(corner_outliers(fitted, self._corners, self.intr)):
                    self._last = tracked
                    return Detection(fitted, self._corners, np.arange(len(tracked), dtype=np.int64))
        self._last = None
        det = self._search_chessboard(gray)
        if det is None or not self.subpix:
            return det
        for search in (lambda: det, lambda: self._search_sb(gray, det)):  # the second only when needed
            attempt = search()
            if attempt is None:
                continue
            fitted = self._model_fit(gray, attempt.image_points.astype(np.float32))
            res = corner_residuals(fitted, attempt.object_points, self.intr)
            worst = int(np.nanargmax(res)) if np.any(np.isfinite(res)) else -1
            if worst < 0 or res[worst] <= outlier_bound(res):
                self._last = attempt.image_points.astype(np.float32)
                return Detection(fitted, attempt.object_points, attempt.ids)
            self.rejection = (f"board corner {worst} lies {res[worst]:.1f} px {UNCONFIRMED}; "
                              "no detection confirmed it")
        return None

    def _search_sb(self, gray: NDArray[np.uint8], like: Detection) -> Detection | None:
        """OpenCV's sector-based chessboard detector, its corners refined like the classic's and
        in the classic detection's order (`like`: the two may start at opposite ends of the board)."""
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        found, corners = cv2.findChessboardCornersSB(gray, self.board.inner_corners, flags=flags)
        if not found or corners is None:
            return None
        pts = corners.reshape(-1, 2).astype(np.float32)
        if len(pts) == len(like.image_points):
            ahead = float(np.median(np.hypot(*(pts - like.image_points).T)))
            turned = float(np.median(np.hypot(*(pts[::-1] - like.image_points).T)))
            if turned < ahead:
                pts = np.ascontiguousarray(pts[::-1])
        return self._refined(gray, pts)

    def _model_fit(self, gray: NDArray[np.uint8], pts: NDArray[np.float32]) -> NDArray[np.float64]:
        """cornerSubPix's corners refined by the X-junction fit (each failed fit keeps its input).

        A corner off the plane of the others is fitted again from where the others put it: on
        small blurred squares cornerSubPix lands up to 1.5 px off (a camera-like image at 4.5 m /
        60 deg, tests/test_checkerboard_outliers.py), further than the fit may move a corner;
        the plane comes from the corners whose fit succeeded."""
        out = pts.astype(np.float64)
        if not self.model_fit:
            return out
        out, fitted = refine_xjunctions(gray, out, self._corners)
        res, pred = plane_fit(out, self._corners, self.intr, trusted=fitted)
        bad = ~fitted | (np.isfinite(res) & (res > outlier_bound(res[fitted] if fitted.sum() >= 6 else res)))
        if np.any(bad) and np.all(np.isfinite(pred[bad])):
            again, ok = refine_xjunctions(gray, np.where(bad[:, None], pred, out), self._corners)
            take = bad & ok
            out[take] = again[take]
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
        return self._refined(gray, corners.reshape(-1, 2).astype(np.float32))

    def _refined(self, gray: NDArray[np.uint8], pts: NDArray[np.float32]) -> Detection:
        """A full board's corners (x fastest) through cornerSubPix (when subpix)."""
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
        # ChArUco corners come fresh from the markers each frame (OpenCV's own refinement): one
        # off the plane of the others is dropped, the rest kept
        bad = corner_outliers(pts, self._corners[idx], self.intr)
        if np.any(bad):
            idx, pts = idx[~bad], pts[~bad]
            if len(idx) < 6:
                self.rejection = f"{int(bad.sum())} ChArUco corners lie {UNCONFIRMED}; {len(idx)} left"
                return None
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
