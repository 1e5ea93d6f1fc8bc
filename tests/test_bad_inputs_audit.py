"""What the bad-input audit found: a full disk, cut or empty files, wrong encodings, out-of-range keys.
Every bad input is written here by code other than the reader under test; each ends in one line that
names the file (and the key), exit 2 for bad input and 1 for other failures, no traceback, and nothing
left behind that reads as complete."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from depthstation.core.capture.mcap_writer import McapFileWriter
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info

sys.path.insert(0, str(Path(__file__).parent))
from console import run_console
from full_disk import disk_full_after


def one_line_error(code: int, err: str, *words: str, exit_code: int = 2) -> str:
    """The one error line (exit code checked); every word must be in it."""
    assert code == exit_code, err
    errors = [x for x in err.splitlines() if x.startswith("depthstation: error")]
    assert len(errors) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    for w in words:
        assert w in errors[0], (w, errors[0])
    return errors[0]


def _small_mcap(path: Path, frames: int = 6) -> Path:
    info = sample_info(160, 120)
    with McapFileWriter(path, info, compression="none") as w:
        for fs in sample_frames(info, frames, seed=3):
            w.write(fs)
    return path


# -- capture compact on a full disk ----------------------------------------------------------------
def test_compact_on_a_full_disk_keeps_nothing_under_the_final_name_and_a_retry_works(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    src = _small_mcap(tmp_path / "a.mcap")
    out_dir = tmp_path / "archive"
    out_dir.mkdir()
    out = out_dir / "a-small.mcap"
    with disk_full_after(monkeypatch, out_dir, src.stat().st_size // 3) as budget:
        code, _, err = run_console(["capture", "compact", str(src), str(out), "--compression", "none"],
                                   capsys)
    assert budget.refused >= 1  # the disk did fill
    line = one_line_error(code, err, str(out), "No space left", exit_code=1)
    assert "nothing was kept in ." not in line
    assert list(out_dir.iterdir()) == []  # neither a cut file under the final name nor a temporary one
    code, _, err = run_console(["capture", "compact", str(src), str(out)], capsys)
    assert code == 0, err  # the retry is not blocked
    assert open_recording(out).frame_count == 6
    assert [p.name for p in out_dir.iterdir()] == ["a-small.mcap"]


def test_compact_refuses_an_existing_file_before_writing(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    src = _small_mcap(tmp_path / "a.mcap")
    out = tmp_path / "b.mcap"
    out.write_bytes(b"keep me")
    code, _, err = run_console(["capture", "compact", str(src), str(out)], capsys)
    one_line_error(code, err, str(out), "never overwritten")
    assert out.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]




# -- acquire on a full disk ------------------------------------------------------------------------
def test_acquire_on_a_full_disk_says_what_was_kept_and_leaves_no_torn_temporary(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from test_acquire_cli import make_recording
    from test_acquire_faults import TWO_HERE

    rec = make_recording(tmp_path / "board.db3", n=240)
    proto = tmp_path / "two.toml"
    proto.write_text(TWO_HERE.replace("frames_per_standpoint = {frames}", "frames_per_standpoint = 80"))
    sess = tmp_path / "s"
    sess.mkdir()
    # room for the first standpoint (~0.58 MB of lz4 MCAP at 640x360) and part of the second
    with disk_full_after(monkeypatch, sess, 900_000) as budget:
        code, _, err = run_console(["acquire", "capture", "--camera", str(rec), "--protocol", str(proto),
                                    "--session", str(sess)], capsys)
    assert budget.refused >= 1
    line = one_line_error(code, err, "No space left", f"kept in {sess}", "standpoint_01.mcap complete",
                          "standpoint_02.mcap.partial", "--resume", exit_code=1)
    assert "nothing was kept" not in line
    names = sorted(p.name for p in sess.iterdir())
    assert names == ["session.json", "standpoint_01.mcap", "standpoint_02.mcap.partial"], names
    state = json.loads((sess / "session.json").read_text())  # whole, never torn
    assert state["standpoints"][0]["status"] == "complete"
    assert open_recording(sess / "standpoint_01.mcap").frame_count == 80
