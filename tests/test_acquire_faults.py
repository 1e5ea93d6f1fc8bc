"""Faults lose nothing: SIGKILL mid-standpoint (finished ones readable, --resume re-records only the
broken one) and Ctrl-C (SIGINT closes the open MCAP properly), in a real subprocess."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from depthstation.core.capture.mcap_writer import FRAME_TOPIC

sys.path.insert(0, str(Path(__file__).parent))
from test_acquire_cli import EXE, SMALL_TOML, make_recording

# two standpoints the recorded pose satisfies (1.0 m at 0 and at 1 degree, tolerance 3 degrees)
TWO_HERE = SMALL_TOML.replace("max_distance_m = 1.5", "max_distance_m = 1.0").replace(
    "inclinations_deg = [0.0]", "inclinations_deg = [0.0, 1.0]")


def _default_sigint() -> None:
    """In the child: Ctrl-C as a shell gives it (a child inherits an ignored SIGINT, and Python then
    leaves it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(rec: Path, proto: Path, sess: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([EXE, "acquire", "capture", "--camera", str(rec), "--protocol", str(proto),
                             "--session", str(sess), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)


def wait_for(path: Path, proc: subprocess.Popen[str], timeout: float = 120.0,
             ready: Callable[[Path], bool] = Path.exists) -> None:
    """Poll until `ready(path)`; a generous timeout, as a loaded machine may be slow to get there."""
    t_end = time.monotonic() + timeout
    while not ready(path):
        if proc.poll() is not None:
            raise AssertionError(f"exited early: {proc.stderr.read() if proc.stderr else ''}")
        if time.monotonic() > t_end:
            proc.kill()
            raise AssertionError(f"{path.name} never became ready")
        time.sleep(0.01)


def holds_a_frame(path: Path) -> bool:
    """Whether the growing MCAP holds a whole frame record on disk (in a finished chunk): read with
    mcap's own stream reader, the record being written (cut short) ends the reading."""
    if not path.exists():
        return False
    with path.open("rb") as f:
        try:
            topics: dict[int, str] = {}
            for r in StreamReader(f, record_size_limit=None).records:
                if isinstance(r, Channel):
                    topics[r.id] = r.topic
                elif isinstance(r, Message) and topics.get(r.channel_id) == FRAME_TOPIC:
                    return True
        except Exception:  # mcap raises several kinds on a file cut short
            pass
    return False


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_recording(tmp_path_factory.mktemp("rec") / "board.db3", n=240)


def test_sigkill_then_resume_rerecords_only_the_broken_standpoint(recording: Path, tmp_path: Path) -> None:
    from depthstation.core.capture.registry import open_recording

    proto = tmp_path / "two.toml"
    proto.write_text(TWO_HERE.replace("frames_per_standpoint = {frames}", "frames_per_standpoint = 80"))
    sess = tmp_path / "s"
    proc = start(recording, proto, sess)
    wait_for(sess / "standpoint_02.mcap.partial", proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    first = sess / "standpoint_01.mcap"
    assert first.is_file()
    mtime = first.stat().st_mtime_ns
    assert open_recording(first).frame_count == 80  # the finished standpoint is readable
    r = subprocess.run([EXE, "acquire", "capture", "--camera", str(recording), "--protocol", str(proto),
                        "--session", str(sess), "--resume"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    data = json.loads((sess / "session.json").read_text())
    status = [(e["name"], e["status"]) for e in data["standpoints"]]
    assert status == [("standpoint_01", "complete"), ("standpoint_02", "partial"),
                      ("standpoint_02", "complete")]
    assert first.stat().st_mtime_ns == mtime  # untouched
    assert open_recording(sess / "standpoint_02.mcap").frame_count == 80
    # the broken attempt is kept aside, never deleted
    assert list(sess.glob("standpoint_02.attempt-*.mcap.partial"))


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """600 frames: a 400-frame standpoint after the guidance's frames. Why: the 8 s recording played
    at its frame rate was used up by the guidance in a fresh checkout (kernels compiled on first
    use), and the recording ended before the Ctrl-C (exit 0)."""
    return make_recording(tmp_path_factory.mktemp("long") / "board.db3", n=600)


def test_sigint_finalises_the_open_file(long_recording: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    proto = tmp_path / "one.toml"
    proto.write_text(TWO_HERE.replace("frames_per_standpoint = {frames}", "frames_per_standpoint = 400"))
    sess = tmp_path / "s"
    # not paced at the frame rate: paced playback that falls behind (kernels compiled in a fresh
    # checkout, a loaded machine) skips ahead by the clock and could end the recording before the
    # Ctrl-C; unpaced, the recording is read as fast as it is processed. The Ctrl-C goes once the
    # file holds a frame on disk (the first chunk, a few frames in): mid-standpoint, whatever the
    # load, with frames for the finished file to keep (not after a fixed sleep)
    proc = start(long_recording, proto, sess)
    partial = sess / "standpoint_01.mcap.partial"
    wait_for(partial, proc, ready=holds_a_frame)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    err = proc.stderr.read() if proc.stderr else ""
    assert proc.returncode == 130, err
    assert "interrupted" in err and "--resume" in err
    with partial.open("rb") as f:
        summary = make_reader(f).get_summary()  # a finished MCAP has its summary section
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count > 0
    data = json.loads((sess / "session.json").read_text())
    assert data["standpoints"][0]["status"] == "partial" and data["standpoints"][0]["frames"] > 0


def test_ctrl_c_while_a_standpoint_is_being_closed_still_finishes_it(tmp_path: Path) -> None:
    """A Ctrl-C that lands while the writer drains and finishes the file is held back until the
    MCAP is complete, then raised: the standpoint stays readable."""
    import os
    import threading

    from depthstation.core.camera_model import Intrinsics, StreamInfo
    from depthstation.core.capture.registry import open_recording
    from depthstation.core.capture.session import Session
    from depthstation.core.frames import FrameSet

    info = StreamInfo(Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5), None)
    session = Session.create(tmp_path / "s", protocol={"name": "t"}, device={})
    writer = session.standpoint_writer("standpoint_01", info, {"name": "standpoint_01"})
    depth = np.full((48, 64), 1000, dtype=np.uint16)
    for i in range(20):
        writer.write(FrameSet(i, 1_700_000_000_000_000_000 + i * 33_333_333, depth=depth))
    real_join = writer._thread.join

    def slow_join(timeout: float | None = None) -> None:
        # the interrupt arrives in the middle of the close
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        real_join(timeout)

    writer._thread.join = slow_join  # type: ignore[method-assign]
    assert threading.current_thread() is threading.main_thread()
    with pytest.raises(KeyboardInterrupt):
        writer.close()
    rec = open_recording(tmp_path / "s" / "standpoint_01.mcap")
    assert rec.frame_count == 20
    assert [e["status"] for e in json.loads((tmp_path / "s" / "session.json").read_text())["standpoints"]] \
        == ["complete"]


def test_a_ctrl_c_held_while_a_standpoint_closes_survives_a_failing_close() -> None:
    """Ctrl-C during the close is held until the file is finished; when the close then fails (a
    full disk), the Ctrl-C still ends the run (exit 130), with that failure as its cause: it was
    dropped, and the run went on."""
    import os

    from depthstation.core.capture.session import _sigint_deferred
    from depthstation.core.errors import CaptureError

    before = signal.getsignal(signal.SIGINT)  # the default, or ignored (a run started in the background)
    with pytest.raises(KeyboardInterrupt) as info, _sigint_deferred():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs: held, not raised here
        raise CaptureError("standpoint_01.mcap: writing failed: no space left on the device")
    assert isinstance(info.value.__cause__, CaptureError)
    assert signal.getsignal(signal.SIGINT) == before  # the handler the block found is back
    with pytest.raises(CaptureError), _sigint_deferred():  # no Ctrl-C: the failure as it was
        raise CaptureError("writing failed")


def _finished(path: Path) -> bool:
    """Whether the MCAP was finished (its summary section is there)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        try:
            return make_reader(f).get_summary() is not None
        except Exception:  # mcap raises several kinds on a file cut short
            return False


@pytest.mark.parametrize("where", ["opening", "entering"])
def test_a_ctrl_c_before_the_recording_loop_holds_the_file_still_finishes_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    """A Ctrl-C right after the standpoint's file was created, before the loop's `with` took charge
    of it ('opening': inside standpoint_writer; 'entering': after it returned, as Python may raise
    it there): the file is finished all the same and the standpoint is 'partial'. Why: such a
    Ctrl-C left an MCAP without its summary (the Ctrl-C test failed under load)."""
    import os

    from test_acquire_loop import RenderedBoardCamera, drive

    from depthstation.acquire.guided_capture import GuidedCapture
    from depthstation.core.board import Board
    from depthstation.core.capture.session import Session, StandpointWriter
    from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances
    from depthstation.simulate.operator import SimulatedOperator, Stance

    proto = Protocol("test", board=Board(), streams=Streams(width=640, height=360),
                     plan=Plan(frames_per_standpoint=6, start_distance_m=1.0, step_m=0.5, max_distance_m=1.0,
                               inclinations_deg=(0.0,)),
                     tolerances=Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3))
    cam = RenderedBoardCamera(proto.board)
    session = Session.create(tmp_path / "s", protocol=proto)

    def ctrl_c() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs by now: raised here, or held where the code holds it

    if where == "opening":
        real = session.standpoint_writer

        def opening(*args: object, **kwargs: object) -> StandpointWriter:
            writer = real(*args, **kwargs)  # type: ignore[arg-type]
            assert writer.partial.exists()
            ctrl_c()
            return writer

        monkeypatch.setattr(session, "standpoint_writer", opening)
    else:
        real_enter = StandpointWriter.__enter__

        def entering(self: StandpointWriter) -> StandpointWriter:
            ctrl_c()
            return real_enter(self)

        monkeypatch.setattr(StandpointWriter, "__enter__", entering)
    cap = GuidedCapture(cam, proto, session, on_guidance=drive(cam, SimulatedOperator(
        proto.board, Stance(range_m=1.0), seed=1)), max_guidance_s=30.0)
    with pytest.raises(KeyboardInterrupt):
        cap.run()
    assert _finished(tmp_path / "s" / "standpoint_01.mcap.partial")
    assert [e["status"] for e in Session.open(tmp_path / "s").standpoints] == ["partial"]
    assert not cam.started
