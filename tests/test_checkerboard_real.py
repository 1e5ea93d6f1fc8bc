"""The real D435 ChArUco set and the `evaluate checkerboard` command, cross-checked with plain numpy."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthstation.core.camera_model import deproject
from depthstation.core.protocol import load_board


def test_real_charuco_every_standpoint(charuco_dir: Path) -> None:
    from depthstation.core.capture.registry import open_inputs
    from depthstation.evaluate.checkerboard.study import evaluate_recording

    board = load_board(charuco_dir / "board.json")
    recs = open_inputs([charuco_dir])
    assert len(recs) == 9
    for rec in recs:
        r = evaluate_recording(rec, board, frames=150, collect_samples=True)
        assert r.frames_used == r.frames_read == 3 and not r.rejected
        assert any("fewer frames than asked" in n for n in r.notes)
        assert 0.8 < r.figures["distance_m"] < 1.8
        assert r.samples is not None
        s = r.samples
        intr = rec.info.depth_intrinsics
        for fr in r.frames:
            sel = s.frame == fr.index
            pts = deproject(intr, s.u[sel], s.v[sel], s.z_meas_m[sel].astype(np.float64))
            # independent: thin SVD plane fit on the same pixels
            q = pts - pts.mean(axis=0)
            sv = np.linalg.svd(q, full_matrices=False)[1]
            assert fr.noise_m == pytest.approx(sv[-1] / np.sqrt(len(q)), rel=1e-6)
            assert fr.valid_pixels == sel.sum()
            # accuracy: signed distance to the plane of the pose used as reference
            ref = fr.pose_depth if r.reference_plane == "frame" else r.pose_depth
            assert ref is not None
            d = (pts - ref[:3, 3]) @ ref[:3, 2]
            assert fr.accuracy_m == pytest.approx(d.mean(), abs=1e-7)
            assert fr.accuracy_m == pytest.approx(s.error_m[sel].mean(), abs=1e-6)
            # the mask is the board seen through the pose: pixel count ~ projected board area
            assert fr.fill_rate > 0.95
        # real D435 at ~1-1.6 m: noise of millimetres to about a centimetre
        assert 0.001 < r.figures["noise_m"] < 0.03


def test_cli_on_real_set(charuco_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "res"
    exe = Path(sys.executable).with_name("depthstation")
    proc = subprocess.run([str(exe), "evaluate", "checkerboard", str(charuco_dir / "pose03"),
                           str(charuco_dir / "pose10"), "--board", str(charuco_dir / "board.json"),
                           "--out", str(out), "--rrd", str(tmp_path / "s.rrd")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader((out / "standpoints.csv").open()))
    assert [r["standpoint"] for r in rows] == ["pose03", "pose10"]
    for col in ("frames", "distance_m", "inclination_deg", "reference_distance_std_m", "fill_rate",
                "noise_m", "noise_std_m", "accuracy_m", "accuracy_std_m", "accuracy_rms_m",
                "noise_black_m", "noise_white_m", "accuracy_black_m", "accuracy_white_m"):
        assert rows[0][col] != ""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["board"]["type"] == "charuco"
    info = json.loads((out / "result.json").read_text())
    assert info["kind"] == "checkerboard"
    # 3 frames each and no --frames: nothing was asked that they fall short of
    assert not [w for w in info["warnings"] if w["code"] == "fewer-frames"], info["warnings"]
    for name in ("fig1_poses.png", "fig4_reference_distance_std.png", "fig5_pixels.png",
                 "fig6_noise.png", "fig7_accuracy.png"):
        assert (out / name).stat().st_size > 10_000
    assert (tmp_path / "s.rrd").stat().st_size > 0


def test_cli_wrong_board_is_input_error(charuco_dir: Path, tmp_path: Path) -> None:
    """A plain-checkerboard description for the ChArUco images: one line, no traceback."""
    bad = tmp_path / "board.json"
    bad.write_text(json.dumps({"type": "charuco", "squares_x": 7, "squares_y": 5,
                               "square_length_m": 0.075, "marker_length_m": 0.05625,
                               "dictionary": "DICT_4X4_50", "first_square_black": False}))
    exe = Path(sys.executable).with_name("depthstation")
    proc = subprocess.run([str(exe), "evaluate", "checkerboard", str(charuco_dir / "pose04"),
                           "--board", str(bad), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "first_square_black = true" in proc.stderr and "Traceback" not in proc.stderr
