"""Warnings reach the user whatever thread raised them: a recording read by a standpoint worker
that turns out truncated, or a standpoint the session lists but whose file is gone, end in the
printed warnings, `result.json` and `--strict`'s exit 3 (they were printed mid-progress, or not at
all, and the run exited 0)."""

from __future__ import annotations

import json
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from depthstation.app.cli import run_cli
from depthstation.core.run_warnings import collecting, warn


def test_a_warning_from_a_pool_thread_is_collected_once() -> None:
    with collecting() as found, ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda i: warn("cut short", "a.mcap", "truncated-input"), range(4)))
    assert [w.code for w in found] == ["truncated-input"]
    with ThreadPoolExecutor(1) as pool:  # no command running: nothing is kept for later
        pool.submit(warn, "alone").result()
    with collecting() as later:
        pass
    assert later == []


def test_a_pool_threads_warning_goes_to_the_innermost_collector_then_outwards() -> None:
    """A batch item keeps its own list (its result.json); what its pool's threads warn belongs to
    it, and reaches the command's list when the item ends."""
    with collecting() as run:
        with collecting() as item, ThreadPoolExecutor(1) as pool:
            pool.submit(warn, "cut short", "b.mcap", "truncated-input").result()
        assert [w.where for w in item] == ["b.mcap"]
        assert [w.where for w in run] == ["b.mcap"]
        with ThreadPoolExecutor(1) as pool:
            pool.submit(warn, "cut short", "c.mcap", "truncated-input").result()
    assert [w.where for w in run] == ["b.mcap", "c.mcap"]


@pytest.fixture(scope="module")
def session(small_session: Path) -> Path:
    return small_session


def _strict(work: Path, board: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, Any]:
    capsys.readouterr()
    code = run_cli(["--strict", "evaluate", "checkerboard", str(work), "--board", str(board),
                    "--out", str(out), "--frames", "12", "--no-figures"])
    info = json.loads((out / "result.json").read_text()) if (out / "result.json").is_file() else {}
    return code, capsys.readouterr().err, info


def test_a_truncated_standpoint_among_two_is_warned_and_strict(session: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    work = tmp_path / "t"
    shutil.copytree(session, work)
    cut = work / "standpoint_02.mcap"
    data = cut.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    code, err, info = _strict(work, session.parent / "p.toml", tmp_path / "o", capsys)
    assert code == 3, err
    assert "cut short" in err and str(cut) in info["truncated_inputs"]


def test_a_standpoint_whose_recording_is_gone_is_warned(session: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    work = tmp_path / "m"
    shutil.copytree(session, work)
    (work / "standpoint_02.mcap").unlink()
    code, err, info = _strict(work, session.parent / "p.toml", tmp_path / "o", capsys)
    assert code == 3, err
    assert "standpoint_02" in err and "missing" in err
    assert any(w["code"] == "missing-recording" for w in info["warnings"])


def test_a_board_other_than_the_recorded_one_is_warned(session: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A print at 97 % given at its nominal size (or the reverse) moves every distance by 3 %,
    inside the board-scale check's 5 %: the session's own board says so."""
    board = tmp_path / "b.json"
    board.write_text(json.dumps({"type": "checkerboard", "squares_x": 7, "squares_y": 5,
                                 "square_length_m": 0.092}))
    code, err, info = _strict(session, board, tmp_path / "o", capsys)
    assert code == 3, err
    said = [w for w in info["warnings"] if w["code"] == "board-mismatch"]
    assert len(said) == 1 and "square_length_m 0.095 there, 0.092" in said[0]["message"]
    capsys.readouterr()
    code = run_cli(["evaluate", "checkerboard", str(session), "--board", str(board), "--roi", "0.4",
                    "--out", str(tmp_path / "r")])
    assert code == 2 and "did you mean 40?" in capsys.readouterr().err


def test_a_truncated_recording_imported_into_a_session_is_warned_at_every_study(
        session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The import's warning is printed once; the session keeps the cut, so a study of it days later
    still says that one standpoint holds only the frames recovered (it was listed as complete)."""
    cut = tmp_path / "standpoint_02.mcap"
    data = (session / "standpoint_02.mcap").read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    imported = tmp_path / "imported"
    code = run_cli(["capture", "import", str(session / "standpoint_01.mcap"), str(cut),
                    "--out", str(imported)])
    assert code == 0
    entry = next(e for e in json.loads((imported / "session.json").read_text())["standpoints"]
                 if e["name"] == "standpoint_02")
    assert entry["status"] == "complete" and 0 < entry["source_truncated"]["recovered_frames"] < 12
    code, err, info = _strict(imported, session.parent / "p.toml", tmp_path / "o", capsys)
    assert code == 3, err
    assert "standpoint_02" in err and "cut short" in err
    assert str(imported / "standpoint_02.mcap") in info["truncated_inputs"]
    assert str(imported / "standpoint_01.mcap") not in info["truncated_inputs"]
    # imported once more (a session moved into another): the cut goes with it
    again = tmp_path / "again"
    assert run_cli(["capture", "import", str(imported), "--out", str(again)]) == 0
    moved = {e["name"]: e for e in json.loads((again / "session.json").read_text())["standpoints"]}
    assert moved["standpoint_02"]["source_truncated"] == entry["source_truncated"]
    assert "source_truncated" not in moved["standpoint_01"]


def test_standpoints_of_two_cameras_are_warned(session: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A session resumed with another camera holds D455 and D435 standpoints; the result named the
    first camera only, and the fitted noise curve mixed two baselines without a word."""
    other = tmp_path / "d435"
    code = run_cli(["simulate", "checkerboard", "--protocol", str(session.parent / "p.toml"),
                    "--model", "d435-ideal", "--out", str(other), "--frames", "12",
                    "--standpoint", "standpoint_02"])
    assert code == 0
    work = tmp_path / "mixed"
    shutil.copytree(session, work)
    (work / "standpoint_02.mcap").unlink()
    shutil.copy(other / "standpoint_02.mcap", work / "standpoint_02.mcap")
    code, err, info = _strict(work, session.parent / "p.toml", tmp_path / "o", capsys)
    assert code == 3, err
    said = [w["message"] for w in info["warnings"] if w["code"] == "mixed-cameras"]
    assert len(said) == 1 and "standpoint_01" in said[0] and "standpoint_02" in said[0]
    assert "baseline_m 0.095" in said[0] and "baseline_m 0.05" in said[0]
    code, err, info = _strict(session, session.parent / "p.toml", tmp_path / "o2", capsys)
    assert code == 0 and not info["warnings"], err  # one camera: no word


def test_a_study_called_from_python_lists_its_warnings_in_result_json(
        session: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A notebook or script that calls the study (no command, no collector of its own) gets the
    same result.json as the command: its warnings listed, and each also logged once."""
    from depthstation.evaluate.checkerboard.run import run_checkerboard

    board = tmp_path / "b.json"
    board.write_text(json.dumps({"type": "checkerboard", "squares_x": 7, "squares_y": 5,
                                 "square_length_m": 0.092}))
    with caplog.at_level("WARNING", logger="depthstation.warnings"):
        run_checkerboard([session], board, tmp_path / "o", frames=12, figures=False)
    info = json.loads((tmp_path / "o" / "result.json").read_text())
    said = [w for w in info["warnings"] if w["code"] == "board-mismatch"]
    assert len(said) == 1 and "0.092" in said[0]["message"], info["warnings"]
    logged = [r.getMessage() for r in caplog.records if "square_length_m 0.095 there" in r.getMessage()]
    assert len(logged) == 1, caplog.records
    # what the summary says the board's scale does to the figures, it does: 3.2 % short
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert "square_length_m 0.092" in summary["absorbed"]["board_scale"]
    told = json.loads((session / "truth.json").read_text())["standpoints"]
    truth = {t["name"]: t["distance_m"] for t in told}
    for sp in summary["standpoints"]:
        ratio = sp["figures"]["distance_m"] / truth[sp["name"]]
        assert ratio == pytest.approx(0.092 / 0.095, abs=0.002), sp["name"]


def test_nested_collectors_leave_the_outer_one_in_place_whatever_they_hold() -> None:
    """A batch: an item with no warning ends before one with a warning. Lists compare by value, so
    the ending item's empty list removed the command's empty one: the next item's thread warning
    then had no collector, and the command ended in a traceback (ValueError) instead of exit 3."""
    with collecting() as run:
        with collecting():
            pass  # the first item: nothing to say
        with collecting() as item, ThreadPoolExecutor(1) as pool:
            pool.submit(warn, "cut short", "d.mcap", "truncated-input").result()
        assert [w.where for w in item] == ["d.mcap"]
    assert [w.where for w in run] == ["d.mcap"]


def test_a_whole_copy_of_a_cut_recording_still_says_it_holds_only_part(
        session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`capture compact` of a cut recording, or the file of a session it was imported into given
    alone, is a complete MCAP: its study said nothing (exit 0 under --strict) of the frames lost."""
    cut = tmp_path / "standpoint_02.mcap"
    data = (session / "standpoint_02.mcap").read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    board = session.parent / "p.toml"
    assert run_cli(["capture", "compact", str(cut), str(tmp_path / "z.mcap")]) == 0
    assert run_cli(["capture", "import", str(cut), "--out", str(tmp_path / "imp")]) == 0
    assert run_cli(["capture", "compact", str(tmp_path / "imp" / "standpoint_02.mcap"),
                    str(tmp_path / "zz.mcap")]) == 0
    for copy in (tmp_path / "z.mcap", tmp_path / "imp" / "standpoint_02.mcap", tmp_path / "zz.mcap"):
        capsys.readouterr()
        out = tmp_path / f"o-{copy.stem}-{copy.parent.name}"
        code = run_cli(["--strict", "evaluate", "checkerboard", str(copy), "--board", str(board), "--out",
                        str(out), "--frames", "12", "--no-figures"])
        err = capsys.readouterr().err
        assert code == 3 and "cut short" in err and str(cut) in err, err
        info = json.loads((out / "result.json").read_text())
        assert str(copy) in info["truncated_inputs"]
