"""`acquire` sessions over several runs: one rerun recording per run, resumes that keep to the session's
camera, plan and files, and starts that fail before leaving a session behind (simulated camera, small
frames, accelerated warm-up)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from test_acquire_cli import SMALL_TOML

from depthstation.app.cli import run_cli
from depthstation.core.capture.rs_writer import write_realsense_recording
from depthstation.core.capture.session import Session
from depthstation.core.protocol import Streams
from depthstation.core.run_warnings import collecting
from depthstation.simulate.simulated_camera import SimulatedCamera

TINY_TOML = (SMALL_TOML.replace("{frames}", "3").replace("step_m = 0.5", "step_m = 0.8")
             .replace("max_distance_m = 1.5", "max_distance_m = 1.8")
             .replace("min_minutes = 1.0", "min_minutes = 0.5")
             .replace("max_minutes = 5.0", "max_minutes = 1.0"))

CAP = ["--yes", "--max-guidance", "60"]
FAST = [*CAP, "--accelerate", "1000", "--interval", "15"]


def acq(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """Run `depthstation acquire ...` in-process: exit code and stderr."""
    capsys.readouterr()
    code = run_cli(["acquire", *args])
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tiny")
    (root / "tiny.toml").write_text(TINY_TOML)
    return root / "tiny.toml"


@pytest.fixture(scope="module")
def done_session(tmp_path_factory: pytest.TempPathFactory, tiny: Path) -> Path:
    """A finished two-standpoint session, recorded once with --rrd (copied by the tests that change it)."""
    root = tmp_path_factory.mktemp("done")
    code = run_cli(["acquire", "session", "--camera", "sim:d455-ideal", "--protocol", str(tiny), "--session",
                    str(root / "s"), "--rrd", str(root / "live.rrd"), *FAST])
    assert code == 0
    return root / "s"


def depth_only_recording(path: Path) -> Path:
    """A RealSense recording of 3 depth frames and no colour stream."""
    cam = SimulatedCamera("d455-ideal")
    info = cam.start(Streams(width=640, height=360, color=False))
    frames = [cam.wait_for_frames() for _ in range(3)]
    write_realsense_recording(path, info, frames)
    return path


def copy(session: Path, tmp: Path) -> Path:
    dst = tmp / "s"
    shutil.copytree(session, dst)
    return dst


def test_session_run_writes_one_recording_and_a_resume_writes_beside_it(
        done_session: Path, tmp_path: Path, tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rrd = done_session.parent / "live.rrd"
    assert rrd.is_file() and rrd.read_bytes()[:3] == b"RRF"  # warm-up and capture: one run, one file
    data = json.loads((done_session / "session.json").read_text())
    assert [e["status"] for e in data["standpoints"]] == ["complete", "complete"]
    before = rrd.read_bytes()
    s = copy(done_session, tmp_path)
    code, err = acq(capsys, "session", "--camera", "sim:d455-ideal", "--session", str(s), "--resume",
                    "--rrd", str(rrd),
                    *FAST)
    assert code == 0, err
    assert rrd.read_bytes() == before  # the earlier run's recording is kept
    assert (rrd.parent / "live.resume-1.rrd").is_file()
    # a new session never overwrites an existing --rrd, and the message offers no --force acquire lacks
    code, err = acq(capsys, "session", "--camera", "sim:d455-ideal", "--protocol", str(tiny), "--session",
                    str(tmp_path / "new"), "--rrd", str(rrd), *FAST)
    assert code == 2 and "live.rrd: exists" in err and "--force" not in err
    assert not (tmp_path / "new").exists()


def test_resume_refuses_another_camera(done_session: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    s = copy(done_session, tmp_path)
    before = (s / "session.json").read_text()
    code, err = acq(capsys, "capture", "--camera", "sim:d435-ideal", "--session", str(s), "--resume", *CAP)
    assert code == 2, err
    assert str(s) in err and "D455" in err and "D435" in err and "baseline_m" in err
    assert json.loads((s / "session.json").read_text())["standpoints"] == json.loads(before)["standpoints"]


def test_resume_adopts_only_the_plans_files_of_its_camera(done_session: Path, tmp_path: Path) -> None:
    """A finished MCAP that session.json does not list is adopted only when its name is a standpoint of
    the plan and the session's camera recorded it; others are left alone with a warning."""
    s = copy(done_session, tmp_path)

    def unlist_second(serial: str) -> None:
        data = json.loads((s / "session.json").read_text())
        data["standpoints"] = data["standpoints"][:1]  # as if the run died before saying it
        data["camera_identity"]["serial_number"] = serial
        (s / "session.json").write_text(json.dumps(data))

    shutil.copy(s / "standpoint_01.mcap", s / "stray.mcap")
    unlist_second("213622070001")
    with collecting() as found:
        sess = Session.open(s)
    assert [e["file"] for e in sess.standpoints] == ["standpoint_01.mcap", "standpoint_02.mcap"]
    assert [(w.code, "stray.mcap" in w.message) for w in found] == [("foreign-recording", True)]
    unlist_second("another")  # the session says another camera: standpoint_02.mcap is not its own
    with collecting() as found:
        sess = Session.open(s)
    assert [e["file"] for e in sess.standpoints] == ["standpoint_01.mcap"]
    assert any("standpoint_02.mcap" in w.message and "another camera" in w.message for w in found)
    assert (s / "stray.mcap").is_file() and (s / "standpoint_02.mcap").is_file()


def test_resume_records_again_a_missing_or_cut_standpoint(done_session: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    s = copy(done_session, tmp_path)
    (s / "standpoint_01.mcap").unlink()
    cut = (s / "standpoint_02.mcap").read_bytes()
    (s / "standpoint_02.mcap").write_bytes(cut[: len(cut) // 2])
    code, err = acq(capsys, "capture", "--camera", "sim:d455-ideal", "--session", str(s), "--resume", *CAP)
    assert code == 0, err
    assert "standpoint_01.mcap is missing" in err and "standpoint_02.mcap is damaged" in err
    data = json.loads((s / "session.json").read_text())
    done = [e["name"] for e in data["standpoints"] if e["status"] == "complete"]
    assert sorted(done) == ["standpoint_01", "standpoint_02"]
    aside = [e["file"] for e in data["standpoints"]
             if e["status"] == "discarded" and e["name"] == "standpoint_02"]
    assert aside and (s / aside[0]).read_bytes() == cut[: len(cut) // 2]  # the damaged file kept aside


def test_resume_uses_the_stored_protocol_and_refuses_another_plan(
        done_session: Path, tmp_path: Path, tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s = copy(done_session, tmp_path)
    code, err = acq(capsys, "capture", "--camera", "sim:d455-ideal", "--session", str(s), "--resume",
                    "--protocol",
                    str(tiny), *CAP)
    assert code == 0 and "protocol stored in session.json" in err
    other = tmp_path / "four.toml"
    other.write_text(TINY_TOML.replace("max_distance_m = 1.8", "max_distance_m = 3.4"))
    code, err = acq(capsys, "capture", "--camera", "sim:d455-ideal", "--session", str(s), "--resume",
                    "--protocol",
                    str(other), *CAP)
    assert code == 2 and "four.toml" in err and "(4)" in err and "(2)" in err
    assert "leave --protocol out" in err


@pytest.mark.parametrize("args", [["--camera", "sim:d999"], ["--seed", "-1"], ["--camera", "live"],
                                  ["--camera", "NOCOLOR"]])
def test_a_failed_start_leaves_no_session(args: list[str], tmp_path: Path, tiny: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The camera is opened and started (and the options checked) before the session is made: the
    corrected command then just works."""
    if "NOCOLOR" in args:
        from test_acquire_cli import make_recording

        rec = make_recording(tmp_path / "rec.db3", n=3)
        proto = tmp_path / "color.toml"  # the recording has colour: ask for infrared it lacks instead
        proto.write_text(TINY_TOML.replace("fps = 30", "fps = 30\\ninfrared = true"))
        args, protocol = ["--camera", str(rec)], proto
    else:
        protocol = tiny
    s = tmp_path / "s"
    code, err = acq(capsys, "capture", *args, "--protocol", str(protocol), "--session", str(s), *CAP)
    assert code == 2 if args != ["--camera", "live"] else code in (1, 2), err
    assert "internal error" not in err and "Traceback" not in err and "Usage" not in err
    assert not (s / "session.json").exists()


@pytest.mark.parametrize("args", [
    ["warmup", "--accelerate", "-10"], ["warmup", "--accelerate", "nan"], ["warmup", "--interval", "-5"],
    ["warmup", "--interval", "nan"], ["warmup", "--interval", "1e9", "--accelerate", "1000"],
    ["capture", "--max-guidance", "-1"], ["capture", "--max-guidance", "nan"],
    ["warmup", "--camera", "REC", "--accelerate", "10"], ["capture", "--session", "FILE"],
])
def test_bad_option_values_are_refused_before_any_work(args: list[str], tmp_path: Path, tiny: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    if "REC" in args:
        from test_acquire_cli import make_recording

        args[args.index("REC")] = str(make_recording(tmp_path / "rec.db3", n=3))
    (tmp_path / "afile").write_text("x")
    args = [str(tmp_path / "afile") if a == "FILE" else a for a in args]
    code, err = acq(capsys, *args, "--protocol", str(tiny), *(["--session", str(tmp_path / "s")]
                                                             if "--session" not in args else []))
    assert code == 2, err
    assert err.startswith("depthstation: error: ") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_warmup_that_never_settles_is_a_warning(tmp_path: Path, tiny: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """The simulated projector still climbs ~2 °C/min at the protocol's 1-min maximum (tolerance 0.1)."""
    s = tmp_path / "s"
    code, err = acq(capsys, "warmup", "--camera", "sim:d455-ideal", "--protocol", str(tiny),
                    "--session", str(s),
                    "--accelerate", "1000", "--interval", "15", "--strict")
    assert code == 3, err
    assert "warm-up ended without the temperature settling" in err
    w = json.loads((s / "session.json").read_text())["warmup"]
    assert w["settled"] is False and w["final_slope_c_per_min"] > 0.1


def test_every_study_of_an_unsettled_session_says_so(tmp_path: Path) -> None:
    """The warm-up's warning was printed once, at acquisition; the session keeps `settled`, and
    reading its standpoints for a study (checkerboard, explain, compare of its results) says it again."""
    s = Session.create(tmp_path / "s", device={"name": "sim"})
    s.set("warmup", {"has_temperature": True, "settled": False, "final_slope_c_per_min": 1.4,
                     "reason": "maximum time of 1 min reached"})
    with collecting() as found:
        s.recordings()
    assert [w.code for w in found] == ["warmup-unsettled"] and "+1.400" in found[0].message
    s.set("warmup", {"has_temperature": True, "settled": True, "final_slope_c_per_min": 0.01})
    with collecting() as found:
        s.recordings()
    assert found == []
    s.set("warmup", {"has_temperature": False, "settled": False})  # no sensor: the time rule, no word
    with collecting() as found:
        s.recordings()
    assert found == []


def test_a_recording_that_does_not_fit_the_protocol_is_said(tmp_path: Path, tiny: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A D435 recording of another size played for a D455 protocol was captured without a word (a
    live camera refuses such a profile; a recording can only be taken as it is)."""
    from dataclasses import replace

    from depthstation.core.capture.sample_recordings import sample_frames, sample_info

    info = replace(sample_info(64, 48), device={"name": "Intel RealSense D435"})
    rec = tmp_path / "d435.db3"
    write_realsense_recording(rec, info, list(sample_frames(info, 3, seed=2)))
    code, err = acq(capsys, "capture", "--camera", str(rec), "--protocol", str(tiny), "--session",
                    str(tmp_path / "c"), "--strict")
    assert code == 3, err
    assert "does not fit the protocol" in err and "depth 64x48, the protocol asks 640x360" in err
    assert "recorded by Intel RealSense D435, the protocol is for a D455" in err


def test_a_board_of_another_size_than_the_protocol_is_said_at_capture(
        tmp_path: Path, tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 95 mm print under a protocol saying 50 mm: guidance took the board for 0.53 m away (the pose
    scales with the square length) where depth read 1.0 m, and recorded it without a word."""
    from test_acquire_cli import make_recording

    rec = make_recording(tmp_path / "rec.db3", n=40)  # the default 95 mm board at 1.0 m
    proto = tmp_path / "p50.toml"
    proto.write_text(TINY_TOML.replace("square_length_m = 0.095", "square_length_m = 0.050")
                     .replace("start_distance_m = 1.0", "start_distance_m = 0.53")
                     .replace("max_distance_m = 1.8", "max_distance_m = 0.6"))
    code, err = acq(capsys, "capture", "--camera", str(rec), "--protocol", str(proto), "--session",
                    str(tmp_path / "s"), "--strict")
    assert code == 3, err
    assert "depth reads 1.90x the distance its pose gives" in err and "implies 0.0950 m" in err
    (entry,) = json.loads((tmp_path / "s" / "session.json").read_text())["standpoints"]
    assert entry["status"] == "complete"  # recorded: the warning says which distance is which
    code, err = acq(capsys, "capture", "--camera", str(rec), "--protocol", str(tiny), "--session",
                    str(tmp_path / "right"), "--strict")
    assert "board-scale" not in err and "depth reads" not in err, err  # the right board: no word


def test_recordings_that_end_too_soon_are_said(tmp_path: Path, tiny: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    from test_acquire_cli import make_recording

    rec = make_recording(tmp_path / "rec.db3", n=3)
    code, err = acq(capsys, "warmup", "--camera", str(rec), "--protocol", str(tiny), "--session",
                    str(tmp_path / "w"), "--interval", "0.01")
    assert code == 2 and f"{rec}: the recording ended before the warm-up's minimum time" in err
    code, err = acq(capsys, "capture", "--camera", str(rec), "--protocol", str(tiny), "--session",
                    str(tmp_path / "c"), "--strict")
    assert code == 3 and "ended before any standpoint was recorded" in err


def test_calibrating_a_captured_session_keeps_the_earlier_table(done_session: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """`acquire calibrate --resume` after the standpoints replaced the session's calibration record
    without a word; the earlier one now goes to calibration_history with the standpoints taken under it."""
    s = tmp_path / "s"
    shutil.copytree(done_session, s)
    before = json.loads((s / "session.json").read_text())["calibration"]
    assert before.get("table_after_b64")
    code, err = acq(capsys, "calibrate", "--camera", "sim:d455-ideal", "--session", str(s), "--resume",
                    "--yes",
                    "--seed", "5", "--strict")
    data = json.loads((s / "session.json").read_text())
    assert data["calibration"]["table_after_b64"] != before["table_after_b64"]  # a new table
    assert code == 3 and "calibration changed after 2 standpoint(s)" in err, err
    (old,) = data["calibration_history"]
    assert old["table_after_b64"] == before["table_after_b64"]
    assert old["standpoints"] == ["standpoint_01", "standpoint_02"]


def test_a_session_that_stores_no_protocol_resumes_only_with_one_given(
        done_session: Path, tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An imported session stores no protocol: a resume without --protocol ran the default one
    (1280x720, 150 frames) beside its 640x360 standpoints, without a word and storing nothing."""
    imported = tmp_path / "imp"
    assert run_cli(["capture", "import", str(done_session), "--out", str(imported)]) == 0
    assert json.loads((imported / "session.json").read_text())["protocol"] is None
    code, err = acq(capsys, "capture", "--camera", "sim:d455-ideal", "--session", str(imported),
                    "--resume", *CAP)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert str(imported / "session.json") in err and "--protocol" in err
    # a resume refused later (a recording without the colour the protocol asks) stores nothing
    no_colour = depth_only_recording(tmp_path / "depth.db3")
    code, err = acq(capsys, "capture", "--camera", str(no_colour), "--session", str(imported), "--resume",
                    "--protocol", str(tiny), *CAP)
    assert code == 2, err
    assert json.loads((imported / "session.json").read_text())["protocol"] is None
    code, err = acq(capsys, "capture", "--camera", "sim:d455-ideal", "--session", str(imported), "--resume",
                    "--protocol", str(tiny), *CAP)
    assert code == 0, err
    assert json.loads((imported / "session.json").read_text())["protocol"]["name"] == "small"
