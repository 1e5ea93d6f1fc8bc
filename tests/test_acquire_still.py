"""A standpoint is recorded from a still camera: a take during which the camera moved is set aside
and recorded again; and the demo's standpoint_01 (recorded while the operator was still stepping
back, after warm-up and calibration) is still."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_acquire_loop import RenderedBoardCamera, drive

from depthstation.acquire.board_detection import board_pose
from depthstation.acquire.guidance import points_agree
from depthstation.acquire.guided_capture import MOVED_MESSAGE, GuidedCapture, LiveState
from depthstation.core.board import Board
from depthstation.core.board_pose import pose_metrics
from depthstation.core.capture.session import Session
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import PROTOCOL_DIR, Plan, Protocol, Streams, Tolerances
from depthstation.simulate.operator import SimulatedOperator, Stance


class TrackedCamera(RenderedBoardCamera):
    """The rendered board that remembers the true camera pose of every frame it delivered."""

    def __init__(self, board: Board) -> None:
        super().__init__(board)
        self.truth: dict[int, np.ndarray] = {}

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        fs = super().wait_for_frames(timeout_s)
        self.truth[fs.index] = self.cam_to_board.copy()
        return fs


def true_distance(board: Board, cam_to_board: np.ndarray) -> float:
    b2c = np.linalg.inv(cam_to_board)
    return pose_metrics(board, b2c[:3, :3], b2c[:3, 3])[0]


def true_points(board: Board, cam_to_board: np.ndarray) -> np.ndarray:
    """The board centre and outer corners in the camera frame, as the stillness checks see them."""
    b2c = np.linalg.inv(cam_to_board)
    w, h = board.size_m
    pts = np.array([board.center, [0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=float)
    return np.asarray(pts @ b2c[:3, :3].T + b2c[:3, 3])


def reference_distances(rec: Any, board: Board) -> list[float]:
    """The board distance of every recorded frame from its own EPnP pose (frames.csv's reference)."""
    out = []
    for fs in rec.frames():
        pose = board_pose(fs.color, board, rec.info)
        assert pose is not None, f"{rec.name}: board not found in frame {fs.index}"
        out.append(pose.distance_m)
    return out


# on the 3rd frame of the first take the operator moves, unprompted, over half a second: 3 cm closer
# turning 1 degree (inside the target's 5 cm, outside the 1 cm of stillness), or 3.4 degrees round the
# board still facing it (the demo's standpoint_04 before the corners were checked: the board centre
# stays put, the corners move 2 cm)
LAPSES = {"step": {"range_m": -0.03, "yaw_deg": 1.0}, "walk_round": {"azimuth_deg": 3.4}}


@pytest.mark.parametrize("lapse", sorted(LAPSES))
def test_a_take_with_a_moving_camera_is_discarded_and_recorded_again(tmp_path: Path, lapse: str) -> None:
    board = Board()
    tol = Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3)
    proto = Protocol("still", board=board, streams=Streams(width=640, height=360),
                     plan=Plan(frames_per_standpoint=10, start_distance_m=1.0, step_m=0.5, max_distance_m=1.0,
                               inclinations_deg=(0.0,)), tolerances=tol)
    cam = TrackedCamera(board)
    op = SimulatedOperator(board, Stance(range_m=1.0), seed=4)
    messages: list[str] = []
    lapsed: list[float] = []

    def on_state(state: LiveState) -> None:
        messages.append(state.message)
        if state.phase == "recording" and state.recorded == 3 and not lapsed:
            t = (state.frame.timestamp_ns - int(1.7e18)) / 1e9 if state.frame else 0.0
            op.lapse(t, duration_s=0.5, **LAPSES[lapse])
            lapsed.append(t)

    session = Session.create(tmp_path / "s", protocol=proto)
    cap = GuidedCapture(cam, proto, session, on_guidance=drive(cam, op), on_state=on_state,
                        max_guidance_s=30.0)
    outcomes = cap.run()
    assert [o.status for o in outcomes] == ["complete"]
    assert lapsed and cap.retakes == 1
    s = Session.open(tmp_path / "s")
    assert [(e["name"], e["status"]) for e in s.standpoints] == [("standpoint_01", "discarded"),
                                                                 ("standpoint_01", "complete")]
    assert "camera moved" in s.standpoints[0]["reason"]
    events = [e for e in s.data["capture"]["events"] if e["event"] == "camera_moved"]
    assert len(events) == 1 and 3 < events[0]["frames_recorded"] < 10
    assert MOVED_MESSAGE in messages
    assert any(m.startswith(MOVED_MESSAGE + "; ") for m in messages)  # stays in front of the guidance
    # the moved take is kept aside, never deleted, and it did move
    aside = tmp_path / "s" / "standpoint_01.discarded-1.mcap"
    assert aside.is_file()
    from depthstation.core.capture.registry import open_recording

    first = [true_points(board, cam.truth[fs.index]) for fs in open_recording(aside).frames()]
    # it did move (not a false alarm of pose noise: a still camera's truth does not move at all); the
    # check stopped it as the pose estimate crossed the tolerance, so by truth about that far
    moved = max(float(np.linalg.norm(a - b, axis=1).max()) for a in first for b in first)
    assert moved > 0.5 * tol.still_translation_m, moved
    # the final take: every frame from the same place, by truth and by the board's own pose
    rec = s.recordings()[0]
    assert rec.frame_count == 10
    d_true = [true_distance(board, cam.truth[fs.index]) for fs in rec.frames()]
    assert max(d_true) - min(d_true) < tol.still_translation_m
    final = [true_points(board, cam.truth[fs.index]) for fs in rec.frames()]
    assert all(points_agree(final[0], c, tol.still_translation_m, tol.still_rotation_deg) for c in final)
    d_ref = reference_distances(rec, board)
    assert max(d_ref) - min(d_ref) < tol.still_translation_m
    assert abs(float(np.mean(d_true)) - 1.0) <= tol.distance_m


def test_demo_standpoint_01_is_still_after_warmup_and_calibration(tmp_path: Path) -> None:
    """Regression: the demo's guided session (seed 1, warm-up on the accelerated clock, on-chip and
    tare calibration) recorded standpoint_01 while the operator was still stepping back from 0.95 to
    1.02 m: the stillness window accepted the first frame of the step. Its frames must be still
    now, without a retake (the stillness check, not the safeguard, keeps it still)."""
    from depthstation.acquire.station import Station, do_calibrate, do_capture, do_warmup
    from depthstation.core.rerun_bridge import RerunTarget

    text = (PROTOCOL_DIR / "demo-d455.toml").read_text()
    # only standpoint_01 of the demo plan, and a warm-up of 2 to 3 simulated minutes (the clock jump
    # back to frame time is what matters, not its length)
    text = (text.replace("max_distance_m = 2.6", "max_distance_m = 1.0")
            .replace("inclinations_deg = [0.0, 35.0]", "inclinations_deg = [0.0]")
            .replace("min_minutes = 10.0", "min_minutes = 2.0").replace("window_minutes = 2.0",
                                                                        "window_minutes = 1.0")
            .replace("max_minutes = 40.0", "max_minutes = 3.0"))
    proto_path = tmp_path / "demo-one.toml"
    proto_path.write_text(text)
    st = Station("sim:d455", str(proto_path), tmp_path / "s", False, 1, False)
    off = RerunTarget(None, False, False)
    warm = do_warmup(st, 15.0, 300.0, off)
    assert warm["accelerated"] and warm["elapsed_s"] >= 120.0
    t_warm = st.camera.device_time_s()
    cal = do_calibrate(st, True, write=False)
    assert not cal["skipped"] and cal["changed"]
    outcomes = do_capture(st, off, 60.0)
    assert [o.status for o in outcomes] == ["complete"]
    s = Session.open(tmp_path / "s")
    assert [(e["name"], e["status"]) for e in s.standpoints] == [("standpoint_01", "complete")]
    assert not [e for e in s.data.get("capture", {}).get("events", []) if e["event"] == "camera_moved"]
    rec = s.recordings()[0]
    # device time went on from the warm-up by frames alone (no jump when the clock was handed back)
    t_dev = np.array([float(fs.metadata["device_time_s"]) for fs in rec.frames()])
    assert t_dev[0] > t_warm
    assert np.allclose(np.diff(t_dev), 1.0 / 30.0, atol=1e-6)
    board = st.protocol.board
    tol = st.protocol.tolerances
    d_ref = reference_distances(rec, board)
    assert len(d_ref) == 10
    assert max(d_ref) - min(d_ref) < tol.still_translation_m, np.round(d_ref, 4)
    truth = rec.metadata["truth"]
    assert abs(truth["distance_m"] - 1.0) <= tol.distance_m
    assert abs(float(np.mean(d_ref)) - truth["distance_m"]) < 0.01
