"""Calibration boards (plain checkerboard or ChArUco): geometry in the board frame and square colours.

Board frame: origin at the outer top-left corner of the square grid, x along the columns
(`squares_x`), y along the rows (`squares_y`), z = x cross y, pointing into the board (away from a
camera that sees the board's front). The board surface is z = 0; its centre is
(squares_x * s / 2, squares_y * s / 2, 0).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import InputError

BOARD_TYPES = ("checkerboard", "charuco")
REQUIRED_MEANING = {
    "type": "checkerboard or charuco",
    "squares_x": "squares along the board's long side",
    "squares_y": "squares along the short side",
    "square_length_m": "the printed square's side in metres: it sets every distance the study reports",
    "marker_length_m": "the ArUco marker's side in metres",
    "dictionary": "the ArUco dictionary, e.g. DICT_4X4_50",
}


@dataclass(frozen=True)
class Board:
    """A printed board; lengths in metres."""

    type: str = "checkerboard"
    squares_x: int = 7
    squares_y: int = 5
    square_length_m: float = 0.095
    marker_length_m: float | None = None
    dictionary: str | None = None
    first_square_black: bool = True
    plate_margin_m: float = 0.05

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(columns, rows) of inner corners: OpenCV's `patternSize` for the plain board."""
        return self.squares_x - 1, self.squares_y - 1

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_length_m, self.squares_y * self.square_length_m

    @property
    def center(self) -> NDArray[np.float64]:
        w, h = self.size_m
        return np.array([w / 2, h / 2, 0.0])

    def corner_points(self) -> NDArray[np.float64]:
        """Inner corners (N x 3, board frame), x fastest: OpenCV's chessboard and ChArUco id order."""
        cx, cy = self.inner_corners
        j, i = np.mgrid[1:cy + 1, 1:cx + 1]
        s = self.square_length_m
        return np.stack([i.ravel() * s, j.ravel() * s, np.zeros(i.size)], axis=1).astype(np.float64)

    def is_black(self, x: NDArray[Any], y: NDArray[Any]) -> NDArray[np.bool_]:
        """Whether board-frame points (x, y) fall on a black square (False outside the grid too)."""
        s = self.square_length_m
        col = np.floor(np.asarray(x) / s).astype(np.int64)
        row = np.floor(np.asarray(y) / s).astype(np.int64)
        inside = (col >= 0) & (col < self.squares_x) & (row >= 0) & (row < self.squares_y)
        parity = ((col + row) % 2 == 0) == self.first_square_black
        return inside & parity

    def inside(self, x: NDArray[Any], y: NDArray[Any], margin_m: float = 0.0) -> NDArray[np.bool_]:
        """Whether board-frame points lie on the square grid, shrunk by `margin_m` on every side."""
        w, h = self.size_m
        x = np.asarray(x)
        y = np.asarray(y)
        return (x >= margin_m) & (x <= w - margin_m) & (y >= margin_m) & (y <= h - margin_m)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str | Path | None = None) -> Board:
        """Validate a board table (board.json or a protocol's [board]); errors name the key."""
        known = set(cls.__dataclass_fields__)
        for key in d:
            if key not in known:
                raise InputError(source, f"board: unknown key '{key}'")
        # the geometry the study measures against has no default: a missing size is not 0.095 m
        required = ["type", "squares_x", "squares_y", "square_length_m"]
        if d.get("type") == "charuco":
            required += ["marker_length_m", "dictionary"]
        missing = [k for k in required if k not in d]
        if missing:
            raise InputError(source, f"board: missing key '{missing[0]}' ({REQUIRED_MEANING[missing[0]]})")
        btype = str(d["type"])
        if btype not in BOARD_TYPES:
            raise InputError(source, f"board.type must be one of {BOARD_TYPES}, got '{btype}'")
        for key in ("squares_x", "squares_y"):
            if isinstance(d[key], bool) or not isinstance(d[key], int):
                raise InputError(source, f"board.{key} must be a whole number, got {d[key]!r}")
        for key in ("square_length_m", "marker_length_m", "plate_margin_m"):
            if key in d and (isinstance(d[key], bool) or not isinstance(d[key], (int, float))
                             or not math.isfinite(float(d[key]))):
                raise InputError(source, f"board.{key} must be a number in metres, got {d[key]!r}")
        if "first_square_black" in d and not isinstance(d["first_square_black"], bool):
            got = d["first_square_black"]
            raise InputError(source, f"board.first_square_black must be true or false, got {got!r}")
        try:
            board = cls(
                type=btype,
                squares_x=int(d["squares_x"]),
                squares_y=int(d["squares_y"]),
                square_length_m=float(d["square_length_m"]),
                marker_length_m=None if d.get("marker_length_m") is None else float(d["marker_length_m"]),
                dictionary=None if d.get("dictionary") is None else str(d["dictionary"]),
                first_square_black=bool(d.get("first_square_black", True)),
                plate_margin_m=float(d.get("plate_margin_m", 0.05)),
            )
        except (TypeError, ValueError) as exc:
            raise InputError(source, f"board: {exc}") from exc
        if board.plate_margin_m < 0:
            raise InputError(source, "board.plate_margin_m must be >= 0")
        if board.squares_x < 3 or board.squares_y < 3:
            raise InputError(source, "board.squares_x and board.squares_y must be at least 3")
        if not 0.005 < board.square_length_m < 1.0:
            raise InputError(source, "board.square_length_m must be in metres (0.005 to 1)")
        if btype == "charuco":
            if board.marker_length_m is None or board.dictionary is None:
                raise InputError(source, "board: a charuco board needs marker_length_m and dictionary")
            if not 0 < board.marker_length_m < board.square_length_m:
                raise InputError(source, "board.marker_length_m must be smaller than square_length_m")
            if board.marker_length_m < 0.2 * board.square_length_m:  # 1 mm markers in 80 mm squares
                small = board.marker_length_m
                raise InputError(source, f"board.marker_length_m {small:g} m is under a fifth of the square "
                                         f"({board.square_length_m:g} m): no ArUco marker is printed that "
                                         "small in its square; metres, not millimetres?")
            if not (board.dictionary.startswith("DICT_") and hasattr(cv2.aruco, board.dictionary)):
                names = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n)
                close = [n for n in names if n.lower() == board.dictionary.lower()]
                hint = f" (did you mean {close[0]}?)" if close else f" (e.g. {', '.join(names[:4])}, ...)"
                raise InputError(source, f"board.dictionary '{board.dictionary}' is not an OpenCV ArUco "
                                         f"dictionary{hint}")
        return board
