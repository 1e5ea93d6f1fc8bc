"""What the bad-input audit found: a full disk, cut or empty files, wrong encodings, out-of-range keys.
Every bad input is written here by code other than the reader under test; each ends in one line that
names the file (and the key), exit 2 for bad input and 1 for other failures, no traceback, and nothing
left behind that reads as complete."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.capture.mcap_writer import McapFileWriter, write_mcap
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


# -- TLS references: empty, cut, stopped writers -------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 3-frame synthetic walk and its poses: enough to reach the reference's reading."""
    from depthstation.evaluate.scan.synthetic import make_sequence
    from depthstation.evaluate.scan.trajectory import write_tum

    root = tmp_path_factory.mktemp("walk")
    seq = make_sequence(frames=3, width=40, height=30, seed=1)
    write_mcap(root / "seq.mcap", seq.info, seq.frames())
    write_tum(root / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    return root / "seq.mcap", root / "poses.txt"


def _scan(walk: tuple[Path, Path], reference: Path, out: Path,
          capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code, _, err = run_console(["evaluate", "scan", "--sequence", str(walk[0]), "--poses", str(walk[1]),
                                "--reference", str(reference), "--out", str(out)], capsys)
    return code, err


def _las(path: Path, n: int) -> Path:
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = np.zeros(3)
    header.scales = np.full(3, 0.001)
    las = laspy.LasData(header)
    pts = np.random.default_rng(0).uniform(0.0, 4.0, (n, 3))
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(str(path))
    return path


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_las_without_points_is_bad_input(tiny_walk: tuple[Path, Path], tmp_path: Path, suffix: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    ref = _las(tmp_path / f"empty{suffix}", 0)
    code, err = _scan(tiny_walk, ref, tmp_path / "out", capsys)
    line = one_line_error(code, err, str(ref), "no points")
    assert "LAZ backend" not in line


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_cut_las_is_said_cut_short(tiny_walk: tuple[Path, Path], tmp_path: Path, suffix: str,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    whole = _las(tmp_path / f"whole{suffix}", 5000)
    ref = tmp_path / f"cut{suffix}"
    ref.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    code, err = _scan(tiny_walk, ref, tmp_path / "out", capsys)
    line = one_line_error(code, err, str(ref), "cut short", "5000 points")
    assert "LAZ backend" not in line  # it is installed: no advice to install it


def test_a_laz_without_a_backend_says_so(tiny_walk: tuple[Path, Path], tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    laspy = pytest.importorskip("laspy")
    ref = _las(tmp_path / "whole.laz", 500)
    monkeypatch.setattr(laspy.LazBackend, "is_available", lambda self: False)  # as without lazrs
    code, err = _scan(tiny_walk, ref, tmp_path / "out", capsys)
    one_line_error(code, err, str(ref), "no LAZ backend", "pip install")


def _e57_killed(path: Path, write_scan: bool) -> Path:
    """An E57 whose writing process died before `close` (what pye57 leaves then)."""
    pytest.importorskip("pye57")
    code = ("import os, sys, numpy as np, pye57\n"
            "e = pye57.E57(sys.argv[1], mode='w')\n"
            "p = np.random.default_rng(0).uniform(0, 4, (2000, 3))\n"
            + ("e.write_scan_raw({'cartesianX': p[:, 0], 'cartesianY': p[:, 1], 'cartesianZ': p[:, 2]})\n"
               if write_scan else "")
            + "os._exit(0)\n")
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=60)
    return path


def _e57_no_scan(path: Path) -> Path:
    pye57 = pytest.importorskip("pye57")
    pye57.E57(str(path), mode="w").close()
    return path


def _e57_cut(path: Path) -> Path:
    pye57 = pytest.importorskip("pye57")
    whole = path.with_name("whole.e57")
    e57 = pye57.E57(str(whole), mode="w")
    p = np.random.default_rng(0).uniform(0, 4, (2000, 3))
    e57.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]})
    e57.close()
    path.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    return path


@pytest.mark.parametrize(("make", "words"), [
    (lambda p: _e57_killed(p, True), ("writer was stopped",)),
    (lambda p: _e57_killed(p, False), ("writer was stopped",)),
    (_e57_no_scan, ("holds no scan",)),
    (_e57_cut, ("cut short",)),
])
def test_a_broken_e57_is_one_line(tiny_walk: tuple[Path, Path], tmp_path: Path, make: Any,
                                  words: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    ref = make(tmp_path / "ref.e57")
    code, err = _scan(tiny_walk, ref, tmp_path / "out", capsys)
    one_line_error(code, err, str(ref), *words)
    assert len(err.strip().splitlines()) == 1, err  # no libE57 debug dump after the line
    assert "Debug info" not in err and "libe57" not in err.lower()


# -- a rosbag2 MCAP cut short ---------------------------------------------------------------------
@pytest.mark.parametrize("share", [0.5, 0.8])
@pytest.mark.parametrize("as_folder", [True, False])
def test_a_cut_rosbag2_mcap_gives_its_complete_chunks(tmp_path: Path, share: float, as_folder: bool,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from ros_bags import write_bag

    from depthstation.core.run_warnings import collecting

    info = sample_info(160, 120)
    frames = list(sample_frames(info, 30, seed=1))
    write_bag(tmp_path / "bag", info, frames)  # rosbags' writer: the recorder's layout
    (whole,) = (tmp_path / "bag").glob("*.mcap")
    data = whole.read_bytes()
    if as_folder:
        cut = tmp_path / "cut"
        cut.mkdir()
        (cut / whole.name).write_bytes(data[: int(len(data) * share)])
        (cut / "metadata.yaml").write_text((tmp_path / "bag" / "metadata.yaml").read_text())
    else:
        cut = tmp_path / "cut.mcap"
        cut.write_bytes(data[: int(len(data) * share)])
    with collecting() as found:
        rec = open_recording(cut)
        got = list(rec.frames())
    assert 0 < len(got) < len(frames)
    assert rec.frame_count == len(got)
    # a whole chunk holds ~1 MB here: at most the chunk the cut fell in (and its neighbour's share) is lost
    assert len(got) >= int(share * len(frames)) - 10, len(got)
    for fs, original in zip(got, frames, strict=False):
        np.testing.assert_array_equal(fs.depth, original.depth)  # the recovered frames are the first ones
    lines = [w.line() for w in found]
    assert any("cut short" in x and f"recovered {len(got)} depth frames" in x for x in lines), lines
    # how much of the recording that is, where its metadata.yaml says how much it held
    listed = f"({len(got)} of the {len(frames)} its metadata.yaml lists)"
    assert any(listed in x for x in lines) == as_folder, lines
    # the command says it too, with exit 0
    code, _, err = run_console(["capture", "info", str(cut)], capsys)
    assert code == 0, err
    assert f"recovered {len(got)} depth frames" in err and "before its first complete chunk" not in err


def test_a_rosbag2_mcap_cut_before_any_chunk_is_bad_input(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    from ros_bags import write_bag

    info = sample_info(160, 120)
    write_bag(tmp_path / "bag", info, sample_frames(info, 30, seed=1))
    (whole,) = (tmp_path / "bag").glob("*.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:300])
    code, _, err = run_console(["capture", "info", str(cut)], capsys)
    one_line_error(code, err, str(cut), "cut short before its first complete chunk")


# -- wrong images on a ROS depth topic ------------------------------------------------------------
def _odd_bag(path: Path, change: str) -> Path:
    """A realsense-ros bag whose depth topic carries bgr8 images, or whose third depth message holds
    half its data (written by rosbags, through the test's own bag writer)."""
    from ros_bags import BagWriter

    class Odd(BagWriter):
        def _image(self, a: np.ndarray, encoding: str, t_ns: int, frame_id: str) -> tuple[str, Any]:
            if encoding == "16UC1" and change == "bgr8":
                a, encoding = np.repeat((a >> 8).astype(np.uint8)[..., None], 3, axis=2), "bgr8"
            msgtype, msg = super()._image(a, encoding, t_ns, frame_id)
            if encoding == "16UC1" and change == "short" and self.seq == 2:
                msg.data = msg.data[: len(msg.data) // 2]
            return msgtype, msg

    info = sample_info(160, 120)
    with Odd(path, info) as w:
        w.write_frames(sample_frames(info, 5, seed=1))
    return path


def test_bgr8_on_the_depth_topic_is_one_error_and_no_false_warning(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _odd_bag(tmp_path / "bag", "bgr8")
    code, _, err = run_console(["capture", "import", str(bag), "--out", str(tmp_path / "imp")], capsys)
    one_line_error(code, err, str(bag), "/camera/camera/depth/image_rect_raw", "message 0", "bgr8",
                   "single-channel")
    assert "65.53 m" not in err and "warning" not in err  # nothing said about depth it never read
    assert not (tmp_path / "imp").exists()


def test_image_data_shorter_than_the_image_names_topic_message_and_sizes(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _odd_bag(tmp_path / "bag", "short")
    code, _, err = run_console(["capture", "import", str(bag), "--out", str(tmp_path / "imp")], capsys)
    line = one_line_error(code, err, str(bag), "/camera/camera/depth/image_rect_raw", "message 2",
                          "38400 bytes", "holds 19200")
    assert "reshape" not in line
    assert not (tmp_path / "imp").exists()


# -- a protocol given as --board is validated whole -------------------------------------------------
@pytest.mark.parametrize(("old", "new", "key"), [
    ("frames_per_standpoint = 10\n", 'frames_per_standpoint = "ten"\n', "plan.frames_per_standpoint"),
    ("frames_per_standpoint = 10\n", "frames_per_standpoint = 0\n", "plan.frames_per_standpoint"),
    ("step_m = ", "step_m = -", "plan.step_m"),
    ("start_distance_m = ", "start_distance_m = -", "plan.start_distance_m"),
])
def test_evaluate_board_protocol_is_validated_whole(small_session: Path, tmp_path: Path, old: str, new: str,
                                                    key: str, capsys: pytest.CaptureFixture[str]) -> None:
    text = (small_session.parent / "p.toml").read_text()
    assert old in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace(old, new, 1))
    code, _, err = run_console(["evaluate", "checkerboard", str(small_session), "--board", str(bad),
                                "--out", str(tmp_path / "o"), "--frames", "3"], capsys)
    one_line_error(code, err, str(bad), key)
    assert not (tmp_path / "o").exists()


# -- evaluate batch checks every scan item's poses and reference before any runs ---------------------
TRIANGLE_PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                "0 0 1\n1 0 1\n0 1 1\n3 0 1 2\n")
EMPTY_PLY = ("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
             "end_header\n")


@pytest.mark.parametrize(("poses", "reference", "file", "words"), [
    ("0.0 1 2 three 0 0 0 1\n", TRIANGLE_PLY, "bad_poses.txt", ("line 1", "not a number")),
    (None, "", "bad.ply", ("empty",)),
    (None, EMPTY_PLY, "bad.ply", ("neither triangles nor points",)),
])
def test_batch_refuses_a_bad_scan_item_before_running_any(tiny_walk: tuple[Path, Path], tmp_path: Path,
                                                          poses: str | None, reference: str, file: str,
                                                          words: tuple[str, ...],
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    seq, good_poses = tiny_walk
    (tmp_path / "room.ply").write_text(TRIANGLE_PLY)
    (tmp_path / "bad.ply").write_text(reference)
    bad_poses = tmp_path / "bad_poses.txt"
    bad_poses.write_text(poses or good_poses.read_text())
    (tmp_path / "other.mcap").write_bytes(seq.read_bytes())  # two recordings: neither counts twice
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        'out = "res"\n'
        f'[[items]]\nkind = "scan"\nname = "first"\n'
        f'inputs = {{ sequence = "{seq}", poses = "{good_poses}", reference = "room.ply" }}\n'
        f'[[items]]\nkind = "scan"\nname = "second"\n'
        f'inputs = {{ sequence = "other.mcap", poses = "{bad_poses}", reference = "bad.ply" }}\n')
    code, _, err = run_console(["evaluate", "batch", str(manifest), "--quiet"], capsys)
    one_line_error(code, err, str(manifest), "items[1] (second)", file, *words)
    assert not (tmp_path / "res").exists()  # nothing ran


# -- view --rrd into a folder that cannot be written --------------------------------------------------
@pytest.fixture()
def read_only_folder(tmp_path: Path) -> Any:
    """A folder nobody may write into: chmod 555 for a user; for root (whom modes do not stop) a
    read-only tmpfs mounted there, else skipped."""
    folder = tmp_path / "ro"
    folder.mkdir()
    mounted = False
    if os.geteuid() == 0:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)],
                           capture_output=True, timeout=30)
        if r.returncode != 0:
            pytest.skip("running as root without mount: no folder root cannot write")
        mounted = True
    else:
        folder.chmod(0o555)
    try:
        yield folder
    finally:
        if mounted:
            subprocess.run(["umount", str(folder)], capture_output=True, timeout=30)
        else:
            folder.chmod(0o755)


def test_view_rrd_into_a_read_only_folder_says_so(tmp_path: Path, read_only_folder: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from test_station_compare import write_checkerboard

    result = write_checkerboard(tmp_path / "cb", 0.095)
    code, _, err = run_console(["view", str(result), "--rrd", str(read_only_folder / "x.rrd")], capsys)
    line = one_line_error(code, err, str(read_only_folder), "not writable")
    assert ".partial" not in line
    assert not any(p.name.endswith(".rrd") for p in result.iterdir())


# -- a damaged grid.npz --------------------------------------------------------------------------
@pytest.mark.parametrize("damage", ["head", "object"])
def test_a_damaged_grid_is_said_damaged_not_pickle_advice(tmp_path: Path, damage: str,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    from test_station_compare import write_scan

    result = write_scan(tmp_path / "scan", 0.004)
    grid = result / "grid.npz"
    if damage == "head":  # its first bytes overwritten (a disk error, another program's write)
        with grid.open("r+b") as f:
            f.write(b"\0" * 64)
    else:  # an archive whose count array holds Python objects, written by numpy itself
        with np.load(grid) as z:
            data = {k: z[k] for k in z.files}
        data["count"] = np.array([None] * data["count"].size, dtype=object)
        grid.unlink()
        np.savez(grid, **data)
    code, _, err = run_console(["view", str(result), "--rrd", str(tmp_path / "v.rrd")], capsys)
    line = one_line_error(code, err, str(grid), "damaged")
    assert "allow_pickle" not in line and "pickle=True" not in line


# -- a killed simulate leaves no hidden folder for ever --------------------------------------------
def test_a_killed_runs_partial_folder_is_removed_by_the_next_run(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    proto = tmp_path / "p.toml"
    proto.write_text((Path(__file__).parents[1] / "protocols" / "demo-d455.toml").read_text()
                     .replace("width = 1280", "width = 640").replace("height = 720", "height = 360"))
    out = tmp_path / "sim"
    args = ["simulate", "checkerboard", "--protocol", str(proto), "--out", str(out), "--frames", "12",
            "--standpoint", "standpoint_01"]
    exe = str(Path(sys.executable).with_name("depthstation"))
    proc = subprocess.Popen([exe, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    partial = tmp_path / f".sim.partial-{proc.pid}"
    deadline = time.monotonic() + 120
    while not partial.is_dir() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.kill()
    proc.wait(timeout=30)
    assert partial.is_dir(), "the run ended before its folder appeared"
    assert not out.exists()
    code, _, err = run_console(args, capsys)
    assert code == 0, err
    assert not partial.exists()
    assert f"removed {partial}" in err and f"pid {proc.pid}" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "sim"]


def test_a_running_runs_partial_folder_is_left_alone(tmp_path: Path) -> None:
    from depthstation.core.results import remove_stale_partials

    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        theirs = tmp_path / f".sim.partial-{alive.pid}"
        theirs.mkdir()
        (theirs / "half.mcap").write_bytes(b"x")
        assert remove_stale_partials(tmp_path / "sim") == []
        assert (theirs / "half.mcap").is_file()
    finally:
        alive.kill()
        alive.wait(timeout=30)
    assert remove_stale_partials(tmp_path / "sim") == [theirs]  # once its owner is gone


# -- a USB drop while recording is said on stderr ------------------------------------------------------
def test_a_usb_drop_while_recording_is_said_with_what_was_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    import fake_realsense as frs
    from test_acquire_live import board_scene

    from depthstation.acquire import station
    from depthstation.acquire.guided_capture import GuidedCapture, LiveState
    from depthstation.core.board import Board
    from depthstation.core.rerun_bridge import RerunTarget

    unit = frs.FakeUnit()
    world = frs.FakeRealSense(unit)
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)
    unit.scene = board_scene(Board(), 1.0)
    armed = [False]

    class Unplugged(GuidedCapture):  # the operator's cable comes out after 3 recorded frames
        def _emit(self, state: LiveState) -> None:
            if state.phase == "recording" and state.recorded == 3 and not armed[0]:
                armed[0] = True
                unit.unplug(0.05)
            super()._emit(state)

    monkeypatch.setattr(station, "GuidedCapture", Unplugged)
    proto = tmp_path / "p.toml"
    proto.write_text('name = "p"\n[board]\ntype = "checkerboard"\nsquares_x = 7\nsquares_y = 5\n'
                     'square_length_m = 0.095\n[streams]\nwidth = 640\nheight = 360\nfps = 30\n'
                     '[plan]\nframes_per_standpoint = 8\n'
                     'start_distance_m = 1.0\nstep_m = 0.2\nmax_distance_m = 1.0\ninclinations_deg = [0.0]\n'
                     '[tolerances]\nstill_seconds = 0.2\n[device]\nmodel = "D455"\n')
    st = station.Station("live", str(proto), tmp_path / "s", False, 0, False)
    capsys.readouterr()
    try:
        station.do_capture(st, RerunTarget(None, False, False), 20.0)
    finally:
        st.close()
    err = capsys.readouterr().err
    assert armed[0]
    lines = err.splitlines()
    drop = [x for x in lines if "the camera disconnected" in x]
    back = [x for x in lines if "the camera is back" in x]
    assert len(drop) == 1 and len(back) == 1, err
    assert "standpoint_01" in drop[0] and "3 frames" in drop[0]
    assert "standpoint_01.discarded-1.mcap" in drop[0]
    assert (tmp_path / "s" / "standpoint_01.discarded-1.mcap").is_file()  # what the line says was kept
    assert lines.index(drop[0]) < lines.index(back[0])
