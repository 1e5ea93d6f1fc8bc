"""The guided capture loop: guide the operator to each standpoint, record it when in place and still.

One standpoint = one MCAP in the session (written by the capture helper's
`Session.standpoint_writer`, `.partial` until closed). Faults lose nothing: a device that drops
off mid-standpoint is reported, its partial file discarded, the camera reopened and the standpoint
re-done; a stream that stalls while the device stays connected is recovered by a hardware reset
(where the camera has one) and the standpoint re-done; Ctrl-C closes the open file properly and
leaves the standpoint incomplete for `--resume`; a killed process leaves every finished standpoint
readable. A take never records the same frame twice, and its metadata says how many frames the
device lost (gaps in the frame numbers) and how many framesets were skipped as repeats.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from depthstation.acquire.board_detection import BoardPose, board_mask, board_pose, fill_rate
from depthstation.acquire.guidance import Guidance, StillnessTracker, end_of_range, guide, points_agree
from depthstation.acquire.recovery import reconnect
from depthstation.core.board_pose import pose_metrics
from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.session import StandpointWriter, _sigint_deferred
from depthstation.core.device import CameraStalled
from depthstation.core.errors import CameraDisconnected, CameraError, CaptureError
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import average_poses
from depthstation.core.protocol import Protocol, Standpoint
from depthstation.core.run_warnings import warn

BOARD_SCALE_TOLERANCE = 0.05  # the evaluation's board-scale check: a camera's own depth scale is within ~2 %
MIN_SCALE_PIXELS = 50  # board depth pixels a frame needs for the scale check


class CameraMoved(CaptureError):
    """The board pose on the recorded frames left the stillness tolerances: the take is discarded."""


MOVED_MESSAGE = "camera moved during recording: hold still; recording again"
NOTICE_SECONDS = 3.0  # a fault notice stays in front of the guidance this long (frame time)


class CaptureInterrupted(CaptureError):
    """Ctrl-C: the open standpoint was closed as a finished '.partial' MCAP; exit code 130 (SIGINT)."""

    exit_code = 130


MAX_FAULTS_PER_STANDPOINT = 5  # disconnects / stalls of one standpoint before the capture gives up
END_OF_RANGE_FRAMES = 10  # consecutive frames with a collapsed fill rate before we call it
MAX_POSE_STRIDE = 5  # during recording the board pose is measured on every 5th frame at most


def pose_stride(frames: int) -> int:
    """Measure the pose on every frame of a short standpoint, on every 5th of a long one (at least
    10 poses go into the average)."""
    return max(1, min(MAX_POSE_STRIDE, frames // 10))


@dataclass
class LiveState:
    """What the panel and rerun show for the latest frame."""

    standpoint: Standpoint
    index: int  # position of the standpoint in the plan
    total: int
    phase: str  # 'guiding', 'recording', 'reconnecting', 'done'
    frame: FrameSet | None = None
    pose: BoardPose | None = None
    guidance: Guidance | None = None
    recorded: int = 0
    frames_per_standpoint: int = 0
    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    message: str = ""


@dataclass
class FrameAccounting:
    """What the frame numbers of one take say. A live camera reports, per frameset, the frames its
    firmware counter skipped and the framesets it dropped as repeats since the previous one; other
    cameras are judged by the gaps in `FrameSet.index`. The first frame's history (before the take)
    does not count. `admit` refuses a frameset that repeats the last one: it is never written."""

    counter: str = "index"  # 'device' (firmware frame counter), 'host' (no gaps visible) or 'index'
    lost: dict[str, int] = field(default_factory=lambda: {"depth": 0, "color": 0})
    # frames that reached the host and were replaced before the capture took them (a slow
    # consumer); None where the camera cannot tell them from the device's losses
    host_dropped: dict[str, int] | None = None
    skipped: dict[str, int] = field(default_factory=lambda: {"repeated": 0, "stale_color": 0})
    duplicates: int = 0
    last_index: int | None = None

    def admit(self, fs: FrameSet) -> bool:
        first = self.last_index is None
        if not first and fs.index == self.last_index:
            self.duplicates += 1
            return False
        meta = fs.metadata or {}
        if "frame_counter" in meta:
            self.counter = str(meta["frame_counter"])
            if not first:
                for k, v in (meta.get("frames_lost_before") or {}).items():
                    self.lost[k] = self.lost.get(k, 0) + int(v)
                for k, v in (meta.get("framesets_skipped_before") or {}).items():
                    self.skipped[k] = self.skipped.get(k, 0) + int(v)
                dropped = meta.get("host_frames_dropped_before")
                if dropped is not None:
                    self.host_dropped = self.host_dropped or {"depth": 0, "color": 0}
                    for k, v in dropped.items():
                        self.host_dropped[k] = self.host_dropped.get(k, 0) + int(v)
        elif not first and self.last_index is not None and fs.index > self.last_index + 1:
            self.lost["depth"] += fs.index - self.last_index - 1
        self.last_index = fs.index
        return True

    def summary(self) -> dict[str, Any]:
        """The take's `frames` record: device-side losses per stream (None where the frame numbers
        come from a host counter and cannot show them), framesets skipped as repeats."""
        return {"frame_counter": self.counter,
                "device_frames_lost": None if self.counter == "host" else dict(self.lost),
                "host_frames_dropped": None if self.host_dropped is None else dict(self.host_dropped),
                "framesets_skipped": {**self.skipped, "duplicate_index": self.duplicates}}


@dataclass
class StandpointOutcome:
    name: str
    status: str  # 'complete' or 'end_of_range'
    measured: dict[str, Any] = field(default_factory=dict)
    frames: int = 0


class GuidedCapture:
    """Runs the plan of a protocol against a camera, writing into a session.

    `on_guidance(guidance, frameset, t_s)` lets a simulated operator act on what the screen says;
    `on_state(LiveState)` feeds the terminal panel and rerun.
    """

    def __init__(self, camera: Any, protocol: Protocol, session: Any, *,
                 on_guidance: Callable[[Guidance, FrameSet, float], None] | None = None,
                 on_state: Callable[[LiveState], None] | None = None,
                 max_guidance_s: float | None = None, reconnect_timeout_s: float = 60.0,
                 frame_timeout_s: float = 5.0, sleep: Callable[[float], None] = time.sleep) -> None:
        self.camera = camera
        self.protocol = protocol
        self.session = session
        self.on_guidance = on_guidance
        self.on_state = on_state
        self.max_guidance_s = max_guidance_s
        self.reconnect_timeout_s = reconnect_timeout_s
        self.frame_timeout_s = frame_timeout_s
        self.sleep = sleep
        self.info: StreamInfo | None = None
        self.events: list[dict[str, Any]] = []
        self.skipped: dict[str, str] = {}
        self.dropped = 0
        self.scale_said = False  # board-scale is one cause for every standpoint: said once per run
        self.retakes = 0  # takes discarded because the camera moved while recording
        self.faults: dict[str, int] = {}  # disconnects and stalls per standpoint
        self.finished: list[StandpointOutcome] = []  # this run's outcomes so far (kept when cut short)
        self._t0_ns: int | None = None
        self._last_temp_ns = 0
        self._writer: StandpointWriter | None = None  # the open standpoint's, from its file's creation

    # -- camera ------------------------------------------------------------------------------
    def _start(self) -> StreamInfo:
        self.info = self.camera.start(self.protocol.streams)
        return self.info

    def _camera_events(self, standpoint: str | None) -> None:
        """The device's own events (reset, re-enumeration, calibration re-applied) into the log."""
        take = getattr(self.camera, "take_events", None)
        if callable(take):
            self.events.extend({**e, "standpoint": standpoint} for e in take())

    def _reconnect(self, state: LiveState, cause: CameraError | None = None) -> None:
        """Stop; after a stall, reset the device where it can; then retry starting the camera until
        it answers or the timeout passes (`recovery.reconnect`; a camera back in an unsuitable
        state, e.g. on USB 2, is said on screen and waited for)."""
        state.phase = "reconnecting"

        def say(text: str) -> None:
            state.message = text
            self._emit(state)

        def start() -> StreamInfo:
            self._camera_events(state.standpoint.name)
            return self._start()

        reconnect(self.camera, start, cause, timeout_s=self.reconnect_timeout_s, sleep=self.sleep, say=say)
        self._camera_events(state.standpoint.name)
        self.events.append({"event": "reconnected", "standpoint": state.standpoint.name,
                            "time_ns": time.time_ns()})
        self._save_log()

    def _frame(self) -> FrameSet:
        fs: FrameSet = self.camera.wait_for_frames(self.frame_timeout_s)
        if self._t0_ns is None:
            self._t0_ns = fs.timestamp_ns
        return fs

    def _t_s(self, fs: FrameSet) -> float:
        return (fs.timestamp_ns - (self._t0_ns or fs.timestamp_ns)) / 1e9

    def _emit(self, state: LiveState) -> None:
        if self.on_state is not None:
            self.on_state(state)

    # -- measuring ---------------------------------------------------------------------------
    def _depth_intrinsics(self) -> Any:
        """The intrinsics of the depth image's pixels (the colour camera's when depth is aligned)."""
        assert self.info is not None
        return self.info.color_intrinsics if self.info.depth_aligned_to_color else self.info.depth_intrinsics

    def _measure(self, fs: FrameSet) -> tuple[BoardPose | None, float | None, Any]:
        """The board pose, its depth fill rate and its depth pixels (mask), each None when unknown."""
        if fs.color is None:
            return None, None, None
        assert self.info is not None
        pose = board_pose(fs.color, self.protocol.board, self.info)
        if pose is None or fs.depth is None:
            return pose, None, None
        intr = self._depth_intrinsics()
        assert intr is not None
        mask = board_mask(pose, self.protocol.board, intr, margin_m=0.5 * self.protocol.board.square_length_m)
        return pose, fill_rate(fs.depth, mask), mask

    def _guidance(self, sp: Standpoint, pose: BoardPose | None, fill: float | None, still: bool) -> Guidance:
        intr = self._depth_intrinsics()
        tol = self.protocol.tolerances
        if pose is None or intr is None:
            return guide(sp, tol, distance_m=None, inclination_deg=None, azimuth_deg=None, fill=fill)
        return guide(sp, tol, distance_m=pose.distance_m, inclination_deg=pose.inclination_deg,
                     azimuth_deg=pose.azimuth_deg, center_px=pose.center_px,
                     image_size=(intr.width, intr.height), fx=intr.fx, still=still, fill=fill)

    # -- the plan ----------------------------------------------------------------------------
    def run(self, done: set[str] | None = None, skipped: set[str] | None = None) -> list[StandpointOutcome]:
        """Capture every standpoint not yet `done` (or `skipped` at the end of a range), in order."""
        prior = self.session.data.get("capture") or {}
        self.skipped.update(prior.get("skipped") or {})
        self.events = list(prior.get("events") or []) + self.events
        done = set(done or ()) | {e["name"] for e in self.session.standpoints
                                  if e.get("status") == "complete"}
        skipped = set(skipped or ()) | set(self.skipped)
        plan = self.protocol.plan.standpoints()
        outcomes: list[StandpointOutcome] = []
        self._start()
        self._camera_events(None)
        try:
            ended_trajectories: set[int] = set()
            for i, sp in enumerate(plan):
                if sp.name in done or sp.name in skipped:
                    if sp.name in skipped:
                        ended_trajectories.add(sp.trajectory)
                    continue
                if sp.trajectory in ended_trajectories:
                    outcomes.append(StandpointOutcome(sp.name, "end_of_range"))
                    skipped.add(sp.name)
                    self._mark_skipped(sp)
                    continue
                state = LiveState(sp, i, len(plan), "guiding",
                                  frames_per_standpoint=self.protocol.plan.frames_per_standpoint,
                                  done=sorted(done), skipped=sorted(skipped))
                out = self._standpoint(sp, state)
                outcomes.append(out)
                self.finished.append(out)
                if out.status == "complete":
                    done.add(sp.name)
                else:
                    skipped.add(sp.name)
                    ended_trajectories.add(sp.trajectory)
                    self._mark_skipped(sp)
        finally:
            self._close_open_writer()
            with contextlib.suppress(CameraError):
                self.camera.stop()
        return outcomes

    def _close_open_writer(self) -> None:
        """A standpoint file left open by a Ctrl-C that came after the file was created but before
        its `with` block took charge of it: finished as 'partial' (a no-op once the block closed it).
        A failing close is recorded in its session entry and must not hide the Ctrl-C."""
        writer, self._writer = self._writer, None
        if writer is not None:
            with contextlib.suppress(CaptureError):
                writer.close(ok=False)

    def _mark_skipped(self, sp: Standpoint) -> None:
        self.skipped[sp.name] = "end of range: the board's depth fill rate collapsed"
        self.events.append({"event": "end_of_range", "standpoint": sp.name, "trajectory": sp.trajectory,
                            "time_ns": time.time_ns()})
        self._save_log()

    def _save_log(self) -> None:
        """The capture's own record in session.json: skipped standpoints and fault events."""
        self.session.set("capture", {"skipped": dict(self.skipped), "events": list(self.events)})

    def _standpoint(self, sp: Standpoint, state: LiveState) -> StandpointOutcome:
        """Guide, then record; a disconnect during either restarts the standpoint after reconnect,
        a camera that moved while recording has its take set aside and recorded again."""
        notice = ""
        while True:
            try:
                if self._guide_until_ready(sp, state, notice) == "end_of_range":
                    return StandpointOutcome(sp.name, "end_of_range")
                return self._record(sp, state)
            except CameraMoved as exc:
                # the writer closed the take as 'partial'; keep it aside (never deleted) and redo it
                self.retakes += 1
                self.session.discard(sp.name, str(exc))
                self.events.append({"event": "camera_moved", "standpoint": sp.name,
                                    "frames_recorded": state.recorded, "error": str(exc),
                                    "time_ns": time.time_ns()})
                self._save_log()
                state.recorded = 0
                state.phase = "guiding"
                state.message = notice = MOVED_MESSAGE
                self._emit(state)
            except CameraDisconnected as exc:
                what = "stalled" if isinstance(exc, CameraStalled) else "disconnected"
                self.faults[sp.name] = self.faults.get(sp.name, 0) + 1
                self._camera_events(sp.name)
                self.events.append({"event": what, "standpoint": sp.name, "during": state.phase,
                                    "frames_recorded": state.recorded, "error": str(exc),
                                    "time_ns": time.time_ns()})
                if state.phase == "recording":
                    # the writer closed the file as 'partial'; move it aside (never deleted)
                    self.session.discard(sp.name, f"camera {what} after {state.recorded} frames")
                self._save_log()
                state.recorded = 0
                if self.faults[sp.name] > MAX_FAULTS_PER_STANDPOINT:
                    msg = (f"{sp.name}: the camera {what} {self.faults[sp.name]} times: check its cable and "
                           "USB 3 port, then --resume")
                    raise CameraError(msg) from exc
                self._reconnect(state, exc)
                state.phase = "guiding"

    def _guide_until_ready(self, sp: Standpoint, state: LiveState, notice: str = "") -> str:
        """Guide until in tolerance and still ('ready') or the end of the range; `notice` (why the
        standpoint starts again) stays in front of the guidance for NOTICE_SECONDS."""
        tol = self.protocol.tolerances
        still = StillnessTracker.from_tolerances(tol)
        fills: list[float] = []
        state.phase = "guiding"
        t_start: float | None = None
        while True:
            fs = self._frame()
            t = self._t_s(fs)
            t_start = t if t_start is None else t_start
            pose, fill, _ = self._measure(fs)
            is_still = still.update(fs.timestamp_ns,
                                    None if pose is None else pose.stillness_points(self.protocol.board))
            g = self._guidance(sp, pose, fill, is_still)
            # end of range: the board is seen within half a step of the target, and depth is gone
            # (farther than that, as when a new trajectory starts from the last one's end, the
            # operator is told to step closer and the fill rate there says nothing of the target)
            if pose is not None and fill is not None:
                if abs(pose.distance_m - sp.distance_m) <= 0.5 * self.protocol.plan.step_m:
                    fills.append(fill)
                else:
                    fills.clear()
            if end_of_range(fills, tol.end_fill_rate, END_OF_RANGE_FRAMES):
                state.message = (f"end of range at {sp.distance_m:.2f} m: the board's depth fill rate "
                                 f"fell below {tol.end_fill_rate:.0%}; next trajectory")
                self._emit(state)
                return "end_of_range"
            state.frame, state.pose, state.guidance, state.message = fs, pose, g, g.text
            if notice and t - t_start < NOTICE_SECONDS:
                state.message = f"{notice}; {g.text}"
            self._emit(state)
            if g.in_tolerance and is_still:
                return "ready"
            if self.on_guidance is not None:
                self.on_guidance(g, fs, t)
            if self.max_guidance_s is not None and t - t_start > self.max_guidance_s:
                raise CaptureError(f"{sp.name}: not reached within {self.max_guidance_s:g} s of guidance")

    def _record(self, sp: Standpoint, state: LiveState) -> StandpointOutcome:
        assert self.info is not None
        n = self.protocol.plan.frames_per_standpoint
        g = state.guidance
        target = {"distance_m": sp.distance_m, "inclination_deg": sp.inclination_deg, "side": sp.side}
        meta: dict[str, Any] = {
            "name": sp.name, "trajectory": sp.trajectory, "target": target,
            "measured_at_start": None if g is None else {
                "distance_m": g.distance_m, "inclination_deg": g.inclination_deg,
                "azimuth_deg": g.azimuth_deg},
        }
        state.phase = "recording"
        state.recorded = 0
        stride = pose_stride(n)
        poses: list[np.ndarray] = []
        centres: list[np.ndarray] = []
        scales: list[float] = []
        frames = FrameAccounting()
        # the file exists from inside standpoint_writer on: a Ctrl-C is held until the writer is
        # kept in self._writer, so run() finishes the file wherever the Ctrl-C then lands (Python
        # can raise it between a call's return and the `with` taking charge of what it returned)
        with _sigint_deferred():
            self._writer = self.session.standpoint_writer(sp.name, self.info, meta)
        with self._writer as writer:
            while state.recorded < n:
                fs = self._frame()
                if not frames.admit(fs):
                    continue  # the same frame again: never recorded twice
                if writer.write(fs) is False:
                    state.message = f"writer queue full: frame {fs.index} dropped"
                state.recorded += 1
                if fs.timestamp_ns - self._last_temp_ns >= 1_000_000_000:
                    temps = self.camera.temperatures()
                    if temps:
                        writer.write_temperature(fs.timestamp_ns, temps)
                    self._last_temp_ns = fs.timestamp_ns
                # the pose on every `stride`-th frame is plenty for the average (30 of 150) and keeps
                # 30 fps at 1280x720: detection costs about a frame period there
                sampled = (state.recorded - 1) % stride == 0
                pose, _, mask = self._measure(fs) if sampled else (None, None, None)
                if pose is not None:
                    m = np.eye(4)
                    m[:3, :3], m[:3, 3] = pose.R, pose.t
                    poses.append(m)
                    centres.append(pose.stillness_points(self.protocol.board))
                    if mask is not None and (r := self._depth_over_pose(fs, pose, mask)) is not None:
                        scales.append(r)
                    moved = self._moved(centres)
                    if moved is not None:
                        raise CameraMoved(f"{sp.name}: {moved} after {state.recorded} frames")
                state.frame = fs
                state.pose = pose or state.pose
                state.message = f"recording {sp.name}: {state.recorded}/{n} frames, hold still"
                self._emit(state)
                if self.on_guidance is not None and state.guidance is not None:
                    self.on_guidance(state.guidance, fs, self._t_s(fs))
            measured = self._measured(poses, n)
            if scales:
                measured["depth_over_pose"] = self._say_scale(sp, float(np.median(scales)))
            meta["measured"] = measured
            meta["frames"] = frames.summary()
            writer.set_metadata("standpoint", meta)
            truth = getattr(self.camera, "truth", None)
            if callable(truth):  # a simulated camera knows where it was: the evaluation's reference
                writer.set_metadata("truth", truth())
            self.dropped += int(getattr(writer, "dropped", 0))
        self._writer = None
        state.done.append(sp.name)
        state.phase = "done"
        self._emit(state)
        return StandpointOutcome(sp.name, "complete", measured, n)

    def _moved(self, centres: list[np.ndarray]) -> str | None:
        """Why the take is not still (the newest sampled view of the board left the stillness
        tolerances against any earlier one of this take), or None. Judged as the stillness before
        recording is (centre and outer corners in the camera frame): the take's spread stays within
        the tolerances."""
        tol = self.protocol.tolerances
        c = centres[-1]
        for i, c_i in enumerate(centres[:-1]):
            if not points_agree(c_i, c, tol.still_translation_m, tol.still_rotation_deg):
                shift = float(np.linalg.norm(c - c_i, axis=1).max())
                cos = float(np.dot(c[0], c_i[0]) / (np.linalg.norm(c[0]) * np.linalg.norm(c_i[0])))
                turn = float(np.degrees(np.arccos(min(1.0, max(-1.0, cos)))))
                return (f"camera moved {100 * shift:.1f} cm / {turn:.2f}° between sampled frames {i + 1} "
                        f"and {len(centres)} (tolerance {100 * tol.still_translation_m:.1f} cm / "
                        f"{tol.still_rotation_deg:g}°)")
        return None

    def _depth_over_pose(self, fs: FrameSet, pose: BoardPose, mask: Any) -> float | None:
        """The board's median depth (over `mask`, its depth pixels from `_measure`) over the z its
        pose gives at its centre (about 1 when the protocol's board is the print; the pose scales
        with square_length_m, depth does not)."""
        assert self.info is not None
        if fs.depth is None:
            return None
        board = self.protocol.board
        d = fs.depth[mask]
        d = d[d > 0]
        w, h = board.size_m
        z_pose = float((pose.R @ np.array([w / 2, h / 2, 0.0]) + pose.t)[2])
        if d.size < MIN_SCALE_PIXELS or z_pose <= 0:
            return None
        return float(np.median(d)) * self.info.depth_units_m / z_pose

    def _say_scale(self, sp: Standpoint, ratio: float) -> float:
        """Warn now, not at the evaluation days later, when depth and pose disagree on the scale: a
        board of another size than the protocol's records every standpoint at the wrong distance."""
        if abs(ratio - 1.0) > BOARD_SCALE_TOLERANCE and not self.scale_said:
            self.scale_said = True
            board = self.protocol.board
            warn(f"{sp.name}: the board's depth reads {ratio:.2f}x the distance its pose gives: the "
                 f"protocol's square_length_m {board.square_length_m:g} m implies "
                 f"{board.square_length_m * ratio:.4f} m for this print (is the protocol's board the one "
                 "held up?); the standpoints are recorded at the pose's distance (each one's ratio: "
                 "measured.depth_over_pose)",
                 str(self.session.dir), "board-scale")
        return ratio

    def _measured(self, poses: list[np.ndarray], n: int) -> dict[str, Any]:
        """The averaged board pose of the recorded frames (as the paper averages 150 EPnP poses)."""

        if not poses:
            return {"frames_with_board": 0}
        avg = average_poses(poses)
        d, inc, az = pose_metrics(self.protocol.board, avg[:3, :3], avg[:3, 3])
        dists = [pose_metrics(self.protocol.board, p[:3, :3], p[:3, 3])[0] for p in poses]
        return {"distance_m": d, "inclination_deg": inc, "azimuth_deg": az,
                "distance_std_m": float(np.std(dists)), "frames_with_board": len(poses), "frames": n,
                "board_to_depth": avg.tolist()}
