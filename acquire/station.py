"""The acquisition's workflows: the station (protocol, camera, session) and its warm-up, calibration
and guided-capture runs, with their progress bars and rerun views.

The `acquire` commands and the demo both call these; the commands only parse options and print.
"""

from __future__ import annotations

import base64
import contextlib
import math
import re
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from depthstation.acquire.calibrate import CalibrationAborted, run_calibration
from depthstation.acquire.camera_select import open_camera, parse_camera
from depthstation.acquire.guidance import Guidance
from depthstation.acquire.guided_capture import (
    MOVED_MESSAGE,
    CaptureInterrupted,
    GuidedCapture,
    LiveState,
    StandpointOutcome,
)
from depthstation.acquire.recovery import reconnect
from depthstation.acquire.views import BOARD_HELP, RerunView, TerminalPanel, blueprint
from depthstation.acquire.warmup import WarmupDecision, WarmupSample, run_warmup
from depthstation.core.capture.session import SESSION_FILE, Session, camera_identity, identity_differences
from depthstation.core.device import CalibratableCamera, CameraUnsuitable, device_model
from depthstation.core.errors import CameraError, CaptureError, DepthstationError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.progress import progress, stderr_console
from depthstation.core.protocol import (
    Protocol,
    check_for_acquisition,
    drop_none,
    load_protocol,
    protocol_from_dict,
)
from depthstation.core.rerun_bridge import RerunTarget, recording
from depthstation.core.results import DISK_ERRORS, is_recording_rrd
from depthstation.core.run_warnings import warn
from depthstation.simulate.model import check_seed
from depthstation.simulate.operator import SimulatedOperator, Stance

DEFAULT_PROTOCOL = "checkerboard-d455"
RECONNECT_TIMEOUT_S = 60.0  # a warm-up waits this long for a stalled or unplugged camera
CALIBRATION_RECONNECTS = 3  # a calibration interrupted by an unplug is run again this often
ACQUIRE_APP_ID = "depthstation-acquire"
GuidanceHook = Callable[[Guidance, FrameSet, float], None]


class Station:
    """The objects one command works on: protocol, camera spec, camera, session.

    The camera keeps streaming from the warm-up through calibration into the capture (a device that
    stops streaming cools while the operator reads the prompts); `close` stops it. A live camera is
    checked against the protocol's `[device] model`; `confirm(question)` may let it enable advanced
    mode. A resumed session whose calibration table lives only in the device's RAM has it set again.
    """

    def __init__(self, camera: str, protocol: str | None, session: Path, resume: bool, seed: int,
                 real_time: bool, confirm: Callable[[str], bool] | None = None, *,
                 accelerate: float = 1.0, warmup_interval_s: float | None = None,
                 max_guidance_s: float | None = None) -> None:
        self.spec = parse_camera(camera)
        check_seed(seed)
        check_run_options(self.spec.kind, accelerate, warmup_interval_s, max_guidance_s)
        if session.exists() and not session.is_dir():
            raise InputError(session, "is a file, not a session folder: give a folder for --session")
        stored: dict[str, Any] | None = None
        if resume:
            opened = Session.open(session)
            self.protocol = resumed_protocol(opened, protocol)
            calibrated = opened.data.get("calibration") is not None
        else:
            if (session / SESSION_FILE).exists():
                raise InputError(session, "holds a session already: add --resume to continue it")
            if session.exists() and any(session.iterdir()):
                raise InputError(session, "is not empty; a new session needs an empty or new folder")
            self.protocol = load_protocol(DEFAULT_PROTOCOL if protocol is None else protocol)
            calibrated = False
        check_for_acquisition(self.protocol)
        if warmup_interval_s is not None and warmup_interval_s > self.protocol.warmup.max_minutes * 60.0:
            raise InputError(None, f"--interval {warmup_interval_s:g} s is longer than the warm-up's maximum "
                                   f"time ({self.protocol.warmup.max_minutes:g} min, warmup.max_minutes): "
                                   "give a shorter interval")
        self.operator: SimulatedOperator | None = None
        options: dict[str, Any] = {}
        if self.spec.kind == "sim":
            options = {"seed": seed, "real_time": real_time}
        elif self.spec.kind == "live":
            cal = self.protocol.calibration
            options = {"model": self.protocol.device.model, "consent": confirm,
                       "needs_advanced_mode": ("tare calibration (it runs with the High Accuracy preset)"
                                               if cal.tare and not calibrated else None)}
        # the camera is opened and streams before the session is made: a camera that cannot
        # (no device, no colour, an unknown model) leaves no session behind to block the retry
        self.camera = open_camera(self.spec, **options)
        try:
            info = self.camera.start(self.protocol.streams)
            if self.spec.kind == "file":
                self.camera.stop()  # the playback starts from its first frame again when used
                say_recording_misfits(info, self.protocol, self.spec.path)
        except BaseException:
            self.close()
            raise
        identity = camera_identity(info)
        if resume:
            self.session = opened
            stored = opened.data.get("camera_identity")
            if isinstance(stored, dict) and (diff := identity_differences(stored, identity)):
                self.close()
                raise InputError(session, f"was recorded with {opened.data.get('camera', 'another camera')} "
                                          f"({_who(stored)}); --camera {camera} is {_who(identity)}: "
                                          f"{'; '.join(diff)}. A session holds one camera's standpoints: "
                                          "resume it with that camera, or start a new session")
            if not isinstance(stored, dict):
                self.session.set("camera_identity", identity)
            if not isinstance(opened.data.get("protocol"), dict):  # what plans the standpoints from here on
                self.session.set("protocol", self.protocol.to_dict())
            self.session.verify_complete()
        else:
            try:
                self.session = Session.create(session, protocol=self.protocol, camera=self.spec.describe(),
                                              camera_identity=identity)
            except BaseException:
                self.close()
                raise
        if self.spec.kind == "file" and real_time:
            self.camera.real_time = True
        self.seed = seed
        self._hold_session_calibration()
        self._record_settings(info)

    def _record_settings(self, info: Any) -> None:
        """The device's options (exposure, laser power, thermal compensation, emitter_on_off, ...)
        and its firmware against the recommended one, per run in `camera_settings` (what the
        depth of this run was made with); an old firmware without the thermal loop is a warning."""
        dev = getattr(info, "device", None) or {}
        if "options" not in dev and "firmware_check" not in dev:
            return
        fw = dev.get("firmware_check") or {}
        runs = list(self.session.data.get("camera_settings") or [])
        runs.append({"time_unix_s": time.time(), "usb": dev.get("usb_type_descriptor"),
                     "options": dev.get("options"), "firmware_check": fw})
        self.session.set("camera_settings", runs)
        if fw and not fw.get("thermal_loop_ok"):
            warn(f"firmware {fw.get('firmware')} of the camera is older than {fw.get('thermal_loop_min')}, "
                 f"which the thermal compensation loop needs (recommended {fw.get('recommended')}): depth "
                 "drifts more with temperature; update it with rs-fw-update or the Viewer",
                 str(self.session.dir), "firmware-old")

    def _hold_session_calibration(self) -> None:
        """A table the session applied to RAM only is gone after a power cycle: set it again."""
        rec = self.session.data.get("calibration")
        hold = getattr(self.camera, "hold_calibration", None)
        if isinstance(rec, dict) and rec.get("applied_to") == "ram" and rec.get("table_after_b64") \
                and callable(hold):
            hold(base64.b64decode(rec["table_after_b64"]))

    def start(self) -> Any:
        """Stream the protocol's profile (kept running when it runs already); its StreamInfo."""
        return self.camera.start(self.protocol.streams)

    def close(self) -> None:
        """Stop streaming (the end of a command)."""
        with contextlib.suppress(CameraError):
            self.camera.stop()

    def attach_operator(self) -> GuidanceHook | None:
        """With a simulated camera nobody holds it: a simulated operator follows the guidance."""
        if self.spec.kind != "sim":
            return None
        op = SimulatedOperator(self.protocol.board, Stance(range_m=self.protocol.plan.start_distance_m + 0.3,
                                                           azimuth_deg=-4.0, yaw_deg=3.0), seed=self.seed)
        fps = float(self.protocol.streams.fps)
        camera = self.camera
        camera.set_pose(op.pose(0.0))

        def on_guidance(g: Guidance, fs: FrameSet, t_s: float) -> None:
            op.step(g, t_s)
            camera.set_pose(op.pose(t_s + 1.0 / fps))

        self.operator = op
        return on_guidance


def check_run_options(kind: str, accelerate: float = 1.0, warmup_interval_s: float | None = None,
                      max_guidance_s: float | None = None) -> None:
    """Refuse option values that cannot mean anything, before a camera or session is touched."""
    if not math.isfinite(accelerate) or accelerate < 1.0:
        raise InputError(None, f"--accelerate must be a number of at least 1, got {accelerate}")
    if accelerate != 1.0 and kind != "sim":
        raise InputError(None, "--accelerate runs the simulated camera's clock faster; a recording or a "
                               "live camera warms up in real time: leave --accelerate out")
    if warmup_interval_s is not None and not (math.isfinite(warmup_interval_s) and warmup_interval_s > 0):
        raise InputError(None, f"--interval must be a positive number of seconds, got {warmup_interval_s}")
    if max_guidance_s is not None and not (math.isfinite(max_guidance_s) and max_guidance_s > 0):
        raise InputError(None, f"--max-guidance must be a positive number of seconds, got {max_guidance_s}")


def _who(identity: dict[str, Any]) -> str:
    """A camera in a few words: name, serial, stream sizes."""
    size = identity.get("depth_size")
    return (f"{identity.get('name') or 'unnamed device'} serial {identity.get('serial_number') or '?'}, "
            f"depth {'x'.join(map(str, size)) if size else '?'}")


def resumed_protocol(session: Session, protocol: str | None) -> Protocol:
    """The protocol a resume runs: the one stored in the session (its plan made the standpoints
    recorded so far). A --protocol given too must plan the same standpoints, else the resume is
    refused (a corrected plan cannot apply to standpoints recorded under the old one)."""
    stored = session.data.get("protocol")
    if not isinstance(stored, dict):  # an imported session, or one a calibration alone made
        if protocol is None:
            raise InputError(session.dir / SESSION_FILE, "stores no protocol (an imported session, or one "
                                                         "no capture made): give --protocol, the plan to "
                                                         "resume it with")
        given = load_protocol(protocol)
        say(f"resuming {session.dir} with --protocol {protocol} ({given.name}), stored in {SESSION_FILE} "
            "once the camera is accepted")
        return given
    used = protocol_from_dict(drop_none(stored), session.dir / SESSION_FILE)
    if protocol is not None:
        given = load_protocol(protocol)
        if given.plan != used.plan:
            n_used, n_given = len(used.plan.standpoints()), len(given.plan.standpoints())
            raise InputError(protocol, f"plans other standpoints ({n_given}) than the protocol stored in "
                                       f"{session.dir / SESSION_FILE} ({n_used}), which a resume uses: leave "
                                       "--protocol out to resume, or start a new session with this protocol")
        if given.to_dict() != used.to_dict():
            say(f"--protocol {protocol} differs from the stored protocol outside the plan: the stored one "
                "is used (a resume keeps the session's protocol)")
    say(f"resuming {session.dir} with the protocol stored in {SESSION_FILE} ({used.name})")
    return used


def say(text: str) -> None:
    """One line to the operator, on stderr."""
    stderr_console.print(text)


WARMUP_HELP = "Warm-up: device temperatures (degrees C) and the centre depth (m) over time (s)."
SESSION_HELP = (f"{WARMUP_HELP} Then the guided capture: {BOARD_HELP}")


def rerun_recording_id(session: Session) -> str:
    """One rerun recording id per session: the .rrd files of its steps and resumes open as one."""
    return f"depthstation-session-{session.data.get('created', '')}-{session.dir.resolve().name}"


@contextlib.contextmanager
def session_view(st: Station, target: RerunTarget | Any, description: str) -> Iterator[Any]:
    """The rerun stream of a step: its own for a RerunTarget (one command, one step), else the
    stream the caller opened for all the steps of one run (`acquire session`), or None."""
    if isinstance(target, RerunTarget):
        with recording(ACQUIRE_APP_ID, target, blueprint(), description=description,
                       recording_id=rerun_recording_id(st.session)) as rec:
            yield rec
    else:
        yield target


@contextlib.contextmanager
def session_run_view(st: Station, target: RerunTarget) -> Iterator[Any]:
    """The one rerun stream (or None) that all the steps of an `acquire session` run write into."""
    with recording(ACQUIRE_APP_ID, target, blueprint(), description=SESSION_HELP,
                   recording_id=rerun_recording_id(st.session)) as rec:
        yield rec


def acquire_rrd(rrd: Path, resume: bool) -> Path:
    """Where an acquire command's --rrd goes. A new session never overwrites a file. A resume
    keeps the earlier run's recording and writes the next `NAME.resume-N.rrd` beside it: same
    recording id, so `rerun NAME.rrd NAME.resume-1.rrd` shows the session as one recording."""
    rrd = Path(rrd)
    if not rrd.exists() or rrd.is_dir():
        return rrd  # a folder is refused by RerunTarget
    if not resume:
        raise InputError(rrd, "exists; depthstation never overwrites a file: choose another name "
                              "(a --resume of the session writes its recording beside it)")
    if not is_recording_rrd(rrd):
        raise InputError(rrd, "exists and is not a rerun recording (.rrd): choose another name")
    n = 1
    while (nxt := rrd.with_name(f"{rrd.stem}.resume-{n}{rrd.suffix}")).exists():
        n += 1
    say(f"{rrd} exists (an earlier run of the session): this run's recording goes to {nxt}")
    return nxt


def recording_misfits(info: Any, protocol: Protocol) -> list[str]:
    """How a recording played as the camera differs from what the protocol asks (another camera
    model, size or stream set): a live camera would refuse such a profile, a recording cannot."""
    out = []
    d = info.depth_intrinsics
    want = protocol.streams
    if (d.width, d.height) != (want.width, want.height):
        out.append(f"depth {d.width}x{d.height}, the protocol asks {want.width}x{want.height}")
    fps = getattr(info, "fps", None)
    if fps and abs(float(fps) - want.fps) > 0.5:  # the frames, and the still time, follow the recording
        out.append(f"{float(fps):g} fps, the protocol asks {want.fps:g}")
    if want.infrared and info.infrared_intrinsics is None:
        out.append("no infrared stream, the protocol asks for one")
    name = str((info.device or {}).get("name") or "")
    model = protocol.device.model.strip().upper()
    found = device_model(name)  # the model a name ends with; else the model as a word in it
    fits = found == model if found else re.search(rf"\b{re.escape(model)}\b", name.upper()) is not None
    if name and not fits:  # not a substring: "D45" is in "D455", "D435" in "D435I"
        out.append(f"recorded by {name}, the protocol is for a {protocol.device.model}")
    return out


def say_recording_misfits(info: Any, protocol: Protocol, path: Path | None) -> None:
    """Warn once per run; the standpoints are captured as recorded (`recording-mismatch`)."""
    if misfits := recording_misfits(info, protocol):
        warn(f"the recording does not fit the protocol ({'; '.join(misfits)}): its standpoints are "
             "captured as recorded", str(path), "recording-mismatch")


def do_warmup(st: Station, interval_s: float, accelerate: float, target: RerunTarget | Any) -> dict[str, Any]:
    """Stream until the protocol's warm-up rule holds; the curve goes into the session and rerun
    (`target`: a RerunTarget, or the stream of the whole run that `session_view` passes on)."""
    rule = st.protocol.warmup
    info = st.camera.start(st.protocol.streams)
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    if accelerate > 1.0:
        # An accelerated, simulated clock: device time advances by exactly what the loop sleeps,
        # and the loop sleeps that much / `accelerate` of wall time. The wall time spent fetching
        # a frame does not count, so the warm-up curve is sampled every interval whatever the load
        # of the machine (a wall-clock multiple would turn 0.3 s of rendering into 2 min).
        virtual = [0.0]

        def fast_clock() -> float:
            return virtual[0]

        def fast_sleep(s: float) -> None:
            virtual[0] += s
            time.sleep(s / accelerate)
        clock, sleep = fast_clock, fast_sleep
        if hasattr(st.camera, "set_clock"):
            st.camera.set_clock(clock)
    try:
        with session_view(st, target, WARMUP_HELP) as rec, progress() as bar:
            task = bar.add_task("warm-up", total=rule.max_minutes * 60.0, status="")
            said_no_temp = [False]

            def on_sample(s: WarmupSample, d: WarmupDecision) -> None:
                if not d.has_temperature and not said_no_temp[0]:
                    said_no_temp[0] = True
                    say("this camera reports no temperature: warm-up falls back to the minimum time")
                temp = s.temperature_c
                slope = "" if d.slope_c_per_min is None else f" slope {d.slope_c_per_min:+.3f} °C/min"
                bar.update(task, completed=s.t_s,
                           status=("" if temp is None else f"{temp:.1f} °C") + slope + f"  {d.reason}")
                if rec is not None:
                    import rerun as rr

                    rec.set_time("warmup_s", duration=s.t_s)
                    for k, v in s.temperatures_c.items():
                        rec.log(f"warmup/temperature_c/{k}", rr.Scalars([v]))
                    if s.depth_m is not None:
                        rec.log("warmup/centre_depth_m", rr.Scalars([s.depth_m]))

            try:
                def recover(exc: BaseException) -> None:
                    reconnect(st.camera, st.start, exc, timeout_s=RECONNECT_TIMEOUT_S, say=say)
                    say("camera back: the warm-up goes on")

                result = run_warmup(st.camera, rule, info.depth_units_m, interval_s=interval_s, clock=clock,
                                    sleep=sleep, on_sample=on_sample, recover=recover)
            except EOFError as exc:
                raise InputError(st.spec.path, f"the recording ended before the warm-up's minimum time "
                                 f"({rule.min_minutes:g} min, warmup.min_minutes): a recording cannot warm a "
                                 "camera up; leave the warm-up out (acquire capture, or acquire session, "
                                 "which records none for a recording)") from exc
    except BaseException:
        st.close()
        raise
    finally:
        if accelerate > 1.0 and hasattr(st.camera, "set_clock"):
            st.camera.set_clock(None)  # back to frame time for what follows
    # the camera keeps streaming into calibration and capture: it must not cool meanwhile
    summary = result.summary()
    summary["interval_s"] = interval_s
    summary["accelerated"] = accelerate > 1.0
    take = getattr(st.camera, "take_events", None)
    if callable(take) and (events := take()):
        summary["device_events"] = events
    st.session.set("warmup", summary)
    note_streaming(st.session, st.camera)
    say(f"warm-up done: {summary['reason']}")
    if summary["has_temperature"] and not summary["settled"]:
        warn(f"warm-up ended without the temperature settling ({summary['reason']}; tolerance "
             f"{rule.max_slope_c_per_min:g} °C/min): depth may still drift during the capture",
             str(st.session.dir), "warmup-unsettled")
    return summary


COOLED_DROP_C = 2.0  # a drop of two whole-degree steps since the warm-up's end: the camera cooled
COOLED_IDLE_S = 120.0  # without a temperature: this long without frames and the camera counts as cooled


def note_streaming(session: Session, camera: Any) -> None:
    """When the camera last streamed (and how warm it was): a resume judges from it whether the
    warm-up still holds."""
    temps = {}
    with contextlib.suppress(CameraError, RuntimeError):
        temps = dict(camera.temperatures())
    session.set("streaming", {"last_frame_unix_s": time.time(), "temperatures_c": temps})


def warmup_cooled(st: Station) -> str | None:
    """Why the session's warm-up no longer holds (the camera cooled since), or None. Judged by the
    temperature now against the warm-up's last reading where the camera reports one, else by the
    time without frames since the session last streamed."""
    rec = st.session.data.get("warmup")
    if not isinstance(rec, dict) or not rec.get("done"):
        return None
    last = st.session.data.get("streaming") or {}
    then = last.get("last_frame_unix_s")
    if then is None:
        then = (st.session.dir / SESSION_FILE).stat().st_mtime
    idle_s = max(0.0, time.time() - float(then))
    curve = rec.get("curve") or []
    end = curve[-1] if curve else {}
    now: dict[str, float] = {}
    with contextlib.suppress(CameraError, RuntimeError):
        now = dict(st.camera.temperatures())
    for key in ("projector", "asic"):
        if f"{key}_c" in end and key in now:
            drop = float(end[f"{key}_c"]) - float(now[key])
            if drop >= COOLED_DROP_C:
                return (f"the {key} temperature fell {drop:g} °C since the warm-up ended "
                        f"({end[f'{key}_c']:g} -> {now[key]:g} °C, {idle_s / 60:.1f} min without frames)")
            return None
    if idle_s > COOLED_IDLE_S:
        return (f"{idle_s / 60:.1f} min without frames since the session last streamed (no temperature to "
                f"judge by; over {COOLED_IDLE_S / 60:g} min counts as cooled)")
    return None


def redo_warmup_if_cooled(st: Station) -> bool:
    """On a resume: a camera that cooled since its warm-up is warmed up again; the earlier record
    goes to `warmup_history` with `settled: false` and why (a cooled camera is never recorded as
    settled). True when the warm-up must run again."""
    why = warmup_cooled(st)
    if why is None:
        return False
    rec = dict(st.session.data["warmup"])
    history = list(st.session.data.get("warmup_history") or [])
    history.append({**rec, "settled": False, "was_settled": bool(rec.get("settled")), "cooled": why})
    st.session.set("warmup_history", history)
    st.session.set("warmup", None)
    say(f"the camera cooled since its warm-up ({why}): warming it up again")
    return True


def do_calibrate(st: Station, yes: bool, write: bool, ask: Callable[[str], bool] | None = None,
                 ask_distance: Callable[[str, float], float] | None = None,
                 choose: Callable[[str], str] | None = None) -> dict[str, Any]:
    """On-chip / tare as the protocol asks; a new table is applied only when the operator agrees
    (`yes`: when recommended, for scripts; else `ask(question)`; without `ask`, never). `ask_distance` lets
    the operator enter the tare target's measured distance from the front glass (not with `yes`).
    The camera streams the protocol's profile before and after (a live one switches to the
    calibration mode for each run). A run that fails is retried (re-aimed), skipped or aborted:
    `choose(question)` asks; with `yes` (or no `choose`) it is retried a set number of times, then
    skipped and the failures recorded."""

    def confirm(question: str) -> bool:
        if yes:
            say(f"{question} yes (--yes)")
            return True
        return ask(question) if ask is not None else False

    if isinstance(st.camera, CalibratableCamera):  # a recording is not started just to be skipped
        try:
            st.start()
            for tries in range(1, CALIBRATION_RECONNECTS + 2):
                try:
                    record = run_calibration(st.camera, st.protocol.calibration, confirm=confirm, say=say,
                                             write=write, ask_distance=None if yes else ask_distance,
                                             unattended=yes, choose=None if yes else choose)
                    break
                except CameraError as exc:
                    # unplugged or reset while it calibrated: wait for it as the capture does, then
                    # run the calibration again (a table set before lives in RAM and is held)
                    final = isinstance(exc, (CalibrationAborted, CameraUnsuitable))
                    if final or tries > CALIBRATION_RECONNECTS:
                        raise
                    say(f"calibration interrupted ({exc}): waiting for the camera, then calibrating again")
                    reconnect(st.camera, st.start, exc, timeout_s=RECONNECT_TIMEOUT_S, say=say)
        except BaseException:
            st.close()
            raise
    else:
        record = run_calibration(st.camera, st.protocol.calibration, confirm=confirm, say=say, write=write)
    take = getattr(st.camera, "take_events", None)
    if callable(take) and (events := take()):
        record["device_events"] = events
    keep_replaced_calibration(st.session, record)
    st.session.set("calibration", record)
    note_streaming(st.session, st.camera)
    return record


def keep_replaced_calibration(session: Session, record: dict[str, Any]) -> None:
    """A new table after standpoints were captured: the earlier record goes to
    `calibration_history` (with the standpoints taken under it) and the run warns. Why: the
    session-level record was replaced without a word, so it no longer described those standpoints
    (each MCAP still carries the calibration it was captured with)."""
    before = session.data.get("calibration")
    taken = [str(e["name"]) for e in session.standpoints if e.get("status") == "complete"]
    if not taken or not isinstance(before, dict) or \
            before.get("table_after_b64") == record.get("table_after_b64"):
        return
    history = list(session.data.get("calibration_history") or [])
    history.append(dict(before, standpoints=taken))
    session.set("calibration_history", history)
    warn(f"the depth calibration changed after {len(taken)} standpoint(s) were captured with the earlier "
         f"table ({', '.join(taken[:4])}{', ...' if len(taken) > 4 else ''}; kept in calibration_history): "
         "the session mixes two calibrations", str(session.dir), "calibration-changed")


def _disk_cause(exc: BaseException) -> OSError | None:
    """The full, read-only or forbidden disk behind `exc` (itself or what it was raised from)."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno in DISK_ERRORS:
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


@contextlib.contextmanager
def disk_full_said(session_dir: Path) -> Iterator[None]:
    """A disk that fills (or turns read-only) during a capture, said as what was kept and where (exit
    1). Why: the line said 'nothing was kept in .' while a finished standpoint and a partial one were."""
    try:
        yield
    except (OSError, CaptureError) as exc:
        cause = _disk_cause(exc)
        if cause is None:
            raise
        raise DepthstationError(kept_after_disk_error(session_dir, cause)) from exc


def kept_after_disk_error(session_dir: Path, exc: OSError) -> str:
    """One line: the failed write, then every standpoint file kept in the session folder."""
    files = sorted(session_dir.iterdir()) if session_dir.is_dir() else []
    done = [p.name for p in files if p.name.endswith(".mcap")]
    cut = [f"{p.name} ({p.stat().st_size} bytes, cut where the write failed: its complete chunks read back)"
           for p in files if p.name.endswith(".mcap.partial")]
    kept = "; ".join([f"{', '.join(done)} complete"] * bool(done) + cut) or "no standpoint file"
    where = exc.filename or session_dir
    return (f"{where}: cannot write ({exc.strerror or exc}); kept in {session_dir}: {kept}; "
            f"{SESSION_FILE} holds the last state written whole; free space, then --resume re-records "
            "the standpoints not complete")


def say_device_drop(session: Session, events: list[dict[str, Any]], state: LiveState,
                    lost: list[str]) -> None:
    """A line on stderr when the camera drops (and what became of the take it cut) and one when it
    is back, panel or not: the panel's red line vanished with the next frame, and without a
    terminal nothing was said at all. `lost` holds the message said last while reconnecting."""
    name = state.standpoint.name
    if state.phase == "reconnecting":
        if lost and lost[-1] == state.message:
            return
        first = not lost
        lost.append(state.message)
        if not first:  # a later message of the same wait (a camera back on USB 2, a reset)
            say(f"{name}: {state.message}")
            return
        drop = next((e for e in reversed(events) if e.get("event") in ("disconnected", "stalled")), None)
        kept = ""
        if drop is not None and drop.get("during") == "recording":
            aside = [e for e in session.standpoints
                     if e.get("name") == name and e.get("status") == "discarded"]
            where = f" kept aside as {session.dir / aside[-1]['file']}" if aside else ""
            kept = f"; the take it cut ({drop.get('frames_recorded', 0)} frames){where}"
        what = drop.get("event", "disconnected") if drop is not None else "disconnected"
        say(f"{name}: the camera {what}{kept}; {state.message}")
    elif lost:
        lost.clear()
        say(f"{name}: the camera is back; the standpoint starts again")


def do_capture(st: Station, target: RerunTarget | Any,
               max_guidance_s: float | None) -> list[StandpointOutcome]:
    """The guided loop with the panel and rerun; a recording's end stops it cleanly."""
    on_guidance = st.attach_operator()
    outcomes: list[StandpointOutcome] = []
    with disk_full_said(st.session.dir), session_view(st, target, BOARD_HELP) as rec:
        views: list[Any] = []
        panel = TerminalPanel() if sys.stderr.isatty() else None
        if panel is not None:
            views.append(panel)
        rerun_view: list[RerunView] = []
        lost: list[str] = []  # the reconnecting message said last (a drop and its wait, on stderr)

        def on_state(state: LiveState) -> None:
            if rec is not None and cap.info is not None:
                if not rerun_view:
                    rerun_view.append(RerunView(rec, cap.info.depth_units_m))
                rerun_view[0](state)
            for v in views:
                v(state)
            say_device_drop(st.session, cap.events, state, lost)
            if state.phase == "done":
                note_streaming(st.session, st.camera)
            if panel is None and state.phase == "done":
                say(f"{state.standpoint.name}: recorded {state.recorded} frames")
            if panel is None and state.message == MOVED_MESSAGE:
                say(f"{state.standpoint.name}: {MOVED_MESSAGE}")

        cap = GuidedCapture(st.camera, st.protocol, st.session, on_guidance=on_guidance, on_state=on_state,
                            max_guidance_s=max_guidance_s)
        try:
            if panel is not None:
                panel.__enter__()
            outcomes = cap.run()
        except EOFError:
            say("the recording ended: the standpoints done so far are in the session; "
                 "the rest stay open for --resume with another recording or a camera")
            if not any(o.status == "complete" for o in cap.finished):
                warn(f"the recording {st.spec.path} ended before any standpoint was recorded in this run "
                     "(the board never held still in place long enough)", str(st.session.dir),
                     "recording-ended")
        except KeyboardInterrupt as exc:
            open_ = [e["name"] for e in st.session.standpoints if e.get("status") == "partial"]
            msg = (f"interrupted: finished standpoints are safe in {st.session.dir}"
                   + (f"; {', '.join(open_)} kept as partial" if open_ else "")
                   + "; --resume continues")
            raise CaptureInterrupted(msg) from exc
        finally:
            if panel is not None:
                panel.__exit__(None, None, None)
            if cap.events or cap.skipped:
                st.session.set("capture", {"skipped": dict(cap.skipped), "events": list(cap.events)})
    done = [e["name"] for e in st.session.standpoints if e.get("status") == "complete"]
    plan = [sp.name for sp in st.protocol.plan.standpoints()]
    open_ = [n for n in plan if n not in done and n not in cap.skipped]
    say(f"session {st.session.dir}: {len(done)} standpoints complete, {len(cap.skipped)} skipped "
         f"(end of range), {len(open_)} open" + (f": {', '.join(open_)}" if open_ else ""))
    if cap.dropped:
        say(f"warning: {cap.dropped} frames dropped by the writer")
    return outcomes
