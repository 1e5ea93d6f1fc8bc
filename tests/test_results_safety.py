"""Results are never lost or torn: a second run into a busy folder refuses and the first one's result
is complete; a non-empty --out or an existing --rrd needs --force; a full disk ends in one line naming
the path, exit 1, and leaves nothing that looks like a finished result."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from contextlib import suppress
from pathlib import Path

import pytest

from depthstation.app.cli import run_cli

EXE = str(Path(sys.executable).with_name("depthstation"))


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=300)


def run_here(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """The console script in this process: (exit code, stderr)."""
    capsys.readouterr()
    code = run_cli(list(args))
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def session(small_session: Path) -> Path:
    return small_session


def test_second_run_into_a_busy_folder_refuses(tmp_path: Path, session: Path) -> None:
    out = tmp_path / "res"
    board = str(session.parent / "p.toml")
    args = ["evaluate", "checkerboard", str(session), "--board", board, "--out", str(out), "--frames", "3",
            "--no-figures"]
    first = subprocess.Popen([EXE, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / ".res.lock"

    def held() -> bool:  # the holder writes its pid once it has the lock (the file exists before)
        with suppress(OSError):
            return lock.read_text().strip() == str(first.pid)
        return False

    deadline = time.monotonic() + 120
    while not held() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert held(), "the first run never took the folder's lock"
    # the first run is paused while the second one tries: it holds the folder however fast it
    # would have finished (a loaded machine starts the second run slowly)
    first.send_signal(signal.SIGSTOP)
    try:
        second = run(*args)
    finally:
        first.send_signal(signal.SIGCONT)
    assert second.returncode == 2, second.stderr
    assert "another depthstation run is writing" in second.stderr and "Traceback" not in second.stderr
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert {"standpoints.csv", "frames.csv", "summary.json", "result.json"} <= {p.name for p in out.iterdir()}
    assert len((out / "standpoints.csv").read_text().splitlines()) == 3
    assert not lock.exists() and not list(tmp_path.glob(".res.partial-*"))


def test_non_empty_out_and_existing_rrd_need_force(tmp_path: Path, session: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    board = str(session.parent / "p.toml")
    out = tmp_path / "res"
    out.mkdir()
    (out / "keep.txt").write_text("a result of last week")
    args = ["evaluate", "checkerboard", str(session), "--board", board, "--frames", "3"]
    code, err = run_here(capsys, *args, "--out", str(out))
    assert code == 2 and "never overwrite" in err
    assert (out / "keep.txt").read_text() == "a result of last week"
    rrd = tmp_path / "x.rrd"
    rrd.write_bytes(b"RRF2 an old recording")
    code, err = run_here(capsys, *args, "--out", str(tmp_path / "new"), "--rrd", str(rrd))
    assert code == 2 and "x.rrd" in err and rrd.read_bytes() == b"RRF2 an old recording"
    assert not (tmp_path / "new").exists()
    # --force replaces an earlier result only: a folder of the user's own files stays
    code, err = run_here(capsys, *args, "--out", str(out), "--rrd", str(rrd), "--force")
    assert code == 2 and "did not write" in err and "Traceback" not in err
    assert (out / "keep.txt").read_text() == "a result of last week"
    assert rrd.read_bytes() == b"RRF2 an old recording"
    earlier = tmp_path / "earlier"
    assert run_here(capsys, *args, "--out", str(earlier))[0] == 0
    (earlier / "notes.txt").write_text("added by hand")  # never deleted with the earlier result
    code, err = run_here(capsys, *args, "--out", str(earlier), "--rrd", str(rrd), "--force")
    assert code == 2 and "notes.txt" in err and (earlier / "notes.txt").is_file()
    (earlier / "notes.txt").unlink()
    code, err = run_here(capsys, *args, "--out", str(earlier), "--rrd", str(rrd), "--force")
    assert code == 0, err
    assert (earlier / "result.json").is_file()
    assert (earlier / ".depthstation-result").is_file()
    assert rrd.read_bytes() != b"RRF2 an old recording" and rrd.read_bytes()[:3] == b"RRF"  # a new one


def test_force_never_deletes_an_input(tmp_path: Path, session: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    """--out pointed at the input (a capture session, or a folder holding it) with --force: refused
    before any work, the capture untouched; also when that folder is an earlier result."""
    work = tmp_path / "copy"
    shutil.copytree(session, work)
    before = sorted(p.relative_to(work) for p in work.rglob("*"))
    board = str(session.parent / "p.toml")
    for out in (work, tmp_path):
        code, err = run_here(capsys, "evaluate", "checkerboard", str(work), "--board", board, "--frames", "3",
                             "--out", str(out), "--force")
        assert code == 2 and "holds the input" in err and "Traceback" not in err, err
    assert sorted(p.relative_to(work) for p in work.rglob("*")) == before
    # an earlier result (simulate writes one) that holds the input of this run
    code, err = run_here(capsys, "evaluate", "checkerboard", str(session), "--board", board, "--frames", "3",
                         "--out", str(session), "--force")
    assert code == 2 and "holds the input" in err
    assert (session / "truth.json").is_file()
    # another simulated session is a capture, not a result this command may replace
    code, err = run_here(capsys, "evaluate", "checkerboard", str(session), "--board", board, "--frames", "3",
                         "--out", str(work), "--force")
    assert code == 2 and "earlier 'simulate-checkerboard' result" in err
    # a recording given as --rrd: never overwritten
    mcap = next(work.glob("*.mcap"))
    head = mcap.read_bytes()[:64]
    code, err = run_here(capsys, "evaluate", "checkerboard", str(session), "--board", board, "--frames", "3",
                         "--out", str(tmp_path / "r"), "--rrd", str(mcap), "--force")
    assert code == 2 and "not a rerun recording" in err and mcap.read_bytes()[:64] == head
    assert sorted(p.relative_to(work) for p in work.rglob("*")) == before


def test_force_keeps_files_added_to_an_earlier_result(tmp_path: Path, session: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A user's notes put into a finished result folder were deleted by the next run's --force; the
    marker now lists the files the result wrote, and --force refuses a folder holding others (the
    recording `view` adds is ours)."""
    out = tmp_path / "res"
    args = ["evaluate", "checkerboard", str(session), "--board", str(session.parent / "p.toml"),
            "--frames", "3", "--out", str(out), "--no-figures"]
    assert run_here(capsys, *args)[0] == 0
    (out / "view.rrd").write_bytes(b"RRF2 made by view later")
    code, err = run_here(capsys, *args, "--force")
    assert code == 0, err  # only its own files (and view's recording): replaced
    (out / "notes").mkdir()
    (out / "notes" / "my_analysis.md").write_text("three weeks of thinking")
    code, err = run_here(capsys, *args, "--force")
    assert code == 2 and "notes/my_analysis.md" in err, err
    assert (out / "notes" / "my_analysis.md").read_text() == "three weeks of thinking"
    assert (out / "standpoints.csv").is_file()


def _small_disk(tmp_path: Path, kbytes: int) -> list[str] | None:
    """A command prefix that runs inside a private mount namespace with a tmpfs of `kbytes` at
    tmp_path/disk, or None where the machine allows no such mount."""
    disk = tmp_path / "disk"
    disk.mkdir()
    for prefix in (["unshare", "--user", "--map-root-user", "--mount"], ["unshare", "--mount"]):
        if shutil.which(prefix[0]) is None:
            continue
        probe = subprocess.run([*prefix, "sh", "-c", f"mount -t tmpfs -o size={kbytes}k tmpfs {disk}"],
                               capture_output=True, text=True)
        if probe.returncode == 0:
            return [*prefix, "sh", "-c", f'mount -t tmpfs -o size={kbytes}k tmpfs {disk} && exec "$@"', "sh"]
    return None


def test_out_under_a_file_is_bad_input_naming_the_file(tmp_path: Path, session: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """--out below a regular file (a typo: the board file as a folder) was "File exists", exit 1."""
    board = tmp_path / "p.toml"
    shutil.copy(session.parent / "p.toml", board)
    code, err = run_here(capsys, "evaluate", "checkerboard", str(session), "--board", str(board),
                         "--out", str(board / "res"), "--frames", "12")
    assert code == 2 and f"{board} is a file" in err, err
    assert board.read_text() == (session.parent / "p.toml").read_text()


def test_full_disk_is_one_line_and_leaves_no_finished_folder(tmp_path: Path, session: Path) -> None:
    prefix = _small_disk(tmp_path, 64)
    if prefix is None:
        pytest.skip("this machine allows no private tmpfs mount (unshare/mount refused)")
    out = tmp_path / "disk" / "res"
    r = subprocess.run([*prefix, EXE, "evaluate", "checkerboard", str(session), "--board",
                        str(session.parent / "p.toml"), "--out", str(out), "--frames", "12"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    lines = [x for x in r.stderr.splitlines() if "error" in x]
    assert len(lines) == 1 and "no space left" in lines[0] and str(tmp_path / "disk") in lines[0], r.stderr
    assert "Traceback" not in r.stderr


def test_full_disk_db3_simulation_fails_loudly(tmp_path: Path) -> None:
    pytest.importorskip("pyrealsense2")
    prefix = _small_disk(tmp_path, 400)
    if prefix is None:
        pytest.skip("this machine allows no private tmpfs mount (unshare/mount refused)")
    out = tmp_path / "disk" / "sim"
    args = ["simulate", "checkerboard", "--protocol", "demo-d455", "--format", "db3", "--out", str(out),
            "--frames", "5", "--standpoint", "standpoint_01"]
    r = subprocess.run([*prefix, EXE, *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "simulated into" not in r.stdout and "Traceback" not in r.stderr
    assert "internal error" not in r.stderr and ("disk full" in r.stderr or "no space left" in r.stderr)
    assert not out.exists() or not (out / "result.json").exists()


def test_a_folder_appearing_meanwhile_keeps_the_result_where_the_error_says(tmp_path: Path) -> None:
    """A folder someone else fills while the run writes is not replaced; the finished result is kept
    under the visible name the error gives (it used to be deleted right after being announced)."""
    from depthstation.core.errors import InputError
    from depthstation.core.results import RESULT_MARKER, result_folder

    out = tmp_path / "res"
    with pytest.raises(InputError) as caught, result_folder(out) as tmp:
        (tmp / "table.csv").write_text("a,b\n1,2\n")
        out.mkdir()
        (out / "theirs.txt").write_text("written by another program meanwhile")
    kept = Path(str(caught.value).rsplit("left in ", 1)[1])
    assert kept.is_dir() and not kept.name.startswith(".")
    assert (kept / "table.csv").read_text() == "a,b\n1,2\n" and (kept / RESULT_MARKER).is_file()
    assert (out / "theirs.txt").read_text() == "written by another program meanwhile"
    assert not list(tmp_path.glob(".res.partial-*"))


def test_write_json_writes_numpy_nan_and_inf_as_null(tmp_path: Path) -> None:
    """NaN and inf become null whether they come as Python floats, numpy scalars or array entries
    (a numpy NaN scalar reached json.dumps as NaN and raised)."""
    import json

    import numpy as np

    from depthstation.core.results import write_json

    path = tmp_path / "x.json"
    write_json(path, {"a": np.float64("nan"), "b": np.float32(np.inf), "c": np.array([1.0, np.nan]),
                      "d": float("nan"), "e": [np.float64(2.5)]})
    assert json.loads(path.read_text()) == {"a": None, "b": None, "c": [1.0, None], "d": None, "e": [2.5]}
