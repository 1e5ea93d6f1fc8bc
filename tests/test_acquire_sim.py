"""A full guided session with the simulated D455 and the simulated operator (tremor + overshoot):
accelerated warm-up ends by the rule, calibration runs, every standpoint is reached within the
tolerances; a disconnect mid-standpoint is re-done; recording at real-time rate drops no frame."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_acquire_cli import EXE, SMALL_TOML

SIM_TOML = (SMALL_TOML.replace("max_distance_m = 1.5", "max_distance_m = 1.6")
            .replace("width = 640\nheight = 360", "width = 424\nheight = 240")  # a D455 mode
            .replace("step_m = 0.5", "step_m = 0.6")
            .replace("inclinations_deg = [0.0]", "inclinations_deg = [0.0, 30.0]")
            .replace("min_minutes = 1.0", "min_minutes = 10.0")
            .replace("window_minutes = 0.5", "window_minutes = 2.0")
            .replace("max_minutes = 5.0", "max_minutes = 90.0")
            .replace("[calibration]\non_chip = true",
                     "[calibration]\non_chip = true\ntare = true\ntare_distance_m = 1.0"))


def test_guided_session_with_simulated_operator(tmp_path: Path) -> None:
    from depthstation.core.capture.session import Session
    from depthstation.core.protocol import load_protocol

    proto_path = tmp_path / "sim.toml"
    proto_path.write_text(SIM_TOML.replace("{frames}", "5"))
    proto = load_protocol(proto_path)
    sess = tmp_path / "session"
    r = subprocess.run([EXE, "acquire", "session", "--camera", "sim:d455-ideal",
                        "--protocol", str(proto_path),
                        "--session", str(sess), "--yes", "--accelerate", "400", "--interval", "15",
                        "--max-guidance", "90", "--seed", "2"], capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((sess / "session.json").read_text())
    # warm-up ends by the slope rule: the simulated projector heats from 25 to 44 degrees C with a
    # 432 s time constant, so its slope (19 / 432 * 60 * exp(-t / 432) C/min) falls below 0.1 C/min at
    # t = 432 ln(26.4) = 1414 s; the 2-min least-squares window lags by about half its length
    w = data["warmup"]
    assert w["done"] and w["has_temperature"] and "settled" in w["reason"]
    assert abs(w["final_slope_c_per_min"]) <= 0.1
    assert w["elapsed_s"] == pytest.approx(432 * np.log(19 / 432 * 60 / 0.1) + 60, abs=120)
    cal = data["calibration"]
    assert not cal["skipped"] and [s["kind"] for s in cal["steps"]] == ["on_chip", "tare"]
    assert cal["changed"]  # --yes applied the new tables
    s = Session.open(sess)
    plan = proto.plan.standpoints()
    assert [e["name"] for e in s.standpoints if e["status"] == "complete"] == [sp.name for sp in plan]
    truth_tol = proto.tolerances
    for rec, sp in zip(s.recordings(), plan, strict=True):
        assert rec.frame_count == 5
        meas = rec.metadata["standpoint"]["measured"]
        assert abs(meas["distance_m"] - sp.distance_m) <= truth_tol.distance_m
        assert abs(meas["inclination_deg"] - sp.inclination_deg) <= truth_tol.inclination_deg
        assert rec.metadata["standpoint"]["target"]["distance_m"] == sp.distance_m


def test_simulated_disconnect_is_reported_and_redone(tmp_path: Path) -> None:
    from depthstation.acquire.guided_capture import GuidedCapture
    from depthstation.core.capture.session import Session
    from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances
    from depthstation.simulate.operator import SimulatedOperator, Stance
    from depthstation.simulate.simulated_camera import SimulatedCamera

    proto = Protocol("one", streams=Streams(width=640, height=360),
                     plan=Plan(frames_per_standpoint=8, start_distance_m=1.2, max_distance_m=1.2,
                               inclinations_deg=(0.0,)),
                     tolerances=Tolerances(still_seconds=0.3))
    # in place from the start: ~10 frames to be still, then 8 to record; unplug on frame 14
    cam = SimulatedCamera("d455-ideal", board=proto.board, disconnect_after_frames=14, failed_reconnects=2)
    op = SimulatedOperator(proto.board, Stance(range_m=1.2), seed=0)
    cam.set_pose(op.pose(0.0))
    states: list[str] = []
    session = Session.create(tmp_path / "s", protocol=proto)
    cap = GuidedCapture(cam, proto, session, on_state=lambda st: states.append(st.message),
                        max_guidance_s=30, sleep=lambda s: None)
    out = cap.run()
    assert [o.status for o in out] == ["complete"]
    assert any("disconnected" in m for m in states)
    s = Session.open(tmp_path / "s")
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]
    ev = [e for e in s.data["capture"]["events"] if e["event"] in ("disconnected", "reconnected")]
    assert [e["event"] for e in ev] == ["disconnected", "reconnected"] and ev[0]["frames_recorded"] > 0
    assert s.recordings()[0].frame_count == 8


def test_no_dropped_frame_at_real_time(tmp_path: Path) -> None:
    """Small frames here (benchmarks/bench_acquire.py does 1280x720): frame numbers contiguous."""
    from depthstation.acquire.guided_capture import GuidedCapture
    from depthstation.core.capture.session import Session
    from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances
    from depthstation.simulate.poses import standpoint_pose
    from depthstation.simulate.simulated_camera import SimulatedCamera

    proto = Protocol("rt", streams=Streams(width=424, height=240, fps=30),
                     plan=Plan(frames_per_standpoint=45, start_distance_m=0.8, max_distance_m=0.8,
                               inclinations_deg=(0.0,)),
                     tolerances=Tolerances(still_seconds=0.2))
    cam = SimulatedCamera("d455-ideal", board=proto.board, real_time=True,
                          pose=standpoint_pose(proto.board, 0.8, 0.0))
    session = Session.create(tmp_path / "s", protocol=proto)
    GuidedCapture(cam, proto, session, max_guidance_s=10).run()
    s = Session.open(tmp_path / "s")
    e = s.standpoints[0]
    assert e["status"] == "complete" and e["dropped_frames"] == 0
    idx = np.array([f.index for f in s.recordings()[0].frames()])
    assert idx.size == 45 and np.all(np.diff(idx) == 1)


@pytest.mark.hardware
def test_live_session_smoke(tmp_path: Path) -> None:
    """On-chip (no), the tare target's distance from the glass (the protocol's), tare (no); a camera
    with advanced mode off is asked first whether to enable it (no: the run stops in one line)."""
    r = subprocess.run([EXE, "acquire", "calibrate", "--camera", "live", "--protocol", "demo-d455",
                        "--session", str(tmp_path / "s")], input="n\n\nn\n", capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    cal = json.loads((tmp_path / "s" / "session.json").read_text())["calibration"]
    assert [s["kind"] for s in cal["steps"]] == ["on_chip", "tare"] and not cal["changed"]
