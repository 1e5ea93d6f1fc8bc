"""The guided loop with a light rendered-board camera: the simulated operator reaches every
standpoint, the session is complete, a disconnect mid-standpoint is discarded and re-done."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from depthstation.acquire.guided_capture import GuidedCapture
from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, StreamInfo, project
from depthstation.core.capture.session import Session
from depthstation.core.errors import CameraDisconnected, CameraError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances
from depthstation.simulate.operator import OperatorSettings, SimulatedOperator, Stance

INTR = Intrinsics(640, 360, 320.0, 320.0, 319.5, 179.5)


def render_board(board: Board, cam_to_board: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Flat-shaded board on its plate (colour, RGB) and the plate's exact plane (depth, mm), the
    same optics for both."""
    import cv2

    b2c = np.linalg.inv(cam_to_board)
    r, t = b2c[:3, :3], b2c[:3, 3]
    img = np.full((intr.height, intr.width, 3), 90, np.uint8)
    depth = np.zeros((intr.height, intr.width), np.uint16)
    s = board.square_length_m
    w, h = board.size_m
    m = 0.04
    plate = np.array([[-m, -m, 0], [w + m, -m, 0], [w + m, h + m, 0], [-m, h + m, 0]])
    uv = np.round(project(intr, plate @ r.T + t) * 16).astype(np.int32)
    cv2.fillConvexPoly(img, uv, (255, 255, 255), cv2.LINE_AA, 4)
    mask = np.zeros(depth.shape, np.uint8)
    cv2.fillConvexPoly(mask, uv, 1, cv2.LINE_8, 4)
    for j in range(board.squares_y):
        for i in range(board.squares_x):
            if (i + j) % 2 == 0:
                q = np.array([[i * s, j * s, 0], [(i + 1) * s, j * s, 0],
                              [(i + 1) * s, (j + 1) * s, 0], [i * s, (j + 1) * s, 0]])
                uvq = np.round(project(intr, q @ r.T + t) * 16).astype(np.int32)
                cv2.fillConvexPoly(img, uvq, (0, 0, 0), cv2.LINE_AA, 4)
    # plane depth: z along each ray hitting n.p = n.p0 (camera frame)
    n = r[:, 2]
    p0 = t
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    d = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones_like(u, float)], -1)
    z = (n @ p0) / (d @ n)
    depth[mask > 0] = np.clip(z[mask > 0] * 1000, 0, 65535).astype(np.uint16)
    return depth, img


class RenderedBoardCamera:
    """Flat-shaded board (colour) and its exact plane (depth) at the pose an operator holds;
    depth and colour share the optics. `fail_at` frame numbers raise CameraDisconnected once."""

    def __init__(self, board: Board, fps: float = 30.0, fail_at: tuple[int, ...] = ()) -> None:
        self.board = board
        self.fps = fps
        self.cam_to_board = np.eye(4)
        self.n = 0
        self.fail_at = set(fail_at)
        self.started = False
        self.starts = 0

    def set_pose(self, cam_to_board: np.ndarray) -> None:
        self.cam_to_board = np.asarray(cam_to_board, dtype=np.float64)

    def start(self, streams: Streams) -> StreamInfo:
        self.started = True
        self.starts += 1
        return StreamInfo(INTR, INTR, fps=self.fps, device={"name": "rendered board"})

    def stop(self) -> None:
        self.started = False

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        if not self.started:
            raise CameraError("not started")
        self.n += 1
        if self.n in self.fail_at:
            self.fail_at.discard(self.n)
            self.started = False
            raise CameraDisconnected("simulated unplug")
        depth, img = render_board(self.board, self.cam_to_board, INTR)
        return FrameSet(self.n, int(1.7e18) + int(self.n * 1e9 / self.fps), depth, img, None, {})

    def temperatures(self) -> dict[str, float]:
        return {"asic": 40.0}

    def device_info(self) -> dict[str, str]:
        return {"name": "rendered board"}

    def options(self) -> dict[str, float]:
        return {}


def small_protocol() -> Protocol:
    return Protocol(
        name="test",
        board=Board(),
        streams=Streams(width=640, height=360),
        plan=Plan(frames_per_standpoint=4, start_distance_m=1.0, step_m=0.5, max_distance_m=1.5,
                  inclinations_deg=(0.0, 30.0)),
        tolerances=Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3),
    )


def drive(camera: RenderedBoardCamera, op: SimulatedOperator):  # type: ignore[no-untyped-def]
    def on_guidance(g, fs, t_s):  # type: ignore[no-untyped-def]
        op.step(g, t_s)
        camera.set_pose(op.pose(t_s + 1.0 / camera.fps))
    camera.set_pose(op.pose(0.0))
    return on_guidance


def test_operator_reaches_every_standpoint(tmp_path: Path) -> None:
    proto = small_protocol()
    cam = RenderedBoardCamera(proto.board)
    op = SimulatedOperator(proto.board, Stance(range_m=1.4, azimuth_deg=-8.0, yaw_deg=4.0),
                           OperatorSettings(overshoot=0.3), seed=3)
    session = Session.create(tmp_path / "s", protocol=proto)
    cap = GuidedCapture(cam, proto, session, on_guidance=drive(cam, op), max_guidance_s=60.0)
    outcomes = cap.run()
    assert [o.status for o in outcomes] == ["complete"] * 4
    tol = proto.tolerances
    for o, sp in zip(outcomes, proto.plan.standpoints(), strict=True):
        assert abs(o.measured["distance_m"] - sp.distance_m) <= tol.distance_m
        assert abs(o.measured["inclination_deg"] - sp.inclination_deg) <= tol.inclination_deg
    assert op.moves > 4  # overshoot made the operator correct at least once somewhere
    s = Session.open(tmp_path / "s")
    assert [e["status"] for e in s.standpoints] == ["complete"] * 4
    recs = s.recordings()
    assert [r.frame_count for r in recs] == [4] * 4


def test_disconnect_mid_standpoint_is_discarded_and_redone(tmp_path: Path) -> None:
    proto = small_protocol()
    proto = Protocol(proto.name, board=proto.board, streams=proto.streams,
                     plan=Plan(frames_per_standpoint=6, start_distance_m=1.0, step_m=0.5, max_distance_m=1.0,
                               inclinations_deg=(0.0,)), tolerances=proto.tolerances)
    cam = RenderedBoardCamera(proto.board)
    op = SimulatedOperator(proto.board, Stance(range_m=1.0), seed=1)
    session = Session.create(tmp_path / "s", protocol=proto)
    cap = GuidedCapture(cam, proto, session, on_guidance=drive(cam, op), max_guidance_s=30.0)
    # the board is in place from the first frame: still after ~0.3 s (10 frames), then 3 frames recorded
    cam.fail_at = {14}
    outcomes = cap.run()
    assert [o.status for o in outcomes] == ["complete"]
    assert cam.starts == 2
    s = Session.open(tmp_path / "s")
    statuses = [(e["name"], e["status"]) for e in s.standpoints]
    assert statuses == [("standpoint_01", "discarded"), ("standpoint_01", "complete")]
    assert any(e["event"] == "disconnected" for e in s.data["capture"]["events"])
    assert (tmp_path / "s" / "standpoint_01.discarded-1.mcap").is_file()
    assert s.recordings()[0].frame_count == 6
