"""The live path against the double's dynamics (tests/fake_realsense.py): a re-enumeration that
takes a while and throws from device creation and option calls meanwhile, several cameras, and
the recoveries of the warm-up and the calibration. Each test names what the device does."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import itertools

import fake_realsense as frs
import test_acquire_live
from test_acquire_live import camera, run_take

from depthstation.acquire.guided_capture import LiveState
from depthstation.core.device import CameraUnsuitable
from depthstation.core.protocol import Streams

PROTO_STREAMS = Streams(width=640, height=360, fps=30)
fake = test_acquire_live.fake  # the fixture that injects the double, one definition for both files




@pytest.mark.parametrize("fault", ["unplug", "stall"])
def test_a_reenumeration_that_throws_meanwhile_is_waited_out(fake: Any, tmp_path: Path, fault: str) -> None:
    """While the device comes back its interfaces enumerate one by one: creating it from the list
    and its option calls throw RuntimeError, and it leaves and arrives again twice. The take is
    redone after it settles; no RuntimeError leaves the capture (it ended the session as an
    internal error)."""
    world, unit = fake(enumerate_s=0.4, flaps=2)
    armed = [False]

    def hook(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 3 and not armed[0]:
            armed[0] = True
            if fault == "unplug":
                unit.unplug(0.05)
            else:
                unit.stall()

    s, _, _ = run_take(world, unit, tmp_path, hook)
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]
    names = world.names()
    assert "create_device_failed" in names  # the live path met the throwing creation
    assert names.count("added") >= 3  # and the extra arrivals
    assert s.data["capture"]["events"][-1]["event"] == "reconnected"


def test_device_creation_that_throws_is_waited_out_or_a_camera_error(fake: Any) -> None:
    """A start while the device is listed but still enumerating waits for it (a --resume right
    after a replug failed); one that outlasts the wait is a CameraError (retried by the capture),
    never a RuntimeError."""
    from depthstation.core.errors import CameraError

    world, unit = fake(enumerate_s=0.5)
    world._remove(unit)
    world._add(unit)
    with pytest.raises(CameraError, match="still enumerating"):
        camera(enumeration_timeout_s=0.1).start(PROTO_STREAMS)
    assert "create_device_failed" in world.names()
    cam = camera()
    cam.start(PROTO_STREAMS)
    assert unit.streaming()
    cam.stop()


def test_several_cameras_without_a_serial_are_listed(monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = frs.FakeUnit(serial="111"), frs.FakeUnit(serial="222")
    world = frs.FakeRealSense(a, b)
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)
    with pytest.raises(CameraUnsuitable, match=r"serials 111, 222.*live:SERIAL"):
        camera().start(PROTO_STREAMS)
    cam = camera(serial="222")
    cam.start(PROTO_STREAMS)
    assert b.streaming() and not a.streaming()
    cam.stop()


def test_a_slow_consumer_drops_frames_on_the_host_counted_apart_from_the_devices(fake: Any,
                                                                                  tmp_path: Path) -> None:
    """Frames arrive in real time; a capture that takes ~3 frame periods per frame (board detection
    at 1280x720 costs about one) has the newer frames replace the ones it did not take. Those are
    host drops; the 3 frames the firmware counter skipped are the device's. Booked together, the
    device seemed to lose every frame the host was late for."""
    world, unit = fake()
    armed = [False]

    def slow(st: LiveState) -> None:
        if st.phase == "recording":
            if st.recorded == 2 and not armed[0]:
                armed[0] = True
                unit.inject(drop={"depth": 3})
            time.sleep(0.1)

    s, _, _ = run_take(world, unit, tmp_path, slow, frames=8)
    rec = s.recordings()[0]
    numbers = [f.index for f in rec.frames()]
    frames = rec.metadata["standpoint"]["frames"]
    assert frames["device_frames_lost"]["depth"] == 3
    host = frames["host_frames_dropped"]["depth"]
    assert host >= 8  # 7 gaps of ~2 frames each at 0.1 s per frame and 30 fps
    # every missing number is either the device's or the host's
    assert numbers[-1] - numbers[0] + 1 - len(numbers) == 3 + host


@pytest.mark.parametrize(("verdicts", "answers", "on_chip", "tare"), [
    (["fill", "ok", "ok"], None, "applied", "applied"),                # --yes: retried, then applied
    (["edges", "edges", "edges", "ok"], None, "skipped", "applied"),   # --yes: 2 retries, then skipped
    (["converge", "ok"], ["skip"], "skipped", "applied"),              # the operator skips it
    (["timeout", "ok", "ok"], ["retry"], "applied", "applied"),        # the operator re-aims, retries
])
def test_a_failed_self_calibration_is_retried_or_skipped_not_the_end(
        fake: Any, verdicts: list[str], answers: list[str] | None, on_chip: str, tare: str) -> None:
    """The firmware fails OCC or tare on a poor scene ("low fill factor", "edges too close", ...):
    the operator retries after re-aiming, skips (recorded with why) or aborts; --yes retries twice,
    then skips. One failure ended the session after an hour of warm-up."""
    from depthstation.acquire.calibrate import run_calibration
    from depthstation.core.protocol import Calibration

    _world, unit = fake(depth_bias=0.02, on_chip_health=0.5)
    unit.verdicts = list(verdicts)
    cam = camera()
    cam.start(PROTO_STREAMS)
    said: list[str] = []
    answer_list = list(answers or [])
    rec = run_calibration(cam, Calibration(on_chip=True, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: True, say=said.append, unattended=answers is None,
                          choose=None if answers is None else (lambda q: answer_list.pop(0)))
    steps = {s["kind"]: s for s in rec["steps"]}
    assert ("skipped" if steps["on_chip"].get("skipped") else "applied") == on_chip
    assert steps["tare"]["applied"] and tare == "applied"
    failures = [v for v in verdicts if v != "ok"]
    assert len(steps["on_chip"].get("failures", [])) == len(failures)
    assert all("\n" not in m for m in said)  # one line each
    assert unit.streaming()  # back in the protocol's mode
    cam.stop()


def test_abort_at_a_failed_calibration_is_one_line_and_resumable(fake: Any) -> None:
    from depthstation.acquire.calibrate import CalibrationAborted, run_calibration
    from depthstation.core.protocol import Calibration

    _world, unit = fake()
    unit.verdicts = ["fill"]
    cam = camera()
    cam.start(PROTO_STREAMS)
    with pytest.raises(CalibrationAborted, match=r"low fill factor.*--resume"):
        run_calibration(cam, Calibration(on_chip=True), confirm=lambda q: True, say=lambda m: None,
                        choose=lambda q: "abort")
    cam.stop()


SESSION_TOML = ('name = "p"\n[board]\ntype = "checkerboard"\nsquares_x = 7\nsquares_y = 5\n'
                'square_length_m = 0.095\n[streams]\nwidth = 640\nheight = 360\nfps = 30\n'
                '[plan]\nframes_per_standpoint = 4\nstart_distance_m = 1.0\nstep_m = 0.2\n'
                'max_distance_m = 1.0\n'
                'inclinations_deg = [0.0]\n[tolerances]\nstill_seconds = 0.2\n'
                '[warmup]\nmin_minutes = 0.01\nmax_minutes = 0.02\nwindow_minutes = 0.01\n'
                '[calibration]\non_chip = true\n[device]\nmodel = "D455"\n')


@pytest.mark.parametrize(("now_c", "cooled"), [(41.0, False), (37.0, True)])
def test_a_resume_warms_a_cooled_camera_up_again(fake: Any, tmp_path: Path, now_c: float,
                                                 cooled: bool) -> None:
    """A session stopped after its warm-up and resumed later: when the camera's temperature fell two
    whole degrees or more since the warm-up ended, the warm-up runs again and the earlier record
    moves to warmup_history with settled false (a resume skipped the warm-up, and session.json kept
    settled true for a cooled camera)."""
    from depthstation.acquire.station import Station, do_warmup, redo_warmup_if_cooled
    from depthstation.core.capture.session import Session
    from depthstation.core.rerun_bridge import RerunTarget

    temp = [41.0]
    fake(temperature=lambda t: temp[0])
    proto = tmp_path / "p.toml"
    proto.write_text(SESSION_TOML)
    st = Station("live", str(proto), tmp_path / "s", False, 0, False)
    do_warmup(st, 0.2, 100.0, RerunTarget(None, False, False))
    st.close()
    assert Session.open(tmp_path / "s").data["warmup"]["done"]
    temp[0] = now_c
    st = Station("live", None, tmp_path / "s", True, 0, False)
    assert redo_warmup_if_cooled(st) is cooled
    st.close()
    data = Session.open(tmp_path / "s").data
    if cooled:
        assert data["warmup"] is None  # `acquire session` runs it again
        old = data["warmup_history"][-1]
        assert old["settled"] is False and "fell 4 °C" in old["cooled"]
    else:
        assert data["warmup"]["done"] and "warmup_history" not in data


def test_a_warmup_recovers_from_a_stall_and_an_unplug(fake: Any, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """An hour-long warm-up meets stalls and unplugs as a capture does: the stall is reset, the
    unplugged camera waited for, and the warm-up goes on; both are recorded in its faults (one such
    fault ended the warm-up, and the session with it)."""
    from depthstation.acquire.live_camera import LiveCamera
    from depthstation.acquire.station import Station, do_warmup
    from depthstation.core.capture.session import Session
    from depthstation.core.rerun_bridge import RerunTarget

    _world, unit = fake(enumerate_s=0.2, flaps=1)
    proto = tmp_path / "p.toml"
    proto.write_text(SESSION_TOML.replace("max_minutes = 0.02", "max_minutes = 0.05"))
    real = LiveCamera.wait_for_frames
    calls = [0]

    def faulty(self: LiveCamera, timeout_s: float = 5.0) -> Any:
        calls[0] += 1
        if calls[0] == 2:
            unit.stall()
        if calls[0] == 4:
            unit.unplug(0.1)
        return real(self, min(timeout_s, 0.3))

    monkeypatch.setattr(LiveCamera, "wait_for_frames", faulty)
    st = Station("live", str(proto), tmp_path / "s", False, 0, False)
    st.camera.removal_timeout_s, st.camera.enumeration_timeout_s, st.camera.quiet_s = 2.0, 3.0, 0.05
    st.camera.stop_deadline_s = 0.2
    summary = do_warmup(st, 0.2, 100.0, RerunTarget(None, False, False))
    st.close()
    assert summary["done"]
    assert [f["event"] for f in summary["faults"]] == ["stalled", "disconnected"]
    assert "hardware_reset" in [e["event"] for e in summary["device_events"]]
    assert Session.open(tmp_path / "s").data["warmup"]["faults"] == summary["faults"]


@pytest.mark.parametrize("ram_on_stop", ["kept", "lost"])
def test_the_tare_runs_on_the_occ_table_whether_ram_outlives_a_stop_or_not(fake: Any,
                                                                           ram_on_stop: str) -> None:
    """OCC then tare: the tare's switch into the calibration mode stops the pipeline. Whether a
    RAM table survives `pipeline.stop()` is not documented; the session's table is set again after
    every start, so the tare starts from the OCC table (its health, 0.05 in the double) and the
    table active at the end is built on it, either way."""
    from depthstation.acquire.calibrate import run_calibration
    from depthstation.core.protocol import Calibration

    _world, unit = fake(depth_bias=0.02, on_chip_health=0.5, ram_on_stop=ram_on_stop)
    cam = camera()
    cam.start(PROTO_STREAMS)
    rec = run_calibration(cam, Calibration(on_chip=True, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: True, say=lambda m: None)
    assert [s["applied"] for s in rec["steps"]] == [True, True]
    active = frs.decode_table(unit.active_table())
    assert active["health"] == pytest.approx(0.05)  # built on the OCC table, not the flash one (0.5)
    assert abs(active["bias"]) < 0.001  # and the tare's correction is what streams now
    cam.stop()
    cam.start(PROTO_STREAMS)
    assert frs.decode_table(unit.active_table()) == active  # set again after the restart
    cam.stop()


@pytest.mark.parametrize(("unit_kw", "domain"), [
    ({}, "global_time"),
    ({"global_time": False}, "hardware_clock (time_of_arrival)"),
    ({"metadata": False}, "system_time"),
])
def test_each_timestamp_domain_gives_a_host_epoch_time(fake: Any, unit_kw: dict[str, Any],
                                                      domain: str) -> None:
    """global_time and system_time are host-epoch ms already; hardware_clock counts from the
    device's boot, so the frame's time of arrival at the host stands in (only global_time was used
    as such; system_time fell back to the read time)."""
    _world, _unit = fake(**unit_kw)
    cam = camera()
    cam.start(PROTO_STREAMS)
    frames = [cam.wait_for_frames(1.0) for _ in range(4)]
    cam.stop()
    now = time.time_ns()
    assert all(f.metadata["timestamp_domain"] == domain for f in frames)
    assert all(abs(now - f.timestamp_ns) < 5e9 for f in frames)  # the host's epoch, not the device's boot
    if "time_of_arrival" in domain:
        assert all(f.timestamp_ns == round(f.metadata["time_of_arrival"] * 1e6) for f in frames)
    steps = [b.timestamp_ns - a.timestamp_ns for a, b in itertools.pairwise(frames)]
    assert all(s > 0 for s in steps)


def test_settings_and_firmware_are_recorded_and_emitter_on_off_pinned(fake: Any, tmp_path: Path) -> None:
    """emitter_on_off left on by another program (it blanks every other frame's pattern) is pinned
    off; the options the depth was made with and the firmware against the thermal loop's minimum
    go into session.json; an old firmware is a warning. The motion module is there and offers no
    video profile the checks could mistake for one."""
    from depthstation.acquire.station import Station
    from depthstation.core.capture.session import Session
    from depthstation.core.run_warnings import collecting

    world, unit = fake(firmware="5.12.7.100")
    unit.options["emitter_on_off"] = 1.0
    proto = tmp_path / "p.toml"
    proto.write_text(SESSION_TOML)
    with collecting() as warned:
        st = Station("live", str(proto), tmp_path / "s", False, 0, False)
        st.close()
    assert unit.options["emitter_on_off"] == 0.0
    assert "emitter_on_off_pinned_off" in [e["event"] for e in st.camera.take_events()]
    run = Session.open(tmp_path / "s").data["camera_settings"][0]
    assert run["options"]["emitter_on_off"] == 0.0 and run["options"]["laser_power"] == 150.0
    assert run["firmware_check"]["thermal_loop_ok"] is False and run["usb"] == "3.2"
    assert any(w.code == "firmware-old" for w in warned)
    rs = world.module
    sensors = rs.context().query_devices()[0].query_sensors()
    assert any(not p.is_video_stream_profile() for p in sensors[-1].get_stream_profiles())


def test_partial_framesets_repeat_on_the_queue_and_are_counted_in_the_capture(fake: Any) -> None:
    """A stream's frame that the device lost: `wait_for_frames` gets the set filled with that
    stream's last frame (the aggregator's `_last_set`); the capture, fed by the callback, waits for
    the stream's next frame and books one device loss. Never the same colour frame twice."""
    world, unit = fake(real_time=True)
    unit.miss_p = 0.3
    rs = world.module
    cfg = rs.config()
    cfg.enable_stream(rs.stream.depth, 640, 360, rs.format.z16, 30)
    cfg.enable_stream(rs.stream.color, 640, 360, rs.format.rgb8, 30)
    pipe = rs.pipeline()
    pipe.start(cfg)
    colors = [pipe.wait_for_frames(1000).get_color_frame().get_frame_number() for _ in range(20)]
    pipe.stop()
    assert len(set(colors)) < len(colors)  # repeats on the queue
    unit.miss_p = 0.3
    cam = camera()
    cam.start(PROTO_STREAMS)
    sets = [cam.wait_for_frames(1.0) for _ in range(20)]
    cam.stop()
    numbers = [s.metadata["color_frame_number"] for s in sets]
    assert len(set(numbers)) == len(numbers)
    lost = sum(s.metadata["frames_lost_before"]["color"] for s in sets[1:])
    dropped = sum(s.metadata["host_frames_dropped_before"]["color"] for s in sets[1:])
    assert lost > 0 and numbers[-1] - numbers[0] + 1 - len(numbers) == lost + dropped


def test_a_stall_carried_into_the_calibration_mode_is_reset_and_the_calibration_run(fake: Any,
                                                                                      tmp_path: Path) -> None:
    """Frames that stopped at the end of the warm-up stay stopped in the calibration mode: the
    missing first frame there is a stall (reset, then the calibration runs), not the end of the
    session (found by benchmarks/chaos_sessions.py, seeds 86 and 122)."""
    from depthstation.acquire.station import Station, do_calibrate

    world, unit = fake()
    proto = tmp_path / "p.toml"
    proto.write_text(SESSION_TOML)
    st = Station("live", str(proto), tmp_path / "s", False, 0, False)
    st.camera.removal_timeout_s, st.camera.enumeration_timeout_s, st.camera.quiet_s = 2.0, 3.0, 0.05
    st.camera.stop_deadline_s, st.camera.first_frame_timeout_s = 0.2, 0.5
    unit.stall()
    rec = do_calibrate(st, True, write=False)
    st.close()
    assert not rec["skipped"] and rec["steps"][0]["kind"] == "on_chip"
    assert "hardware_reset" in world.names()
