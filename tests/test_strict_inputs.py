"""Strict inputs: every required key present, every value in its physical range, text files in
UTF-8, manifests writing only inside their folder. Each bad input ends in exit 2 and one line that
names the file and the key, never a silent default and never an internal error."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from depthstation.app.cli import run_cli
from depthstation.core.capture.sample_recordings import sample_frames, sample_info

EXE = str(Path(sys.executable).with_name("depthstation"))
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


@pytest.fixture()
def run(capsys: pytest.CaptureFixture[str]) -> Callable[..., Ran]:
    """The console script in this process (the same code path as the installed command, without a
    second start-up per case); one case also runs the real executable."""

    def call(*args: str) -> Ran:
        capsys.readouterr()
        code = run_cli(list(args))
        out = capsys.readouterr()
        return Ran(code, out.out, out.err)
    return call


def test_the_executable_says_it_the_same_way(tmp_path: Path) -> None:
    bad = tmp_path / "m.toml"
    bad.write_text("[effects.disparity_noise]\nsigma_px = 0.08\n")
    r = subprocess.run([EXE, "simulate", "checkerboard", "--model", str(bad), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    one_line_error(Ran(r.returncode, r.stdout, r.stderr), "m.toml", "camera.preset")


def one_line_error(r: Ran, *words: str, code: int = 2) -> None:
    assert r.returncode == code, r.stdout + r.stderr
    errors = [x for x in r.stderr.splitlines() if x.startswith("depthstation: error")]
    assert len(errors) == 1, r.stderr
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    for w in words:
        assert w in errors[0], (w, errors[0])


@pytest.fixture()
def png_set(tmp_path: Path, charuco_dir: Path) -> Path:
    """A copy of one real standpoint with its own camera.json and board.json to break."""
    root = tmp_path / "set"
    (root / "pose03").mkdir(parents=True)
    for f in sorted((charuco_dir / "pose03").iterdir())[:4]:
        (root / "pose03" / f.name).symlink_to(f)
    (root / "camera.json").write_text((charuco_dir / "camera.json").read_text())
    (root / "board.json").write_text((charuco_dir / "board.json").read_text())
    return root


def edit_json(path: Path, change: dict[str, object], drop: tuple[str, ...] = ()) -> None:
    data = json.loads(path.read_text())
    for k, v in change.items():
        target = data
        *head, last = k.split(".")
        for h in head:
            target = target[h]
        target[last] = v
    for k in drop:
        data.pop(k)
    path.write_text(json.dumps(data))


def test_board_without_square_length(png_set: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    edit_json(png_set / "board.json", {}, drop=("square_length_m",))
    r = run("evaluate", "checkerboard", str(png_set), "--board", str(png_set / "board.json"),
            "--out", str(tmp_path / "o"), "--frames", "1")
    one_line_error(r, "board.json", "square_length_m")
    assert not (tmp_path / "o").exists()


def test_one_standpoint_name_from_two_inputs(png_set: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    # two copies of a session hold the same standpoint names: evaluated together, their results
    # (and explain's pairs) would merge or replace each other by name without a word
    twin = tmp_path / "twin"
    twin.mkdir()
    (twin / "pose03").mkdir()
    for f in sorted((png_set / "pose03").iterdir()):
        (twin / "pose03" / f.name).symlink_to(f.resolve())
    (twin / "camera.json").write_text((png_set / "camera.json").read_text())
    r = run("evaluate", "checkerboard", str(png_set), str(twin), "--board", str(png_set / "board.json"),
            "--out", str(tmp_path / "o"), "--frames", "1")
    one_line_error(r, "pose03", "also comes from", "separate runs")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("change", "drop", "words"), [
    ({"color.fx": 0}, (), ("camera.json", "color", "fx")),
    ({"depth_units_m": 0}, (), ("camera.json", "depth_units_m")),
    ({}, ("depth_units_m",), ("camera.json", "depth_units_m")),
    ({"color.cx": 5000.0}, (), ("camera.json", "ppx")),
])
def test_camera_json_out_of_range(png_set: Path, tmp_path: Path, change: dict[str, object],
                                  drop: tuple[str, ...], words: tuple[str, ...],
                                  run: Callable[..., Ran]) -> None:
    edit_json(png_set / "camera.json", change, drop)
    r = run("capture", "info", str(png_set / "pose03"))
    one_line_error(r, *words)


def test_images_of_another_size_than_camera_json(png_set: Path, tmp_path: Path,
                                                 run: Callable[..., Ran]) -> None:
    """Width and height of camera.json that are not the images' (swapped, or another resolution's):
    every pixel would sit on the wrong ray, or the kernels read past the image."""
    cam = json.loads((png_set / "camera.json").read_text())
    w, h = cam["color"]["width"], cam["color"]["height"]
    edit_json(png_set / "camera.json",
              {"color.width": h, "color.height": w, "color.cx": h / 2, "color.cy": w / 2})
    r = run("evaluate", "checkerboard", str(png_set), "--board", str(png_set / "board.json"),
            "--out", str(tmp_path / "o"), "--frames", "1")
    one_line_error(r, "_depth.png", f"is {w}x{h} pixels", f"{h}x{w}")
    assert not (tmp_path / "o").exists()


def test_unaligned_depth_needs_its_transform(png_set: Path, run: Callable[..., Ran]) -> None:
    """depth_aligned_to_color false without depth_to_color: identity was assumed without a word."""
    cam = json.loads((png_set / "camera.json").read_text())
    edit_json(png_set / "camera.json", {"depth_aligned_to_color": False, "depth": cam["color"]})
    one_line_error(run("capture", "info", str(png_set / "pose03")), "camera.json", "depth_to_color")
    edit_json(png_set / "camera.json", {"depth_to_color": {"rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                                                           "translation": [-0.05, 0, 0]}})
    r = run("capture", "info", str(png_set / "pose03"))
    assert r.returncode == 0, r.stderr
    from depthstation.core.capture.registry import open_recording

    assert open_recording(png_set / "pose03").info.depth_to_color.translation == (-0.05, 0.0, 0.0)


def test_board_dictionary_typo_names_the_file_and_the_fix(tmp_path: Path, run: Callable[..., Ran]) -> None:
    board = tmp_path / "b.json"
    board.write_text(json.dumps({"type": "charuco", "squares_x": 7, "squares_y": 5, "square_length_m": 0.075,
                                 "marker_length_m": 0.056, "dictionary": "DICT_4x4_50"}))
    r = run("evaluate", "checkerboard", str(tmp_path), "--board", str(board), "--out", str(tmp_path / "o"))
    one_line_error(r, "b.json", "board.dictionary", "did you mean DICT_4X4_50?")


PROTOCOL = (ROOT / "protocols" / "demo-d455.toml").read_text()


@pytest.mark.parametrize(("old", "new", "words"), [
    ("[plan]\n", "[x]\n", ("missing table [plan]",)),
    ("square_length_m = 0.095\n", "", ("square_length_m",)),
    ("distance_m = 0.05\n", "distance_m = -0.05\n", ("tolerances.distance_m",)),
    ("min_minutes = 10.0\n", "min_minutes = -10.0\n", ("warmup.min_minutes",)),
    ("max_minutes = 40.0\n", "max_minutes = 5.0\n", ("warmup.max_minutes",)),
    ("fps = 30\n", "", ("streams.fps",)),
])
def test_protocol_required_and_in_range(tmp_path: Path, old: str, new: str, words: tuple[str, ...],
                                        run: Callable[..., Ran]) -> None:
    assert old in PROTOCOL
    bad = tmp_path / "bad.toml"
    text = PROTOCOL.replace(old, new, 1)
    if new == "[x]\n":  # the whole [plan] table gone, its keys with it
        head, rest = text.split("[x]\n", 1)
        text = head + rest[rest.index("\n["):]
    bad.write_text(text)
    r = run("simulate", "checkerboard", "--protocol", str(bad), "--out", str(tmp_path / "o"), "--frames", "1")
    one_line_error(r, "bad.toml", *words)


@pytest.mark.parametrize(("text", "words"), [
    ('[effects.disparity_noise]\nsigma_px = 0.08\n', ("camera.preset",)),
    ('[camera]\npreset = "d455"\n[effects.thermal_drift]\ncoeff_px_per_c = 0.01\n',
     ("effects.thermal_drift.reference_c", "degC")),
    ('[camera]\npreset = "d455"\nbaseline_m = -0.095\n', ("baseline_m",)),
])
def test_model_required_and_in_range(tmp_path: Path, text: str, words: tuple[str, ...],
                                     run: Callable[..., Ran]) -> None:
    bad = tmp_path / "m.toml"
    bad.write_text(text)
    r = run("simulate", "checkerboard", "--protocol", "demo-d455", "--model", str(bad), "--out",
            str(tmp_path / "o"), "--frames", "1")
    one_line_error(r, "m.toml", *words)


def test_non_utf8_trajectory(tmp_path: Path, run: Callable[..., Ran]) -> None:
    seq = tmp_path / "seq.mcap"
    from depthstation.core.capture.mcap_writer import write_mcap

    info = sample_info(32, 24)
    write_mcap(seq, info, sample_frames(info, 2))
    poses = tmp_path / "poses.txt"
    poses.write_bytes(b"0.0 0 0 0 0 0 0 1\n\xff\xfe junk \x80\n")
    mesh = tmp_path / "room.ply"
    mesh.write_text("ply\n")
    r = run("evaluate", "scan", "--sequence", str(seq), "--poses", str(poses), "--reference", str(mesh),
            "--out", str(tmp_path / "o"))
    one_line_error(r, "poses.txt", "UTF-8")


def test_wrong_board_is_input_error(charuco_dir: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    board = tmp_path / "board.json"
    board.write_text(json.dumps({"type": "checkerboard", "squares_x": 7, "squares_y": 5,
                                 "square_length_m": 0.075}))
    r = run("evaluate", "checkerboard", str(charuco_dir / "pose03"), "--board", str(board), "--out",
            str(tmp_path / "o"), "--frames", "2")
    one_line_error(r, "board.json", "board was found in no frame")


def test_batch_item_outside_its_folder(tmp_path: Path, run: Callable[..., Ran]) -> None:
    m = tmp_path / "m.toml"
    m.write_text('out = "res"\n[[items]]\nkind = "checkerboard"\nout = "../../x"\n'
                 'inputs = { inputs = "a", board = "b.json" }\n')
    r = run("evaluate", "batch", str(m))
    one_line_error(r, "m.toml", "items[0].out", "outside")
    assert not (tmp_path.parent / "x").exists()


def test_mcap_cut_before_its_first_chunk(tmp_path: Path, run: Callable[..., Ran]) -> None:
    from depthstation.core.capture.mcap_writer import write_mcap

    info = sample_info(64, 48)
    full = tmp_path / "full.mcap"
    write_mcap(full, info, sample_frames(info, 3))
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: min(len(data) // 2, 2000)])
    r = run("capture", "info", str(cut))
    one_line_error(r, "cut.mcap", "cut short")


def test_one_recording_under_two_names(small_session: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    """A copy of a standpoint's recording under another name counted twice (explain took the copies
    for independent evidence and discovered a noise term in a null session)."""
    copy = tmp_path / "again.mcap"
    copy.write_bytes((small_session / "standpoint_01.mcap").read_bytes())
    r = run("evaluate", "checkerboard", str(small_session), str(copy),
            "--board", str(small_session.parent / "p.toml"), "--out", str(tmp_path / "o"), "--frames", "3")
    one_line_error(r, "again.mcap", "same recording as", "standpoint_01.mcap")
    assert not (tmp_path / "o").exists()


def test_mcap_cut_before_its_first_complete_frame(tmp_path: Path, run: Callable[..., Ran]) -> None:
    """Its first chunk survived but holds no whole frame: it was imported as a 0-frame session and
    exported as an empty TUM folder with exit 0, and the scan study failed later on 'nothing for
    registration'; now bad input at once, and nothing is written."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from depthstation.core.capture.mcap_writer import McapFileWriter

    info = sample_info(64, 48)
    full = tmp_path / "full.mcap"
    with McapFileWriter(full, info, compression="lz4", chunk_size=2 * 1024) as w:
        for f in sample_frames(info, 6, seed=3):
            w.write(f)
    with full.open("rb") as fh:  # the end of the first chunk that holds data
        reader = StreamReader(fh, emit_chunks=True)
        end = next(fh.tell() for r in reader.records if isinstance(r, Chunk) and r.data)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:end + 1])
    for args in (("capture", "import", str(cut), "--out", str(tmp_path / "imp")),
                 ("capture", "export", str(cut), "--to", "tum", "--out", str(tmp_path / "exp"))):
        r = run(*args)
        one_line_error(r, "cut.mcap", "cut short before its first complete frame")
    assert not (tmp_path / "imp").exists() and not (tmp_path / "exp").exists()


def test_a_png_frame_without_its_depth_image_is_said(png_set: Path) -> None:
    """A frame whose depth file is gone was not even counted as read (a missing colour image was
    warned of): now `frames-rejected` names the folder and the frame."""
    from depthstation.core.capture.png_folder import open_png
    from depthstation.core.run_warnings import collecting

    depth = sorted((png_set / "pose03").glob("frame*_depth.png"))
    k = depth[0].name.split("_")[0][len("frame"):]
    assert (png_set / "pose03" / f"frame{k}_color.png").exists()
    depth[0].unlink()
    with collecting() as said:
        open_png(png_set / "pose03")
    assert [(w.code, w.where) for w in said] == [("frames-rejected", str(png_set / "pose03"))]
    assert f"no depth image (frame {int(k)})" in said[0].message


def test_a_charuco_marker_far_smaller_than_its_square_is_bad_input(tmp_path: Path,
                                                                  run: Callable[..., Ran]) -> None:
    """marker_length_m 0.001 in 75 mm squares passed the board check and ended in 'does this board
    file describe the printed board?' after every frame was tried."""
    board = tmp_path / "b.json"
    board.write_text(json.dumps({"type": "charuco", "squares_x": 7, "squares_y": 5, "square_length_m": 0.075,
                                 "marker_length_m": 0.001, "dictionary": "DICT_4X4_50"}))
    r = run("evaluate", "checkerboard", str(tmp_path), "--board", str(board), "--out", str(tmp_path / "o"))
    one_line_error(r, "b.json", "board.marker_length_m 0.001 m is under a fifth of the square")


def test_a_colour_lens_that_does_not_fit_names_the_intrinsics_and_the_standpoint(
        png_set: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    """The depth stream's focal length given as the colour's: every frame fails on its reprojection
    error, and the refusal named only the board file. It names the standpoint and the intrinsics."""
    depth_stream = {"color.fx": 639.04, "color.fy": 639.04, "color.cx": 635.5, "color.cy": 359.2}
    edit_json(png_set / "camera.json", depth_stream)
    r = run("evaluate", "checkerboard", str(png_set), "--board", str(png_set / "board.json"),
            "--out", str(tmp_path / "o"), "--frames", "2")
    one_line_error(r, "pose03: reprojection error", "camera.json")


def test_a_board_file_with_another_dictionary_than_the_recordings_is_said(
        png_set: Path, tmp_path: Path, run: Callable[..., Ran]) -> None:
    """DICT_4X4_100 shares its first 50 markers with DICT_4X4_50, so the board is found either way;
    the set's own board.json says 4X4_50 and the check compared sizes only."""
    board = json.loads((png_set / "board.json").read_text())
    given = tmp_path / "given.json"
    given.write_text(json.dumps({**board, "dictionary": "DICT_4X4_100"}))
    r = run("evaluate", "checkerboard", str(png_set), "--board", str(given), "--out", str(tmp_path / "o"),
            "--frames", "2", "--no-figures")
    assert r.returncode == 0, r.stderr
    info = json.loads((tmp_path / "o" / "result.json").read_text())
    said = [w["message"] for w in info["warnings"] if w["code"] == "board-mismatch"]
    assert len(said) == 1 and "dictionary 'DICT_4X4_50' there, 'DICT_4X4_100'" in said[0]
    assert "centre, area and corners follow its description" in said[0]
