"""The acquire commands against a recording (playback replaces the device) and their error contract."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_acquire_loop import INTR, RenderedBoardCamera

from depthstation.acquire.camera_select import parse_camera
from depthstation.core.board import Board
from depthstation.core.camera_model import StreamInfo
from depthstation.core.errors import InputError
from depthstation.core.protocol import Streams
from depthstation.simulate.operator import Stance

ROOT = Path(__file__).resolve().parents[1]
EXE = str(ROOT / ".venv" / "bin" / "depthstation")

SMALL_TOML = """
name = "small"
[board]
type = "checkerboard"
squares_x = 7
squares_y = 5
square_length_m = 0.095
[streams]
width = 640
height = 360
fps = 30
[plan]
frames_per_standpoint = {frames}
start_distance_m = 1.0
step_m = 0.5
max_distance_m = 1.5
inclinations_deg = [0.0]
[tolerances]
distance_m = 0.05
inclination_deg = 3.0
still_seconds = 0.3
[warmup]
min_minutes = 1.0
max_slope_c_per_min = 0.1
window_minutes = 0.5
max_minutes = 5.0
[calibration]
on_chip = true
"""


def write_protocol(tmp: Path, frames: int = 5) -> Path:
    p = tmp / "small.toml"
    p.write_text(SMALL_TOML.replace("{frames}", str(frames)))
    return p


def make_recording(path: Path, n: int = 30) -> Path:
    """A .db3 of a board held at 1.0 m facing the camera, through librealsense's recorder."""
    from depthstation.core.capture.rs_writer import write_realsense_recording

    cam = RenderedBoardCamera(Board())
    cam.set_pose(Stance(range_m=1.0).camera_to_board(Board()))
    cam.start(Streams())
    # the board holds still and the render is noiseless, so every frame is the first one again, with
    # its own number and time: rendered once (13 ms of CPU a frame; the 600-frame recording of
    # test_acquire_faults spent 8 s rendering the same image)
    first = cam.wait_for_frames()
    frames = [replace(first, index=first.index + k, timestamp_ns=first.timestamp_ns + int(k * 1e9 / cam.fps))
              for k in range(n)]
    info = StreamInfo(INTR, INTR, fps=30.0, device={"name": "Intel RealSense D455 (rendered)"})
    write_realsense_recording(path, info, frames)
    return path


def test_parse_camera(tmp_path: Path) -> None:
    assert parse_camera("live").kind == "live"
    assert parse_camera("live:123").serial == "123"
    assert parse_camera("sim").model == "d455"
    assert parse_camera("sim:d435").model == "d435"
    f = tmp_path / "x.db3"
    f.write_bytes(b"")
    assert parse_camera(str(f)).kind == "file"
    with pytest.raises(InputError, match="recording not found"):
        parse_camera(str(tmp_path / "missing.db3"))
    with pytest.raises(InputError, match="--camera"):
        parse_camera("webcam")


def test_capture_from_a_recording(tmp_path: Path) -> None:
    rec = make_recording(tmp_path / "board.db3")
    proto = write_protocol(tmp_path)
    sess = tmp_path / "session"
    r = subprocess.run([EXE, "acquire", "capture", "--camera", str(rec), "--protocol", str(proto),
                        "--session", str(sess)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    err = " ".join(r.stderr.split())  # rich wraps long lines
    assert "recording ended" in err and "1 standpoints complete" in err and "open: standpoint_02" in err
    data = json.loads((sess / "session.json").read_text())
    entries = {e["name"]: e for e in data["standpoints"]}
    assert entries["standpoint_01"]["status"] == "complete" and entries["standpoint_01"]["frames"] == 5
    from depthstation.core.capture.registry import open_recording

    r1 = open_recording(sess / "standpoint_01.mcap")
    meas = r1.metadata["standpoint"]["measured"]
    assert meas["distance_m"] == pytest.approx(1.0, abs=0.02)
    assert meas["inclination_deg"] == pytest.approx(0.0, abs=2.0)
    idx = [f.index for f in r1.frames()]
    assert np.all(np.diff(idx) == 1)  # contiguous frame numbers
    # a second run without --resume refuses (exit code 2, one line)
    r = subprocess.run([EXE, "acquire", "capture", "--camera", str(rec), "--protocol", str(proto),
                        "--session", str(sess)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--resume" in r.stderr and "Traceback" not in r.stderr
    # calibration and warm-up on a recording: said and recorded, nothing applied
    r = subprocess.run([EXE, "acquire", "calibrate", "--camera", str(rec), "--protocol", str(proto),
                        "--session", str(sess), "--resume", "--yes"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    data = json.loads((sess / "session.json").read_text())
    assert data["calibration"]["skipped"]


def test_bad_camera_is_exit_2(tmp_path: Path) -> None:
    r = subprocess.run([EXE, "acquire", "capture", "--camera", str(tmp_path / "nope.db3"), "--session",
                        str(tmp_path / "s")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "recording not found" in r.stderr
