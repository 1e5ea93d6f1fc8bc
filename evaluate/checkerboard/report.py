"""The study's result folder: standpoints.csv, frames.csv, summary.json, result.json."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.board import Board
from depthstation.core.results import software_versions, write_json, write_result_info
from depthstation.evaluate.checkerboard.dqt import DQT_COLUMNS
from depthstation.evaluate.checkerboard.figures import write_figures
from depthstation.evaluate.checkerboard.frame import FrameResult
from depthstation.evaluate.checkerboard.study import (
    StandpointResult,
    frame_corner_noise_px,
    frame_inclination_deg,
)

COLUMNS = ("standpoint", "frames", "frames_read", "distance_m", "inclination_deg",
           "inclination_depth_deg", "pose_depth_normal_angle_deg",
           "reference_distance_std_m", "fill_rate", "fill_rate_std", "noise_m", "noise_std_m",
           "accuracy_m", "accuracy_std_m", "accuracy_rms_m", "accuracy_rms_std_m",
           "noise_black_m", "noise_black_std_m", "noise_white_m", "noise_white_std_m",
           "accuracy_black_m", "accuracy_black_std_m", "accuracy_white_m", "accuracy_white_std_m",
           "noise_black_white_p", "noise_black_white_paired_p", "accuracy_black_white_p",
           "accuracy_black_white_paired_p", "accuracy_frame_pose_m", "reprojection_px",
           "corner_shift_px", "pixels_per_frame", "corner_noise_px", "inclination_std_deg",
           "inclination_frame_std_deg", "reference_plane",
           "distance_m_u95", "inclination_deg_u95", "noise_m_u95", "accuracy_m_u95",
           "corner_random_px", "corner_static_px", *DQT_COLUMNS)
FRAME_COLUMNS = ("standpoint", "index", "timestamp_ns", "status", "corners", "reprojection_px",
                 "corner_shift_px", "reference_distance_m", "board_pixels", "valid_pixels",
                 "fill_rate", "noise_m", "noise_black_m", "noise_white_m", "accuracy_m",
                 "accuracy_rms_m", "accuracy_black_m", "accuracy_white_m", "accuracy_own_m",
                 "temperature_c", "corner_noise_px", "inclination_deg")
# frames.csv columns derived from a FrameResult rather than stored on it
_FRAME_DERIVED: dict[str, Callable[[FrameResult, Board], float]] = {
    "corner_noise_px": lambda f, board: frame_corner_noise_px(f), "inclination_deg": frame_inclination_deg}


def _cell(v: Any) -> Any:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return v


def standpoint_row(r: StandpointResult) -> dict[str, Any]:
    row = {**r.row(), "reference_plane": r.reference_plane}
    return {c: _cell(row.get(c, float("nan"))) for c in COLUMNS}


def frame_row(r: StandpointResult, f: FrameResult, board: Board) -> dict[str, Any]:
    """One row of frames.csv (a frame's own corner noise and pose inclination included)."""
    row = {"standpoint": r.name}
    for c in FRAME_COLUMNS[1:]:
        derive = _FRAME_DERIVED.get(c)
        row[c] = _cell(derive(f, board) if derive is not None else getattr(f, c))
    return row


def write_tables(out: Path, results: list[StandpointResult], board: Board) -> None:
    """standpoints.csv (one row per standpoint) and frames.csv (one row per frame read)."""
    with (out / "standpoints.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in results:
            w.writerow(standpoint_row(r))
    with (out / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FRAME_COLUMNS)
        w.writeheader()
        for r in results:
            for f in r.frames:
                w.writerow(frame_row(r, f, board))


def absorbed(board: Board) -> dict[str, str]:
    """What the reference pose takes as exact, so that every figure carries its error, and none of
    it is in <figure>_u95: a reader must know it before calling a few per cent the camera's."""
    return {
        "board_scale": f"square_length_m {board.square_length_m:g} is taken as the print's: a print k % "
                       "larger places the reference k % nearer (distance_m reads k % short, accuracy_m "
                       "k % of the distance too far); the recording's own board is compared where it names "
                       "one (board-mismatch), and depth checks it to 5 % (board-scale)",
        "colour_intrinsics": "the colour camera's focal length from the recording: k % too long places the "
                             "reference k % farther (distance_m k % long, accuracy_m k % of the distance "
                             "too near)",
        "depth_to_colour": "the recording's depth-to-colour extrinsics: a translation error moves the "
                           "reference plane by its component along the board's normal (accuracy_m)",
    }


def summary(results: list[StandpointResult], board: Board, inputs: list[str],
            parameters: dict[str, Any], device: dict[str, Any]) -> dict[str, Any]:
    """Everything a reader needs to trust the table: inputs, board, software, per-standpoint detail."""
    stand: list[dict[str, Any]] = []
    for r in results:
        entry: dict[str, Any] = {
            "name": r.name, "path": r.path, "frames_requested": r.frames_requested,
            "frames_read": r.frames_read, "frames_used": r.frames_used, "rejected": r.rejected,
            "notes": r.notes, "reference_plane": r.reference_plane, "figures": r.figures,
            "pose_board_to_depth": None if r.pose_depth is None else r.pose_depth.tolist(),
            "camera_in_board": None if r.camera_in_board is None else r.camera_in_board.tolist(),
        }
        if r.truth is not None:
            entry["truth"] = r.truth
        stand.append(entry)
    return {
        "inputs": inputs, "device": device, "board": board.to_dict(), "parameters": parameters,
        "software": software_versions(), "standpoints": stand,
        "unusable_standpoints": [r.name for r in results if not r.usable],
        "frames_rejected": {r.name: r.rejected for r in results if r.rejected},
        "conventions": "DESIGN §2: distance = z-depth of the board centre in the depth frame; "
                       "inclination = ray to centre vs board normal; noise = RMS orthogonal "
                       "residual to the frame's SVD plane; accuracy = mean signed orthogonal "
                       "distance to the reference plane, positive = behind it (too far).",
        "expanded_uncertainty": "<figure>_u95 = k u_c, k = t(0.975, frames - 1) (GUM): distance and "
                                "inclination from the pose's random corner noise (corner_random_px, "
                                "averaged over the frames; at least the frames' own scatter of the "
                                "pose, also for the reference plane) and a static corner error "
                                "(corner_static_px from the mean residuals, at least 0.01 px) through "
                                "the Jacobian of the corners seen (each weighted by the frames that saw it); "
                                "inclination near 0 deg as a folded magnitude (Rayleigh bound); "
                                "noise from the frames' scatter plus 0.4 % for the estimator; "
                                "accuracy from the frames' scatter plus the reference plane's offset "
                                "uncertainty. See docs/checkerboard-study.md.",
        "absorbed": absorbed(board),
        "pose_uncertainty": "inclination_std_deg = Cramer-Rao std of the averaged pose's normal "
                            "(worse tilt axis) from the mean per-frame corner noise (corner_noise_px, "
                            "from reprojection residuals) over the frames used; "
                            "inclination_frame_std_deg = std of the per-frame pose inclinations. "
                            "Random corner noise only: a static corner bias (the same every frame) "
                            "is not in either and does not average out.",
    }


def write_study(out: Path, results: list[StandpointResult], board: Board, inputs: list[str],
                parameters: dict[str, Any], device: dict[str, Any], figures: bool = True,
                caption: str = "") -> list[Path]:
    """Write the whole result folder; returns the figure files."""
    out.mkdir(parents=True, exist_ok=True)
    write_tables(out, results, board)
    write_json(out / "summary.json", summary(results, board, inputs, parameters, device))
    pngs: list[Path] = []
    if figures:

        pngs = write_figures(out, results, board, caption)
    samples = [r for r in results if r.samples is not None]
    if samples:
        arrays: dict[str, Any] = {}
        for r in samples:
            assert r.samples is not None
            for k, v in r.samples.to_dict().items():
                arrays[f"{r.name}/{k}"] = v
        np.savez_compressed(out / "samples.npz", **arrays)
    write_result_info(out, "checkerboard", inputs, parameters, device,
                      extra={"standpoints": len(results), "files": ["standpoints.csv", "frames.csv",
                             "summary.json", *(p.name for p in pngs)]})
    return pngs
