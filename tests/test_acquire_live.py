"""The live path against a device double (tests/fake_realsense.py): a fake pyrealsense2 that
behaves as librealsense's sources, Intel's examples and its issue tracker say a D455 does. One test
per finding of the live-path review: calibration mode and order, health scales, tables that do not
stay, whole-degree temperatures, advanced mode, stalls, replugs, repeated frames and gaps, USB 2,
model check, streaming kept alive, the tare ground truth's reference point."""

from __future__ import annotations

import base64
import io
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import itertools

import fake_realsense as frs
from test_acquire_loop import render_board

from depthstation.acquire.calibrate import GOOD, IMPROVABLE, REQUIRED, TARE_OFF, TARE_SMALL, run_calibration
from depthstation.acquire.guided_capture import GuidedCapture, LiveState
from depthstation.acquire.live_camera import LiveCamera
from depthstation.acquire.warmup import run_warmup
from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics
from depthstation.core.capture.session import Session
from depthstation.core.device import CameraUnsuitable
from depthstation.core.protocol import PROTOCOL_DIR, Calibration, Plan, Protocol, Streams, Tolerances, Warmup
from depthstation.simulate.poses import standpoint_pose

PROTO_STREAMS = Streams(width=640, height=360, fps=30)
CAL_PROFILE = [("depth", 256, 144, "z16", 90, 0)]
PROTO_PROFILE = [("depth", 640, 360, "z16", 30, 0), ("color", 640, 360, "rgb8", 30, 0)]


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """Inject a world with one D455 as `pyrealsense2`; `fake(**unit options)` builds it."""

    def make(**unit: Any) -> tuple[frs.FakeRealSense, frs.FakeUnit]:
        u = frs.FakeUnit(**unit)
        world = frs.FakeRealSense(u)
        monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)
        return world, u

    yield make


def camera(**kw: Any) -> LiveCamera:
    """A live camera with the recovery waits scaled to the fake's (0.05 s gone, 0.3 s back)."""
    opts: dict[str, Any] = {"model": "D455", "removal_timeout_s": 2.0, "enumeration_timeout_s": 3.0,
                            "quiet_s": 0.05, "poll_s": 0.01, "stop_deadline_s": 0.2}
    return LiveCamera(**{**opts, **kw})


def board_scene(board: Board, distance_m: float) -> frs.Scene:
    """The board rendered at a standpoint, once per image size (the operator holds still)."""
    pose = standpoint_pose(board, distance_m, 0.0)
    cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def scene(kind: str, intr: tuple[int, int, float, float, float, float], unit: frs.FakeUnit) -> Any:
        if intr[:2] not in cache:
            cache[intr[:2]] = render_board(board, pose, Intrinsics(*intr))
        depth, color = cache[intr[:2]]
        return depth if kind == "depth" else color if kind == "color" else color[..., 0]
    return scene


def one_standpoint(frames: int = 8) -> Protocol:
    return Protocol("live", streams=PROTO_STREAMS,
                    plan=Plan(frames_per_standpoint=frames, start_distance_m=1.0, max_distance_m=1.0,
                              inclinations_deg=(0.0,)),
                    tolerances=Tolerances(still_seconds=0.2))


def starts(world: frs.FakeRealSense) -> list[list[tuple[Any, ...]]]:
    return [v["streams"] for k, v in world.calls if k == "pipeline.start"]


# -- calibration mode, order, health scales, tables --------------------------------------------
def test_calibration_runs_in_intels_mode_after_the_first_frame(fake: Any) -> None:
    world, unit = fake()
    cam = camera()
    cam.start(PROTO_STREAMS)
    said: list[str] = []
    rec = run_calibration(cam, Calibration(on_chip=True, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: True, say=said.append)
    assert not rec["skipped"]
    # the double refuses outside the mode; the live path switched to it and waited for a frame first
    seq = [(k, v) for k, v in world.calls if k in ("pipeline.start", "pipeline.stop", "first_frame",
                                                     "run_on_chip_calibration", "run_tare_calibration")]
    names = [k for k, _ in seq]
    i = names.index("run_on_chip_calibration")
    assert names[i - 2:i + 1] == ["pipeline.start", "first_frame", "run_on_chip_calibration"]
    assert seq[i - 2][1]["streams"] == CAL_PROFILE and seq[i][1]["streams"] == CAL_PROFILE
    assert seq[i][1]["emitter"] == 1.0  # the Viewer runs on-chip and tare with the emitter on
    j = names.index("run_tare_calibration")
    assert names[j - 2:j + 1] == ["pipeline.start", "first_frame", "run_tare_calibration"]
    assert seq[j][1]["streams"] == CAL_PROFILE
    # between and after the runs the protocol's profile streams again (the camera stays warm)
    assert starts(world) == [PROTO_PROFILE, CAL_PROFILE, PROTO_PROFILE, CAL_PROFILE, PROTO_PROFILE]
    assert unit.describe_streams() == PROTO_PROFILE
    # and the device double itself refuses a calibration in the protocol's mode
    rs = world.module
    with pytest.raises(RuntimeError, match="calibration mode"):
        rs.auto_calibrated_device(rs.context().query_devices()[0]).run_on_chip_calibration("{}", 30000)
    cam.stop()


def test_usb2_has_no_calibration_mode_and_says_so_in_one_line(fake: Any) -> None:
    world, unit = fake(usb="2.1")
    cam = camera()
    streams = Streams(width=640, height=480, fps=15)  # offered on USB 2
    cam.start(streams)
    said: list[str] = []
    rec = run_calibration(cam, Calibration(on_chip=True), confirm=lambda q: True, say=said.append)
    assert rec["skipped"] and "USB 2.1" in rec["reason"] and "256x144" in rec["reason"]
    assert [s for s in said if "256x144" in s] == [rec["reason"]] and "\n" not in rec["reason"]
    assert "run_on_chip_calibration" not in world.names()
    assert unit.describe_streams() == [("depth", 640, 480, "z16", 15, 0), ("color", 640, 480, "rgb8", 15, 0)]
    cam.stop()


@pytest.mark.parametrize(("health", "level", "recommend"), [(0.10, GOOD, False), (-0.40, IMPROVABLE, True),
                                                            (0.80, REQUIRED, True)])
def test_on_chip_health_is_one_value_on_intels_bands(fake: Any, health: float, level: str,
                                                     recommend: bool) -> None:
    fake(on_chip_health=health)
    cam = camera()
    said: list[str] = []
    rec = run_calibration(cam, Calibration(on_chip=True), confirm=lambda q: False, say=said.append)
    step = rec["steps"][0]
    assert step["health"] == [pytest.approx(health)]  # the SDK's second value (0.0) is no health
    assert step["verdict"] == [level] and step["recommended"] is recommend


@pytest.mark.parametrize(("bias", "level", "recommend"), [(0.20, TARE_OFF, True), (0.012, TARE_OFF, True),
                                                          (0.001, TARE_SMALL, False)])
def test_tare_health_is_a_relative_depth_error(fake: Any, bias: float, level: str, recommend: bool) -> None:
    """Tare returns (Z / GT - 1) before and after: a 20 % error is not 'good' (the on-chip bands)."""
    _world, _unit = fake(depth_bias=bias)
    cam = camera()
    said: list[str] = []
    rec = run_calibration(cam, Calibration(on_chip=False, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: False, say=said.append)
    step = rec["steps"][0]
    before, after = step["health"]
    assert before == pytest.approx(bias, abs=1e-9)  # the ground truth is the true depth-origin distance
    assert abs(after) < 1e-3
    assert step["verdict"] == [level] and step["recommended"] is recommend
    assert any(f"{100 * bias:+.3f} % before" in s for s in said)


def test_tare_ground_truth_is_measured_from_the_depth_origin(fake: Any) -> None:
    """The operator measures 1 m from the glass; the D455 measures from 4.55 mm behind it."""
    world, unit = fake(depth_bias=0.004)
    cam = camera()
    rec = run_calibration(cam, Calibration(on_chip=False, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: True, say=lambda s: None)
    sent = [v["ground_truth_mm"] for k, v in world.calls if k == "run_tare_calibration"]
    assert sent == [pytest.approx(1004.55)]
    details = rec["steps"][0]["details"]
    assert details["depth_origin_behind_glass_mm"] == 4.55 and details["distance_from_glass_m"] == 1.0
    # after the tare the camera reads the true depth: residual well under a millimetre
    assert abs(unit.true_depth_mm() * (1 + unit.bias()) - 1004.55) < 0.2
    # a ground truth taken from the glass would have left the offset in every depth
    cam.run_tare_calibration(1.0)
    assert unit.true_depth_mm() * (1 + unit.bias()) - 1004.55 == pytest.approx(-4.55, abs=0.2)


def test_a_table_kept_in_ram_is_set_again_after_a_replug(fake: Any) -> None:
    """On-chip yes, tare no: the tare's table (left active by the run) is undone, the on-chip one is
    held in RAM; a replug reverts the device to flash, and the next start sets it again."""
    _world, unit = fake(depth_bias=0.01)
    flash = list(unit.flash)
    cam = camera()
    cam.start(PROTO_STREAMS)
    answers = iter([True, False])
    rec = run_calibration(cam, Calibration(on_chip=True, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: next(answers), say=lambda s: None)
    on_chip = base64.b64decode(rec["steps"][0]["table_new_b64"])
    assert bytes(unit.active_table()) == on_chip and unit.flash == flash
    assert rec["applied_to"] == "ram" and rec["reapplied_after_reconnect"]
    assert base64.b64decode(rec["table_after_b64"]) == on_chip
    unit.unplug(0.1)
    time.sleep(0.3)
    assert unit.active_table() == flash  # the device forgot it
    cam.stop()
    cam.start(PROTO_STREAMS)
    assert bytes(unit.active_table()) == on_chip
    assert [e["event"] for e in cam.take_events()] == ["removed", "calibration_reapplied"]
    cam.stop()


def test_write_burns_the_table_to_flash(fake: Any) -> None:
    world, unit = fake()
    cam = camera()
    rec = run_calibration(cam, Calibration(on_chip=True), confirm=lambda q: True, say=lambda s: None,
                          write=True)
    assert rec["applied_to"] == "flash" and not rec["reapplied_after_reconnect"]
    assert bytes(unit.flash) == base64.b64decode(rec["steps"][0]["table_new_b64"])
    assert world.names().index("write_calibration") > world.names().index("set_calibration_table")


# -- identity, link, advanced mode ---------------------------------------------------------------
@pytest.mark.parametrize(("unit", "needle"), [
    ({"name": "RealSense D435", "product_id": "0B07"}, "'RealSense D435'"),
    ({"name": "RealSense D455F"}, "'RealSense D455F'"),
    ({"usb": "2.1"}, "USB 2.1 offers no depth 1280x720 z16 at 30 fps, color 1280x720 rgb8 at 30 fps: "
                     "connect"),
])
def test_model_and_usb_are_checked_before_streaming(fake: Any, unit: dict[str, Any], needle: str) -> None:
    world, _ = fake(**unit)
    t0 = time.monotonic()
    with pytest.raises(CameraUnsuitable) as err:
        camera().start(Streams())
    assert needle in str(err.value) and "\n" not in str(err.value)
    assert "pipeline.start" not in world.names() and time.monotonic() - t0 < 1.0


def test_the_older_intel_name_is_the_same_model(fake: Any) -> None:
    fake(name="Intel RealSense D455")
    cam = camera()
    cam.start(PROTO_STREAMS)
    assert cam.device_info()["model"] == "D455"
    cam.stop()


def test_a_preset_without_advanced_mode_is_refused_in_one_line(fake: Any, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    from depthstation.app.cli import main

    world, unit = fake(advanced_mode=False)
    proto = tmp_path / "ha.toml"
    demo = (PROTOCOL_DIR / "demo-d455.toml").read_text()
    proto.write_text(demo.replace("[streams]\n", '[streams]\npreset = "High Accuracy"\n', 1))
    monkeypatch.setattr(sys, "argv", ["depthstation", "acquire", "warmup", "--camera", "live", "--protocol",
                                      str(proto), "--session", str(tmp_path / "s")])
    monkeypatch.setattr(sys, "stdin", io.StringIO("n\n"))  # the operator declines to enable it
    with pytest.raises(SystemExit) as code:
        main()
    err = capsys.readouterr().err
    assert code.value.code == 1
    assert "Enable it now?" in err  # the question was asked (stdin answered no)
    line = err[err.index("depthstation: error:"):]
    assert line.count("\n") == 1
    assert line.startswith("depthstation: error: advanced mode is off on RealSense D455")
    assert "streams.preset 'High Accuracy'" in line and "realsense-viewer" in line
    assert "pipeline.start" not in world.names() and unit.pipeline is None
    assert not [c for c in world.calls if c[0] == "set_option" and c[1]["option"] == "visual_preset"]
    # with consent the station enables it (the device resets), then sets the preset
    cam = camera(consent=lambda q: True)
    cam.start(Streams(width=640, height=360, preset="High Accuracy"))
    assert unit.advanced and unit.options["visual_preset"] == frs.PRESETS.index("High Accuracy")
    assert cam.device_info()["preset_applied"] == "High Accuracy"
    assert [e["event"] for e in cam.take_events()][:1] == ["advanced_mode_enabled"]
    cam.stop()


# -- temperatures ----------------------------------------------------------------------------------
def test_warmup_on_whole_degree_readings(fake: Any) -> None:
    """The device reports whole degrees, only while streaming; the rule then bounds the slope over a
    window long enough for 1-degree steps and ends only once the true slope is small."""
    now = [0.0]
    u = frs.FakeUnit()
    world = frs.FakeRealSense(u, clock=lambda: now[0])
    sys.modules["pyrealsense2"] = world.module
    try:
        cam = camera()
        assert cam.temperatures() == {}
        rs = world.module
        with pytest.raises(RuntimeError, match="during streaming only"):
            rs.context().query_devices()[0].first_depth_sensor().get_option(rs.option.asic_temperature)
        info = cam.start(PROTO_STREAMS)
        rule = Warmup(min_minutes=5.0, max_slope_c_per_min=0.05, window_minutes=5.0, max_minutes=180.0)

        def sleep(s: float) -> None:
            now[0] += s

        res = run_warmup(cam, rule, info.depth_units_m, interval_s=10.0, clock=lambda: now[0], sleep=sleep)
        cam.stop()
    finally:
        del sys.modules["pyrealsense2"]
    temps = [s.temperatures_c["asic"] for s in res.samples]
    assert all(t == int(t) for t in temps) and temps[-1] > temps[0]
    d = res.decision
    assert d is not None and d.done and "settled" in d.reason
    assert d.resolution_c == 1.0 and d.window_s == pytest.approx(40 * 60)
    t = res.samples[-1].t_s
    true_slope = 17.0 / 720.0 * np.exp(-t / 720.0) * 60.0  # the double's first-order warm-up, C/min
    assert true_slope <= rule.max_slope_c_per_min


# -- frames and faults during a take ---------------------------------------------------------------
def run_take(world: frs.FakeRealSense, unit: frs.FakeUnit, tmp_path: Path, hook: Any,
             frames: int = 8, table: bytes | None = None,
             **cam_kw: Any) -> tuple[Session, list[str], LiveCamera]:
    """One standpoint through the live camera and the guided loop; `hook(state)` sees every state
    (and injects the faults)."""
    proto = one_standpoint(frames)
    unit.scene = board_scene(proto.board, 1.0)
    cam = camera(**cam_kw)
    if table is not None:
        cam.start(proto.streams)
        cam.set_calibration_table(table)
    session = Session.create(tmp_path / "s", protocol=proto)
    messages: list[str] = []

    def on_state(st: LiveState) -> None:
        messages.append(st.message)
        hook(st)

    cap = GuidedCapture(cam, proto, session, on_state=on_state, max_guidance_s=20, frame_timeout_s=0.3,
                        reconnect_timeout_s=10.0, sleep=time.sleep)
    out = cap.run()
    assert [o.status for o in out] == ["complete"]
    return Session.open(tmp_path / "s"), messages, cam


def test_repeated_frames_are_never_recorded_and_gaps_are_counted(fake: Any, tmp_path: Path) -> None:
    world, unit = fake()
    armed = [False]

    def inject(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 2 and not armed[0]:
            armed[0] = True
            unit.inject(repeat="color")          # a frameset with a stale colour frame
            unit.inject(drop={"depth": 3, "color": 3})  # the device lost 3 of each
            unit.inject(repeat="depth")          # the aggregator re-sends the last depth frame
            unit.inject(drop={"depth": 2})       # 2 more depth frames lost
            unit.inject(repeat="depth")

    s, _, _ = run_take(world, unit, tmp_path, inject, frames=8)
    rec = s.recordings()[0]
    fsets = list(rec.frames())
    depth_numbers = [f.index for f in fsets]
    color_numbers = [f.metadata["color_frame_number"] for f in fsets]
    assert len(fsets) == 8
    assert len(set(depth_numbers)) == 8 and len(set(color_numbers)) == 8  # no frame twice
    frames = rec.metadata["standpoint"]["frames"]
    assert frames["frame_counter"] == "device"
    assert frames["device_frames_lost"] == {"depth": 5, "color": 3}
    # the capture takes frames through a pipeline callback, which gets the synchronised frames only
    # (src/pipeline/aggregator.cpp, `async_set`): the aggregator's repeats never reach it
    assert frames["framesets_skipped"] == {"repeated": 0, "stale_color": 0, "duplicate_index": 0}
    assert set(frames["host_frames_dropped"]) == {"depth", "color"}


def test_a_take_admits_no_frame_twice() -> None:
    """The capture's own guard, for any camera: the same frame number is never written twice, and
    a camera without the live metadata has its gaps read from the frame numbers."""
    from depthstation.acquire.guided_capture import FrameAccounting
    from depthstation.core.frames import FrameSet

    acc = FrameAccounting()
    admitted = [acc.admit(FrameSet(i, i)) for i in (10, 11, 11, 14, 15, 15, 16)]
    assert admitted == [True, True, False, True, True, False, True]
    assert acc.summary() == {"frame_counter": "index", "device_frames_lost": {"depth": 2, "color": 0},
                             "host_frames_dropped": None,
                             "framesets_skipped": {"repeated": 0, "stale_color": 0, "duplicate_index": 2}}


def test_without_frame_metadata_gaps_cannot_be_seen(fake: Any) -> None:
    _world, unit = fake(metadata=False)
    cam = camera()
    cam.start(PROTO_STREAMS)
    cam.wait_for_frames(1.0)
    unit.inject(drop={"depth": 4})
    fs = cam.wait_for_frames(1.0)
    assert fs.metadata["frame_counter"] == "host" and fs.metadata["frames_lost_before"] is None
    cam.stop()


def test_a_stall_is_reset_and_the_take_redone_with_the_table_set_again(fake: Any, tmp_path: Path) -> None:
    world, unit = fake()
    session_table = bytes(frs.encode_table(0.0, 0.05, unit.serial))
    unit.stop_hang_s = 0.5  # stop() hangs after a stall (librealsense#7252)
    armed = [False]

    def stall(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 3 and not armed[0]:
            armed[0] = True
            unit.stall()

    s, messages, _ = run_take(world, unit, tmp_path, stall, table=session_table)
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]
    events = [e["event"] for e in s.data["capture"]["events"]]
    assert events == ["stalled", "stop_hung", "hardware_reset", "removed", "reenumerated",
                      "calibration_reapplied", "reconnected"]
    assert "hardware_reset" in world.names()
    assert bytes(unit.active_table()) == session_table  # the reset cleared RAM; the station set it again
    assert any("stalled" in m for m in messages)
    assert s.recordings()[0].frame_count == 8


def test_a_fast_replug_is_noticed_even_when_frames_resume(fake: Any, tmp_path: Path) -> None:
    """Replugged within a fraction of a second, the old pipeline delivers again: only the callback
    (and the frame counter starting over) says that RAM, preset and emitter were reset."""
    world, unit = fake()
    session_table = bytes(frs.encode_table(0.0, 0.05, unit.serial))
    armed = [False]

    def replug(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 3 and not armed[0]:
            armed[0] = True
            unit.unplug(0.05, resume=True)

    s, _, _ = run_take(world, unit, tmp_path, replug, table=session_table)
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]
    events = [e["event"] for e in s.data["capture"]["events"]]
    assert events[:2] in (["removed", "disconnected"], ["disconnected", "removed"])
    assert events[-2:] == ["calibration_reapplied", "reconnected"]
    assert bytes(unit.active_table()) == session_table
    sets = [c for c in world.calls if c[0] == "set_option"]
    assert [(v["option"], v["value"], v["streams"]) for _, v in sets[-2:]] == [
        ("visual_preset", 1.0, PROTO_PROFILE), ("emitter_enabled", 1.0, PROTO_PROFILE)]


def test_a_camera_back_on_usb2_is_told_to_move_and_waited_for(fake: Any, tmp_path: Path) -> None:
    world, unit = fake()
    armed = [False, False]

    def replug(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 3 and not armed[0]:
            armed[0] = True
            unit.unplug(0.05, usb="2.1")
        if "USB 2.1" in st.message and not armed[1]:
            armed[1] = True
            unit.unplug(0.05, usb="3.2")  # the operator moves it to a USB 3 port

    s, messages, _ = run_take(world, unit, tmp_path, replug)
    hint = [m for m in messages if "USB 2.1" in m]
    assert hint and "offers no depth 640x360 z16 at 30 fps" in hint[0]
    assert "connect it to a USB 3 port" in hint[0]
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]


def test_the_session_streams_from_warmup_through_calibration_into_capture(fake: Any, tmp_path: Path) -> None:
    """Warm-up, calibration and capture through the station with a live camera: streaming never
    pauses except to switch into and out of the calibration mode."""
    from depthstation.acquire.station import Station, do_calibrate, do_capture, do_warmup
    from depthstation.core.rerun_bridge import RerunTarget

    world, unit = fake()
    proto = tmp_path / "p.toml"
    proto.write_text('name = "p"\n[board]\ntype = "checkerboard"\nsquares_x = 7\nsquares_y = 5\n'
                     'square_length_m = 0.095\n[streams]\nwidth = 640\nheight = 360\nfps = 30\n'
                     '[plan]\nframes_per_standpoint = 4\n'
                     'start_distance_m = 1.0\nstep_m = 0.2\nmax_distance_m = 1.0\ninclinations_deg = [0.0]\n'
                     '[tolerances]\nstill_seconds = 0.2\n[warmup]\nmin_minutes = 0.01\nmax_minutes = 0.02\n'
                     'window_minutes = 0.01\n'
                     '[calibration]\non_chip = true\n[device]\nmodel = "D455"\n')
    unit.scene = board_scene(Board(), 1.0)
    st = Station("live", str(proto), tmp_path / "s", False, 0, False)
    off = RerunTarget(None, False, False)
    do_warmup(st, 0.2, 100.0, off)
    assert unit.streaming()
    cal = do_calibrate(st, True, write=False)
    assert cal["applied_to"] == "ram" and unit.streaming()
    do_capture(st, off, 20.0)
    st.close()
    calls = [k for k, _ in world.calls if k in ("pipeline.start", "pipeline.stop")]
    # every stop but the last is followed at once by a start: the device never idles
    assert calls[0] == "pipeline.start" and calls[-1] == "pipeline.stop"
    assert all(b == "pipeline.start" for a, b in itertools.pairwise(calls) if a == "pipeline.stop")
    assert starts(world) == [PROTO_PROFILE, CAL_PROFILE, PROTO_PROFILE]
    data = Session.open(tmp_path / "s").data
    assert data["standpoints"][0]["status"] == "complete"


@pytest.mark.hardware
def test_a_real_d455_behaves_as_the_double_assumes() -> None:
    """On a real camera: what the double copies (identity, the calibration mode on USB 3, whole
    degrees only while streaming, the firmware frame counter) holds for this unit and SDK."""
    import pyrealsense2 as rs

    cam = LiveCamera(model="D455")
    info = cam.start(PROTO_STREAMS)
    try:
        ident = cam.device_info()
        assert ident["model"] == "D455" and ident["product_id"] == "0B5C"
        fs = cam.wait_for_frames(5.0)
        temps = cam.temperatures()
        assert temps and all(v == int(v) for v in temps.values())
        assert fs.metadata["frame_counter"] in ("device", "host") and info.depth_units_m > 0
        # the double's assumptions: host-epoch stamps, counted drops, the options it pins and records
        assert fs.metadata["timestamp_domain"].split()[0] in ("global_time", "system_time", "hardware_clock")
        assert abs(fs.timestamp_ns - time.time_ns()) < 5e9
        assert fs.metadata["host_frames_dropped_before"] is not None
        assert info.device["options"].get("emitter_on_off", 0.0) == 0.0
        assert info.device["firmware_check"]["firmware"]
        dev = rs.context().query_devices()[0]
        if ident["usb_type_descriptor"].startswith("3."):
            assert ("depth", 256, 144, "z16", 90) in cam._offered(dev)
        # a D455 has a motion module: its profiles are not video profiles
        profiles = [p for s in dev.query_sensors() for p in s.get_stream_profiles()]
        assert any(not p.is_video_stream_profile() for p in profiles)
    finally:
        cam.stop()
    with pytest.raises(RuntimeError, match="streaming"):
        rs.context().query_devices()[0].first_depth_sensor().get_option(rs.option.asic_temperature)
