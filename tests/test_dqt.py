"""Intel's Depth Quality Tool metrics: on a simulated frontal wall they read the model's disparity
noise and Intel's expected RMS; the plane fit is the DQT's; the study and compare carry them."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from depthstation.evaluate.checkerboard.dqt import (
    DQT_COLUMNS,
    TemporalStack,
    centred_roi,
    expected_rms_mm,
    frame_metrics,
    plane_from_sums,
)


def _rays(intr: object, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
    rx = (np.arange(x0, x1) - intr.ppx) / intr.fx  # type: ignore[attr-defined]
    ry = (np.arange(y0, y1) - intr.ppy) / intr.fy  # type: ignore[attr-defined]
    shape = (ry.size, rx.size)
    return np.broadcast_to(rx[None, :], shape), np.broadcast_to(ry[:, None], shape)


@pytest.mark.parametrize("distance_m", [1.0, 2.5, 4.0])
def test_frontal_wall_reads_the_model_disparity_noise(distance_m: float) -> None:
    """Subpixel RMS = the model's matching noise (white 0.04 px and window-shared 0.07 px: 0.081 px)
    within 10 %, and the plane-fit RMS = Intel's Z^2 subpixel / (f B) within 10 %; both read ~4 %
    low from the DQT's 0.5 % trimming of each tail (a Gaussian cut at 2.58 sigma keeps 96 % of its RMS)."""
    from depthstation.simulate.model import load_model
    from depthstation.simulate.scene import Scene, Surface, quad
    from depthstation.simulate.view_renderer import ViewRenderer

    model = load_model("d455-ideal")
    # the subpixel RMS sees the whole matching noise: white and window-shared parts together
    sigma = float(np.hypot(*(model.effect(name).params["sigma_px"]  # type: ignore[union-attr]
                             for name in ("disparity_noise", "window_noise"))))
    info = model.camera.stream_info(640, 360, 30.0)
    di = info.depth_intrinsics
    z = distance_m
    wall = Scene([Surface("wall", *quad(np.array([[-30, -30, z], [30, -30, z], [30, 30, z], [-30, 30, z]])))])
    renderer = ViewRenderer(wall, model, info, seed=1, color=False)
    renderer.set_pose(np.eye(4))
    x0, y0, x1, y1 = centred_roi(di.width, di.height, 0.4)
    rx, ry = _rays(di, x0, y0, x1, y1)
    every = np.ones((y1 - y0, x1 - x0), dtype=bool)
    centre = np.array([(di.width / 2 - di.ppx) / di.fx, (di.height / 2 - di.ppy) / di.fy, 1.0])
    frames, stack = [], TemporalStack()
    for i in range(4):
        fs = renderer.frame(i, i * 33_333_333, rng=np.random.default_rng([7, i]))
        assert fs.depth is not None
        frames.append(frame_metrics(fs.depth[y0:y1, x0:x1], every, rx, ry, info.depth_units_m, every.size,
                                    info.stereo.fx, info.baseline_m, centre))
        if stack.rows is None:
            r, c = np.mgrid[y0:y1, x0:x1]
            stack.start(r.ravel(), c.ravel())
        stack.add(fs.depth)
    sub = np.mean([f.subpixel_rms_px for f in frames])
    assert sub == pytest.approx(sigma, rel=0.10)
    dist = np.mean([f.distance_mm for f in frames])
    assert dist == pytest.approx(1000 * z, rel=0.002)
    rms = np.mean([f.plane_fit_rms_mm for f in frames])
    assert rms / expected_rms_mm(dist, info.stereo.fx, info.baseline_m) == pytest.approx(1.0, abs=0.10)
    # the tool's range-based subpixel reads lower off the centre (cos^3 of the off-axis angle)
    assert np.mean([f.subpixel_rms_tool_px for f in frames]) < sub
    assert all(f.fill_rate_pct > 95 for f in frames)
    assert abs(np.mean([f.z_accuracy_pct(1000 * z) for f in frames])) < 0.3  # unbiased model
    # temporal noise ~ the depth noise relative to depth (4 frames: the std reads a little low)
    assert 0.6 < stack.noise_pct(info.depth_units_m) / (100 * rms / dist) < 1.1


def test_plane_fit_and_trimming_are_the_dqts() -> None:
    """The dominant-axis fit finds a tilted plane exactly; the trim removes n // 200 points at each
    end of z even when depth values tie (millimetre steps)."""
    rng = np.random.default_rng(3)
    n_true = np.array([0.3, -0.2, 1.0])
    n_true /= np.linalg.norm(n_true)
    h, w = 120, 160
    rx = (np.arange(w) - 80) / 200.0
    ry = (np.arange(h) - 60) / 200.0
    rays = np.stack(np.broadcast_arrays(rx[None, :], ry[:, None], np.ones((h, w))), axis=-1)
    z = 1.5 / (rays @ n_true)  # plane n.p = 1.5 m
    raw = np.rint(z * 1000 + rng.normal(0, 2, z.shape)).astype(np.uint16)
    inside = np.ones((h, w), bool)
    inside[:10] = False
    rxx, ryy = np.broadcast_to(rx[None, :], (h, w)), np.broadcast_to(ry[:, None], (h, w))
    f = frame_metrics(raw, inside, rxx, ryy, 0.001, inside.size, 600.0, 0.095, np.array([0.0, 0.0, 1.0]))
    assert f.distance_mm == pytest.approx(1500, abs=1.0)
    assert f.fill_rate_pct == pytest.approx(100 * 110 / 120)
    zz = raw[inside] * 0.001
    pts = np.stack([zz * np.broadcast_to(rx, (h, w))[inside],
                    zz * np.broadcast_to(ry[:, None], (h, w))[inside], zz], axis=-1)
    s = pts.sum(axis=0)
    ss = np.array([pts[:, 0] @ pts[:, 0], pts[:, 0] @ pts[:, 1], pts[:, 0] @ pts[:, 2],
                   pts[:, 1] @ pts[:, 1], pts[:, 1] @ pts[:, 2], pts[:, 2] @ pts[:, 2]])
    plane = plane_from_sums(len(pts), s, ss)
    assert plane is not None
    assert float(plane[0] @ n_true) > 1 - 1e-5
    # the trimmed RMS: recompute by sorting (the DQT's way) and compare
    k = len(pts) // 200
    order = np.argsort(pts[:, 2], kind="stable")[k:len(pts) - k]
    resid = pts[order] @ plane[0] + plane[1]
    assert f.plane_fit_rms_mm == pytest.approx(1000 * np.sqrt(np.mean(resid**2)), rel=2e-3)
    assert f.median_distance_mm == pytest.approx(1000 * np.sort(resid)[len(resid) // 2], abs=0.05)


def test_study_table_and_roi(tmp_path: Path) -> None:
    """A simulated standpoint through the study: the dqt_* columns (and dqt_roi_* with --roi 40)
    in standpoints.csv; the DQT distance is the board's; a bad --roi is exit 2."""
    pytest.importorskip("open3d")
    from depthstation.core.capture.registry import open_inputs
    from depthstation.core.errors import InputError
    from depthstation.core.protocol import load_protocol
    from depthstation.evaluate.checkerboard.chunks import StandpointOptions
    from depthstation.evaluate.checkerboard.report import COLUMNS, standpoint_row
    from depthstation.evaluate.checkerboard.run import prepare_checkerboard
    from depthstation.evaluate.checkerboard.study import evaluate_recording
    from depthstation.simulate.checkerboard_session import simulate_checkerboard

    proto = load_protocol("demo-d455")
    out = simulate_checkerboard(proto, "d455-ideal", tmp_path / "sim", frames=3,
                                standpoints=["standpoint_01"],
                                seed=2)
    rec = open_inputs([out])[0]
    r = evaluate_recording(rec, proto.board, frames=3, roi=0.4)
    row = standpoint_row(r)
    assert set(DQT_COLUMNS) <= set(COLUMNS)
    f = r.figures
    assert f["dqt_distance_mm"] == pytest.approx(1000 * f["distance_m"], rel=0.01)  # frontal board
    assert 90 < f["dqt_fill_rate_pct"] <= 100
    assert abs(f["dqt_z_accuracy_pct"]) < 0.5
    assert 0.7 < f["dqt_rms_ratio"] < 1.3
    assert np.isfinite(f["dqt_temporal_noise_pct"]) and np.isfinite(f["dqt_roi_plane_fit_rms_mm"])
    assert row["dqt_subpixel_rms_px"] != "" and row["dqt_roi_fill_rate_pct"] != ""
    with pytest.raises(InputError, match="--roi"):
        prepare_checkerboard([out], proto.board, StandpointOptions(roi=1.5))
    # without --roi the ROI columns are empty, the board-mask ones filled
    plain = standpoint_row(evaluate_recording(rec, proto.board, frames=3))
    assert plain["dqt_roi_fill_rate_pct"] == "" and plain["dqt_fill_rate_pct"] != ""
    path = tmp_path / "t.csv"
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerow(row)
    assert next(csv.DictReader(path.open()))["dqt_plane_fit_rms_pct"] == row["dqt_plane_fit_rms_pct"]
