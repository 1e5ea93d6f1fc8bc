"""The reference pose's own uncertainty per standpoint (paper Fig. 4): predicted from corner noise
(Cramer-Rao) against the measured scatter of the per-frame pose inclinations, on simulated frames."""

from __future__ import annotations

import csv
import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics

FRAMES = 16
DISTANCES = (1.0, 1.8, 2.6)
TILT_DEG = 8.0  # near-frontal: the worse tilt axis is the inclination's (see docs), no folding at 0


def _vertical_pose(board: Board, distance_m: float, inclination: float) -> Any:
    """Camera above the board's centre line, tilted about the board's long (x) axis."""
    from depthstation.core.geometry import look_at

    a = np.radians(inclination)
    c = board.center
    return look_at(c + distance_m * np.array([0.0, -np.sin(a), -np.cos(a)]), c, up=(0.0, -1.0, 0.0))


def _study(tmp: Path, colour_noise_dn: float | None, monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """Three still standpoints at 1.0, 1.8, 2.6 m (640x360, 16 frames), evaluated."""
    pytest.importorskip("open3d")
    import depthstation.simulate.checkerboard_session as sim
    from depthstation.core.capture.registry import open_inputs
    from depthstation.core.protocol import load_protocol
    from depthstation.evaluate.checkerboard.study import evaluate_recording

    if colour_noise_dn is not None:
        monkeypatch.setattr(sim, "ViewRenderer", functools.partial(sim.ViewRenderer,
                                                                   color_noise_dn=colour_noise_dn))
    proto = load_protocol("demo-d455")
    names = [s.name for s in proto.plan.standpoints()][:len(DISTANCES)]
    poses = {n: _vertical_pose(proto.board, d, TILT_DEG) for n, d in zip(names, DISTANCES, strict=True)}
    out = sim.simulate_checkerboard(proto, "d455-ideal", tmp / "sim", frames=FRAMES, standpoints=names,
                                    poses=poses, seed=1)
    recs = sorted(open_inputs([out]), key=lambda r: r.name)
    results = [evaluate_recording(r, proto.board, frames=FRAMES) for r in recs]
    for r in results:
        assert r.frames_used == FRAMES, r.rejected
    return results


def _std_ratio_bounds(dof: int, alpha: float = 1e-3) -> tuple[float, float]:
    """Two-sided bounds of (sample std / true std) with `dof` degrees of freedom (chi-square)."""
    from scipy import stats

    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], dof)
    return float(np.sqrt(lo / dof)), float(np.sqrt(hi / dof))


def test_measured_pose_scatter_matches_the_corner_noise_prediction(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """With 8 grey levels of colour noise the random corner noise (~0.02 px) dwarfs the static
    corner error (~0.005 px), so the residual-based corner noise is the random one and the
    predicted single-frame std must agree with the std over frames to within the sampling error
    of 16 frames; both grow with distance."""
    results = _study(tmp_path, 8.0, monkeypatch)
    lo, hi = _std_ratio_bounds(FRAMES - 1)
    predicted, measured = [], []
    for r in results:
        f = r.figures
        one = f["inclination_std_deg"] * np.sqrt(r.frames_used)
        ratio = f["inclination_frame_std_deg"] / one
        assert lo < ratio < hi, (r.name, f["inclination_frame_std_deg"], one)
        assert 0.005 < f["corner_noise_px"] < 0.05
        predicted.append(f["inclination_std_deg"])
        measured.append(f["inclination_frame_std_deg"])
    assert predicted[0] < predicted[1] < predicted[2]
    assert predicted[2] > 3 * predicted[0]  # ~ distance^2 for near-frontal tilt
    assert measured[2] > 2 * measured[0]


def test_default_colour_noise_prediction_is_conservative(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """At the simulator's 2 grey levels the residuals also hold the static corner error, so the
    prediction may only overstate: the measured scatter is never significantly above it. The
    result folder carries the columns, frames.csv the per-frame corner noise and inclination."""
    from depthstation.core.protocol import load_protocol
    from depthstation.evaluate.checkerboard.report import write_study

    results = _study(tmp_path, None, monkeypatch)
    hi = _std_ratio_bounds(FRAMES - 1)[1]
    for r in results:
        f = r.figures
        assert f["inclination_frame_std_deg"] < hi * f["inclination_std_deg"] * np.sqrt(r.frames_used)
    board = load_protocol("demo-d455").board
    out = tmp_path / "study"
    pngs = write_study(out, results, board, ["sim"], {}, {})
    assert out / "fig4_reference_distance_std.png" in pngs
    with (out / "standpoints.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [float(row["inclination_std_deg"]) for row in rows] == pytest.approx(
        [r.figures["inclination_std_deg"] for r in results], rel=1e-5)
    with (out / "frames.csv").open() as fh:
        frames = [row for row in csv.DictReader(fh) if row["standpoint"] == results[0].name]
    incl = np.array([float(row["inclination_deg"]) for row in frames])
    # frames.csv keeps 6 significant digits (1e-5 deg at 8 deg): the std agrees to that
    assert incl.std(ddof=1) == pytest.approx(results[0].figures["inclination_frame_std_deg"], abs=2e-5)
    assert all(float(row["corner_noise_px"]) > 0 for row in frames)
    summary = json.loads((out / "summary.json").read_text())
    assert "static corner bias" in summary["pose_uncertainty"]
    assert summary["standpoints"][0]["figures"]["inclination_std_deg"] > 0


def test_frame_corner_noise_equals_the_residual_estimate() -> None:
    """The per-frame corner noise recovered from RMS and corner count is pose.corner_noise_px."""
    import cv2

    from depthstation.core.board_pose import solve_board_pose
    from depthstation.evaluate.checkerboard.detection import Detection
    from depthstation.evaluate.checkerboard.frame import FrameResult
    from depthstation.evaluate.checkerboard.pose import corner_noise_px
    from depthstation.evaluate.checkerboard.study import frame_corner_noise_px

    intr = Intrinsics(640, 360, 460.0, 460.0, 319.5, 179.5, "none", (0.0,) * 5)
    board = Board()
    obj = board.corner_points()
    pose = _board_to_camera(_vertical_pose(board, 2.0, 20.0))
    uv, _ = cv2.projectPoints(obj, cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], intr.K, np.zeros(5))
    det = Detection(uv.reshape(-1, 2) + np.random.default_rng(0).normal(0, 0.03, (len(obj), 2)), obj,
                    np.arange(len(obj)))
    p = solve_board_pose(det.object_points, det.image_points, intr)
    assert p is not None
    res = FrameResult(0, 0, reprojection_px=p.reprojection_px, corners=len(obj))
    assert frame_corner_noise_px(res) == pytest.approx(corner_noise_px(p, det, intr), rel=1e-9)
    assert frame_corner_noise_px(FrameResult(1, 0)) != frame_corner_noise_px(FrameResult(1, 0))  # NaN


def _board_to_camera(cam_to_board: Any) -> Any:
    return np.linalg.inv(np.asarray(cam_to_board, dtype=np.float64))
