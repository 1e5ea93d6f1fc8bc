"""explain's inputs in the open world: mixed cameras, short standpoints, missing calibration, models
that disagree with the recording, and bad options, each refused or warned in one line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from test_acquire_cli import SMALL_TOML

from depthstation.app.cli import run_cli

PROTOCOL = (SMALL_TOML.replace("{frames}", "3").replace("width = 640", "width = {width}")
            .replace("height = 360", "height = {height}"))


def _protocol(root: Path, width: int = 320, height: int = 180) -> Path:
    p = root / f"p_{width}.toml"
    p.write_text(PROTOCOL.format(width=width, height=height))
    return p


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 320x180 standpoints of 3 frames (1.0 and 1.5 m); `p_320.toml` beside them is the board."""
    root = tmp_path_factory.mktemp("small")
    assert run_cli(["simulate", "checkerboard", "--model", "d455-ideal", "-p", str(_protocol(root)),
                    "--out", str(root / "s"),
                    "--seed", "1"]) == 0
    return root


def _explain(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    capsys.readouterr()
    code = run_cli(["explain", *args])
    return code, capsys.readouterr().err


def test_mixed_resolutions_refused(small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 640x360 standpoint among 320x180 ones would be simulated at 320x180: refused, each camera's
    standpoints named."""
    big = tmp_path / "big"
    assert run_cli(["simulate", "checkerboard", "--model", "d455-ideal", "-p",
                    str(_protocol(tmp_path, 640, 360)), "--out", str(big),
                    "--standpoint", "standpoint_02"]) == 0
    (big / "standpoint_02.mcap").rename(big / "far.mcap")
    code, err = _explain(capsys, str(small / "s" / "standpoint_01.mcap"), str(big / "far.mcap"),
                         "--board", str(small / "p_320.toml"), "--out", str(tmp_path / "e"))
    assert code == 2, err
    assert "more than one camera" in err
    assert "standpoint_01: color_size [320, 180], depth_size [320, 180]" in err
    assert "far: color_size [640, 360], depth_size [640, 360]" in err
    assert "Traceback" not in err and not (tmp_path / "e").exists()


def test_frames_below_three_refused(small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _explain(capsys, str(small / "s"), "--board", str(small / "p_320.toml"),
                         "--out", str(tmp_path / "e"), "--frames", "2")
    assert code == 2 and "--frames must be at least 3" in err and "Traceback" not in err


def test_two_frame_standpoint_left_out_of_noise_tests(small: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A standpoint of 2 frames among 3-frame ones: warned, and no false noise mismatch (its temporal
    variance has no scatter over frames: t ~ 1e5 before)."""
    short = tmp_path / "short"
    assert run_cli(["simulate", "checkerboard", "--model", "d455-ideal", "-p",
                    str(small / "p_320.toml"), "--out", str(short),
                    "--frames", "2", "--standpoint", "standpoint_02", "--seed", "5"]) == 0
    out = tmp_path / "e"
    code, err = _explain(capsys, str(small / "s" / "standpoint_01.mcap"), str(short / "standpoint_02.mcap"),
                         "--board", str(small / "p_320.toml"), "--out", str(out), "--frames", "3",
                         "--no-resimulate", "--no-discover")
    assert code == 0, err
    result = json.loads((out / "result.json").read_text())
    short_w = [w for w in result["warnings"] if w["code"] == "explain-short-standpoint"]
    assert [w["where"] for w in short_w] == ["standpoint_02"]
    data = json.loads((out / "explain.json").read_text())
    by_stand = {(t["kind"], t["label"]) for t in data["tests"] if t["family"] == "standpoint"}
    assert ("bias", "standpoint_02") in by_stand and ("noise", "standpoint_01") in by_stand
    assert ("noise", "standpoint_02") not in by_stand   # its bias is tested, its noise is not


def test_report_handles_a_remaining_term_without_fit_figures() -> None:
    """window_noise is named for a correlation region from the noise's structure, without delta BIC or
    Wald p: the report said `internal error: KeyError: 'delta_bic'`."""
    from depthstation.evaluate.explain.report import _discovered_md

    data = {"discovered": [], "discovery": {}, "mismatch": {"significant": True},
            "remaining_after": [{"family": "correlation_u", "kind": "noise", "label": "u lag 1 px",
                                 "term": "window_noise", "why_not_selected": "more correlated"},
                                {"family": "distance", "kind": "bias", "label": "1-1.5 m", "term": "poly_z",
                                 "delta_bic": -3.0, "wald_p": 0.2, "why_not_selected": "BIC"}]}
    text = "\n".join(_discovered_md(data, []))
    assert "| `window_noise` | more correlated |" in text
    assert "`poly_z` (delta BIC -3.0, Wald p 0.2)" in text


def _rewrite(src: Path, dst: Path, **info_changes: object) -> Path:
    """A copy of one recording with its stream info changed (a recording made without calibration)."""
    from depthstation.core.capture.mcap_writer import write_mcap
    from depthstation.core.capture.registry import open_inputs

    (rec,) = open_inputs([src])
    meta = dict(rec.metadata)
    device = dict(meta.get("device") or {})
    for k in info_changes:
        device.pop(k, None)
    meta["device"] = device
    write_mcap(dst, replace(rec.info, **info_changes), list(rec.frames()), meta)
    return dst


def test_recording_without_baseline_takes_the_models_with_a_warning(
        small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """No baseline in the recording: the model's is assumed and said (was 95 mm hard-coded in the scan
    form, the model's silently here)."""
    real = tmp_path / "real"
    real.mkdir()
    for name in ("standpoint_01", "standpoint_02"):
        _rewrite(small / "s" / f"{name}.mcap", real / f"{name}.mcap", baseline_m=None)
    model = tmp_path / "m.toml"
    model.write_text('[camera]\npreset = "d455"\nbaseline_m = 0.05\n')
    out = tmp_path / "e"
    code, err = _explain(capsys, str(real), "--board", str(small / "p_320.toml"), "--out", str(out),
                         "--frames", "3", "--model", str(model), "--no-resimulate", "--no-discover")
    assert code == 0, err
    result = json.loads((out / "result.json").read_text())
    (w,) = [w for w in result["warnings"] if w["code"] == "assumed-baseline"]
    assert "50 mm assumed from model 'm'" in w["message"]


def test_model_camera_differing_from_the_recording_is_warned(
        small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Model baseline 50 mm / units 0.1 mm on D455 data, and a D435 model: warned (they are never
    simulated: the recording's camera is); the recording's device is in result.json."""
    model = tmp_path / "m.toml"
    model.write_text('[camera]\npreset = "d455"\nbaseline_m = 0.05\ndepth_units_m = 1e-4\n'
                     'depth_hfov_deg = 70.0\ndepth_to_color_translation_m = [0.0, 0.0, 0.0]\n')
    runs = {"m": str(model), "d435": "d435-ideal", "d455": "d455-ideal"}
    said = {}
    for key, mdl in runs.items():
        out = tmp_path / key
        code, err = _explain(capsys, str(small / "s"), "--board", str(small / "p_320.toml"),
                             "--out", str(out), "--frames", "3", "--model", mdl, "--no-resimulate",
                             "--no-discover")
        assert code == 0, err
        result = json.loads((out / "result.json").read_text())
        said[key] = [w["message"] for w in result["warnings"] if w["code"] == "model-camera"]
        assert "D455" in result["device"]["name"]
    assert len(said["m"]) == 1 and "baseline 50 mm (the recording's 95 mm)" in said["m"][0]
    assert "depth units 0.0001 m (the recording's 0.001 m)" in said["m"][0]
    assert "depth_hfov_deg 70.0" in said["m"][0]
    assert "depth_to_color_translation_m [0.0, 0.0, 0.0]" in said["m"][0]
    assert len(said["d435"]) == 1 and "camera D435" in said["d435"][0]
    assert said["d455"] == []


def test_force_keeps_the_model_inside_out(small: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The model TOML and the board are inputs: listed in result.json, and `--force` refuses to replace a
    folder that holds one (it deleted the model before)."""
    out = tmp_path / "e"
    model = tmp_path / "m.toml"
    model.write_text('[camera]\npreset = "d455"\n')
    args = ["--board", str(small / "p_320.toml"), "--frames", "3", "--no-resimulate", "--no-discover"]
    code, err = _explain(capsys, str(small / "s"), "--out", str(out), "--model", str(model), *args)
    assert code == 0, err
    inputs = json.loads((out / "result.json").read_text())["inputs"]
    assert inputs == [str(small / "s"), str(small / "p_320.toml"), str(model)]
    kept = out / "mine.toml"
    kept.write_text(model.read_text())
    code, err = _explain(capsys, str(small / "s"), "--out", str(out), "--model", str(kept), "--force", *args)
    assert code == 2 and f"holds the input {kept}" in err
    assert kept.is_file()


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated room walk: 24 frames of 256x144, its trajectory and mesh."""
    from depthstation.simulate.scan_sequence import simulate_scan

    out = tmp_path_factory.mktemp("room") / "sim"
    return simulate_scan("room", "walk", "d455-ideal", out, frames=24, width=256, height=144,
                         color=False, seed=5)


def test_scan_frames_without_pose_are_counted(room: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Poses for the first 12 of 24 frames: warned, and the report says 12 frames (it said 24 in 6
    blocks); result.json carries the recording's device."""
    lines = [x for x in (room / "trajectory.txt").read_text().splitlines() if x and not x.startswith("#")]
    half = tmp_path / "half.txt"
    half.write_text("\n".join(lines[:12]) + "\n")
    out = tmp_path / "e"
    code, err = _explain(capsys, "--scan", str(room / "sequence.mcap"), "--poses", str(half),
                         "--reference", str(room / "scene.ply"), "--out", str(out), "--block-frames", "4",
                         "--frames", "24", "--no-resimulate", "--no-discover")
    assert code == 0, err
    data = json.loads((out / "explain.json").read_text())
    assert (data["frames"], data["frames_read"], data["skipped_no_pose"], data["blocks"]) == (12, 24, 12, 3)
    result = json.loads((out / "result.json").read_text())
    (w,) = [w for w in result["warnings"] if w["code"] == "frames-without-pose"]
    assert "12 of 24 frames have no pose" in w["message"] and w["where"] == str(half)
    assert "D455" in result["device"]["name"]
    assert "12 frames in 3 blocks" in (out / "report.md").read_text()


@pytest.mark.parametrize(("extra", "said"), [
    (["--seed", "-1"], "--seed must be 0 or more, not -1"),
    (["--cluster", "notanaddress"], "--cluster 'notanaddress' is not a Dask scheduler address"),
])
def test_bad_explain_options(small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                             extra: list[str], said: str) -> None:
    """Internal errors before (the cluster one after a 40 s wait)."""
    code, err = _explain(capsys, str(small / "s"), "--board", str(small / "p_320.toml"),
                         "--out", str(tmp_path / "e"), "--frames", "3", *extra)
    assert code == 2 and said in err, err


def test_out_that_is_a_file(small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "afile.txt"
    out.write_text("mine\n")
    code, err = _explain(capsys, str(small / "s"), "--board", str(small / "p_320.toml"), "--out", str(out),
                         "--frames", "3")
    assert code == 2 and f"{out}: is a file" in err and out.read_text() == "mine\n"


def test_no_board_pixels_names_the_board_or_the_model(small: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """'no standpoint gave board pixels to compare' was exit 1 naming nothing: a board found in no frame
    names the board file; a model whose simulation has no depth names the model (and warns no-depth)."""
    board = tmp_path / "board.json"
    board.write_text('{"type": "checkerboard", "squares_x": 9, "squares_y": 6, "square_length_m": 0.095}')
    code, err = _explain(capsys, str(small / "s"), "--board", str(board), "--out", str(tmp_path / "a"),
                         "--frames", "3")
    assert code == 2 and f"{board}: the board was found in no frame" in err, err
    model = tmp_path / "neg.toml"
    model.write_text('[camera]\npreset = "d455"\n[effects.dropout]\nmax_disparity_px = 126.0\n'
                     'range_z50_m = 6.5\nrange_width_m = 0.4\ngrazing_deg50 = 80.0\ngrazing_width_deg = 2.5\n'
                     'dark_probability = 0.02\nbase_probability = 1.0\n')  # every pixel lost
    code, err = _explain(capsys, str(small / "s"), "--board", str(small / "p_320.toml"),
                         "--model", str(model), "--out", str(tmp_path / "b"), "--frames", "3")
    assert code == 2 and f"{model}: model 'neg': its simulation of the real standpoints gave no board" in err
    said = [x for x in err.splitlines() if "the simulation holds no depth" in x]  # once for both
    assert len(said) == 1 and said[0].startswith("depthstation: warning: standpoint_01, standpoint_02: "), err


def test_help_keeps_square_brackets_and_pass_points_is_refused(
        room: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Rich took `[board]` for markup ('a protocol TOML with .'); explain offered --register pass-points
    but has no --pass-points option."""
    env = {**os.environ, "COLUMNS": "250"}
    exe = Path(sys.executable).with_name("depthstation")

    def helptext(*cmd: str) -> str:
        return subprocess.run([str(exe), *cmd, "--help"], capture_output=True, text=True, env=env).stdout

    text = helptext("explain")
    assert "a protocol TOML with [board]." in text and "pass-points" not in text
    assert "'fx fy cx cy [w h] [factor]'" in helptext("evaluate", "scan")
    code, err = _explain(capsys, "--scan", str(room / "sequence.mcap"), "--poses",
                         str(room / "trajectory.txt"), "--reference", str(room / "scene.ply"),
                         "--out", str(tmp_path / "e"), "--register", "pass-points")
    assert code == 2 and "explain --scan registers with none, rigid or similarity" in err
