"""The `depthstation simulate` commands through the console script (exit codes) and the scan output."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from depthstation.app.cli import run_cli

EXE = Path(sys.executable).with_name("depthstation")
Run = Callable[..., subprocess.CompletedProcess[str]]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(EXE), "simulate", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture()
def here(capsys: pytest.CaptureFixture[str]) -> Callable[..., subprocess.CompletedProcess[str]]:
    """`depthstation simulate ...` in this process (the error checks: a process start each cost
    ~2 s of imports); the executable itself is run by the tests above."""

    def call(*args: str) -> subprocess.CompletedProcess[str]:
        capsys.readouterr()
        code = run_cli(["simulate", *args])
        out = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out.out, out.err)

    return call


def test_checkerboard_command_and_errors(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    r = _run("checkerboard", "--protocol", "demo-d455", "--out", str(out), "--frames", "1",
             "--standpoint", "standpoint_04", "--seed", "2")
    assert r.returncode == 0, r.stderr
    names = {p.name for p in out.iterdir()}
    assert {"session.json", "standpoint_04.mcap", "truth.json", "result.json"} <= names
    truth = json.loads((out / "truth.json").read_text())
    assert truth["standpoints"][0]["inclination_deg"] == pytest.approx(35.0)
    r = _run("checkerboard", "--protocol", "demo-d455", "--out", str(out), "--frames", "1")
    assert r.returncode == 2 and "never overwrite" in r.stderr and "Traceback" not in r.stderr
    r = _run("checkerboard", "--model", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "model not found" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\npreset = "d455"\n[effects.disparity_noise]\nsigma = 0.1\n')
    r = _run("checkerboard", "--model", str(bad), "--out", str(tmp_path / "y"))
    assert r.returncode == 2 and "unknown parameter" in r.stderr


def test_scan_writes_sequence_trajectory_and_mesh(tmp_path: Path) -> None:
    from depthstation.core.camera_model import deproject
    from depthstation.core.capture.registry import open_inputs
    from depthstation.simulate.poses import read_tum
    from depthstation.simulate.scene import mesh_scene

    out = tmp_path / "scan"
    r = _run("scan", "--scene", "room", "--trajectory", "walk", "-m", "d455-ideal", "--out", str(out),
             "--frames", "3",
             "--width", "320", "--height", "240")
    assert r.returncode == 0, r.stderr
    stamps, poses = read_tum(out / "trajectory.txt")
    assert len(poses) == 3 and np.allclose(np.diff(stamps), 1 / 30, atol=1e-6)
    (rec,) = open_inputs([out])
    frames = list(rec.frames())
    assert len(frames) == 3
    np.testing.assert_allclose([f.timestamp_ns / 1e9 for f in frames], stamps, atol=1e-6)
    # the measured depth, put into the world with the true pose, lies on the reference mesh
    import open3d as o3d

    mesh = mesh_scene(out / "scene.ply")
    rc = mesh.raycasting_scene()
    f = frames[1]
    z = f.depth_m(rec.info.depth_units_m)
    v, u = np.nonzero(np.isfinite(z))
    pts = deproject(rec.info.depth_intrinsics, u, v, z[v, u])
    world = pts @ poses[1][:3, :3].T + poses[1][:3, 3]
    dist = rc.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
    assert np.median(dist) < 0.02  # within the sensor noise at room scale


def _tum(path: Path, rows: list[tuple[float, ...]]) -> Path:
    body = "".join(" ".join(map(str, r)) + "\n" for r in rows)
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + body)
    return path


@pytest.mark.parametrize(("args", "said"), [
    (["checkerboard", "--seed", "-1"], "--seed must be 0 or more, not -1"),
    (["scan", "--seed", "-1"], "--seed must be 0 or more, not -1"),
    (["scan", "--fps", "0"], "--fps must be a positive number"),
    (["scan", "--fps", "nan"], "--fps must be a positive number"),
    (["scan", "--fps", "-30"], "--fps must be a positive number"),
    (["scan", "--width", "0", "--height", "0"], "--width and --height must be positive"),
    (["scan", "--width", "333", "--height", "180"], "--width/--height: d455: no 333x180 mode"),
    (["checkerboard", "--standpoint", "standpoint_01", "--standpoint", "standpoint_01"],
     "--standpoint standpoint_01 is given more than once"),
])
def test_bad_options_are_bad_input(tmp_path: Path, args: list[str], said: str,
                                   here: Run) -> None:
    """Each was an internal error (exit 1, or a NaN/negative-time output with exit 0) before."""
    r = here(*args, "--out", str(tmp_path / "o"), "--frames", "2")
    assert r.returncode == 2 and said in r.stderr and "internal error" not in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def test_bad_trajectories_name_the_file_and_line(tmp_path: Path,
                                                 here: Run) -> None:
    q = (0.0, 0.0, 0.0, 1.0)
    a, b = (0.0, 0, 0, 0, *q), (0.1, 0, 0, 0, *q)
    cases = {"one.txt": ([a], "trajectory holds 1 pose(s)"),
             "clash.txt": ([a, b, (0.1, 1.0, 0, 0, *q)], "lines 3 and 4 give two different poses at t=0.1"),
             "zeroq.txt": ([a, (0.1, 0, 0, 0, 0, 0, 0, 0)], "line 3: zero quaternion")}
    for name, (rows, said) in cases.items():
        traj = _tum(tmp_path / name, rows)
        r = here("scan", "--trajectory", str(traj), "--out", str(tmp_path / f"o_{name}"), "--width", "256",
                 "--height", "144")
        assert r.returncode == 2 and f"{traj}: {said}" in r.stderr, (name, r.stderr)
    # what the scan study takes (lines out of time order, one line twice) the simulator takes too
    from depthstation.evaluate.scan.trajectory import read_tum
    from depthstation.simulate.poses import read_tum as read_sim

    both = _tum(tmp_path / "both.txt", [b, a, (0.2, 0, 0, 0.1, *q), b])
    stamps, poses = read_sim(both)
    np.testing.assert_array_equal(stamps, read_tum(both).timestamps_s)
    np.testing.assert_array_equal(np.asarray(poses), read_tum(both).poses)


def test_frames_beyond_a_protocols_bound_are_bad_input(tmp_path: Path, here: Run) -> None:
    """--frames 100000000 started writing (40 GB in 10 minutes); a protocol holds at most 100000."""
    r = here("checkerboard", "--frames", "100000000", "--standpoint", "standpoint_01", "--out",
             str(tmp_path / "o"))
    assert r.returncode == 2 and "--frames must lie in 1..100000" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def test_a_broken_scene_mesh_is_bad_input(tmp_path: Path, here: Run) -> None:
    """A NaN vertex made holes in the rendered depth (half a frame gone, exit 0, NaN copied into the
    output scene.ply); a face naming a vertex the file lacks was an internal error (exit 1)."""
    ply = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
           "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
           "-5 -5 3\n5 -5 3\n5 5 3\n{v3}\n3 0 1 2\n3 0 2 {i}\n")
    cases = {"nan.ply": (ply.format(v3="-5 5 nan", i=3), "1 of 4 vertices are not finite numbers"),
             "index.ply": (ply.format(v3="-5 5 3", i=9), "triangle 1 names vertex 9, which the 4 vertices"),
             "empty.ply": ("", "is no PLY file (empty, or it does not begin with 'ply')")}
    for name, (text, said) in cases.items():
        (tmp_path / name).write_text(text)
        r = here("scan", "--scene", str(tmp_path / name), "--out", str(tmp_path / f"o_{name}"),
                 "--width", "256", "--height", "144", "--frames", "2")
        assert r.returncode == 2 and f"{tmp_path / name}: {said}" in r.stderr, (name, r.stderr)
        assert not (tmp_path / f"o_{name}").exists()


def test_a_trajectory_in_milliseconds_is_warned(tmp_path: Path, here: Run) -> None:
    """Times in ms put the frames 33 s apart while the stream said 30 fps, without a word."""
    q = (0.0, 0.0, 0.0, 1.0)
    for name, step, warned in (("ms.txt", 33.333, True), ("s.txt", 1 / 30, False)):
        traj = _tum(tmp_path / name, [(k * step, 0.0, 1.0, 0.0, *q) for k in range(3)])
        r = here("scan", "--trajectory", str(traj), "--out", str(tmp_path / f"o_{name}"), "--width", "256",
                 "--height", "144", "--frames", "2")
        assert r.returncode == 0, r.stderr
        info = json.loads((tmp_path / f"o_{name}" / "result.json").read_text())
        codes = [w["code"] for w in info["warnings"]]
        assert ("trajectory-rate" in codes) is warned, (name, r.stderr)
        if warned:
            assert f"{traj}: its poses are 33.33 s apart" in r.stderr


def test_protocol_mode_error_names_the_protocol(tmp_path: Path,
                                                here: Run) -> None:
    proto = tmp_path / "p.toml"
    proto.write_text('name = "odd"\n[board]\ntype = "checkerboard"\nsquares_x = 7\nsquares_y = 5\n'
                     'square_length_m = 0.095\n[streams]\nwidth = 333\nheight = 180\nfps = 30\n[plan]\n'
                     'frames_per_standpoint = 1\nstart_distance_m = 1.0\nstep_m = 0.5\nmax_distance_m = 1.0\n'
                     'inclinations_deg = [0.0]\n')
    r = here("checkerboard", "--protocol", str(proto), "--out", str(tmp_path / "o"), "--frames", "1")
    assert r.returncode == 2, r.stderr
    assert f"{proto}: [streams] width/height: d455: no 333x180 mode" in r.stderr


@pytest.mark.parametrize(("line", "said"), [
    ("depth_pp_offset_px = [1]", "depth_pp_offset_px must be a list of 2 numbers"),
    ("depth_to_color_translation_m = [0.1]", "depth_to_color_translation_m must be a list of 3 numbers"),
    ("depth_to_color_translation_m = 5", "depth_to_color_translation_m must be a list of 3 numbers"),
    ('baseline_m = "abc"', "baseline_m must be a number, got 'abc'"),
    ("depth_to_color_translation_m = [-59, 0, 0]", "depth_to_color_translation_m must be in metres"),
    # each ran: every pixel 1 m (a millimetre typed as metres), or an internal error (exit 1)
    ("depth_units_m = 1.0", "depth_units_m must be metres per depth count (1e-6 to 0.01"),
    ("depth_units_m = inf", "depth_units_m must be positive and finite"),
    ("depth_pp_offset_px = [nan, 0.0]", "depth_pp_offset_px must be finite pixels"),
])
def test_model_camera_values_of_the_wrong_shape(tmp_path: Path, line: str, said: str,
        here: Run) -> None:
    model = tmp_path / "m.toml"
    model.write_text(f'[camera]\npreset = "d455"\n{line}\n')
    r = here("model", str(model))
    assert r.returncode == 2 and f"{model}: model: [camera] {said}" in r.stderr, r.stderr


@pytest.mark.parametrize(("table", "said"), [
    ("[effects.term_noise_frame_common]\nc = -1.0", "[effects.term_noise_frame_common] is a variance (px^2) "
                                                     "below zero everywhere (c = -1)"),
    ("[effects.term_noise_distance_poly1]\nc1 = -0.5", "[effects.term_noise_distance_poly1] is a variance"),
    ("[effects.term_noise_frame_common]", "missing key 'effects.term_noise_frame_common.c'"),
    ("[effects.term_bias_time_poly1]\nc1 = 0.1", "missing key 'effects.term_bias_time_poly1.ref_time_s'"),
    ("[effects.quantization]\ndisparity_step_px = 0.03125\ndepth_unit_m = 0.0001",
     "'effects.quantization.depth_unit_m' = 0.0001 m differs from the camera's depth units 0.001 m"),
    # each ran without a word: range dropout off (millimetres), depths thrown to 7.8 m (per cent as a
    # ratio), a division by zero, a 3.6 TiB allocation
    ("[effects.dropout]\nmax_disparity_px = 126.0\nrange_z50_m = 6500.0\nrange_width_m = 400.0\n"
     "grazing_deg50 = 80.0\ngrazing_width_deg = 2.5\ndark_probability = 0.02\nbase_probability = 0.0",
     "effect 'dropout': range_z50_m (0 to 100)"),
    ("[effects.flying_pixels]\nedge_probability = 0.3\nwidth_px = 1.0\nspread_ratio = 5.0",
     "effect 'flying_pixels': spread_ratio is a fraction of z (0 to 1), got 5"),
    ("[effects.reference_pose_noise]\ncorner_sigma_px = 0.1\nboard_size_m = 0.0",
     "effect 'reference_pose_noise': corner_sigma_px >= 0"),
    ("[effects.window_noise]\nsigma_px = 0.07\nwindow_px = 1e6", "effect 'window_noise': sigma_px >= 0"),
    ("[effects.depth_scale]\nscale_error = 2.0",
     "effect 'depth_scale': scale_error is relative (-0.5 to 0.5), got 2"),
])
def test_model_effects_checked(tmp_path: Path, table: str, said: str,
        here: Run) -> None:
    """Each was accepted: a negative variance clipped to nothing, a missing coefficient taken as 0, a
    quantisation unit the camera's units override."""
    model = tmp_path / "m.toml"
    model.write_text(f'[camera]\npreset = "d455"\n{table}\n')
    r = here("model", str(model))
    assert r.returncode == 2 and f"{model}: model: {said}" in r.stderr, r.stderr


def test_model_with_positive_and_sign_changing_terms_loads(tmp_path: Path,
        here: Run) -> None:
    """The checks refuse only what is wrong: a time term's negative slope is a variance that grows
    towards earlier times, and every parameter given loads."""
    model = tmp_path / "m.toml"
    model.write_text('[camera]\npreset = "d455"\n[effects.term_noise_time_poly1]\nc1 = -0.001\n'
                     'ref_time_s = 100.0\n[effects.term_noise_frame_common]\nc = 0.01\n')
    r = here("model", str(model))
    assert r.returncode == 0 and "[effects.term_noise_time_poly1]" in r.stdout, r.stderr


def test_a_model_that_renders_no_depth_is_warned(tmp_path: Path, here: Run) -> None:
    """A dropout that takes every pixel (base probability 1): every pixel 0, exit 0 and no word
    before (depth units of 1e-9 m, which put every z beyond 16 bits, are refused now)."""
    model = tmp_path / "tiny.toml"
    model.write_text('[camera]\npreset = "d455"\n[effects.dropout]\nmax_disparity_px = 126.0\n'
                     'range_z50_m = 6.5\nrange_width_m = 0.4\ngrazing_deg50 = 80.0\ngrazing_width_deg = 2.5\n'
                     'dark_probability = 0.02\nbase_probability = 1.0\n')
    proto = tmp_path / "p.toml"  # the demo protocol at 640x360: a quarter of the rendering
    proto.write_text((Path(__file__).parents[1] / "protocols" / "demo-d455.toml").read_text()
                     .replace("width = 1280", "width = 640").replace("height = 720", "height = 360"))
    r = here("checkerboard", "--protocol", str(proto), "-m", str(model), "--out", str(tmp_path / "c"),
             "--frames", "1", "--standpoint", "standpoint_01")
    assert r.returncode == 0 and "standpoint_01: the simulation holds no depth" in r.stderr
    assert f"model '{model}'" in r.stderr
    r = _run("scan", "-m", str(model), "--out", str(tmp_path / "s"), "--frames", "2", "--width", "256",
             "--height", "144")
    assert r.returncode == 0 and "sequence: the simulation holds no depth in any of its 2 frames" in r.stderr
    codes = [w["code"] for w in json.loads((tmp_path / "s" / "result.json").read_text())["warnings"]]
    assert codes == ["no-depth"]
    r = _run("checkerboard", "--protocol", "demo-d455", "--out", str(tmp_path / "ok"), "--frames", "1",
             "--standpoint", "standpoint_01")
    assert r.returncode == 0 and "no depth" not in r.stderr


def test_model_lists_every_effect_with_its_source_and_units_draw_others(here: Run) -> None:
    """`simulate model d455` names each effect's meaning and source above its table; `--unit-seed N`
    is another unit: its depth scale, disparity offset and static pattern differ from the preset's,
    the same for the same N, within Intel's spec; an ideal model stays ideal; a negative seed is bad
    input."""
    from depthstation.simulate.model import load_model, model_from_toml
    from depthstation.simulate.units import unit_spread

    r = here("model", "d455")
    assert r.returncode == 0, r.stderr
    preset = model_from_toml(r.stdout)
    assert r.stdout.count("# source: ") == len(preset.effects) == len(load_model("d455").effects)
    one, again = here("model", "d455", "--unit-seed", "3"), here("model", "d455", "--unit-seed", "3")
    assert one.returncode == 0 and one.stdout == again.stdout
    unit = model_from_toml(one.stdout)
    s_scale, s_offset = unit_spread(preset)
    for name, param, sigma in (("depth_scale", "scale_error", s_scale),
                               ("disparity_offset", "offset_px", s_offset)):
        a, b = preset.effect(name).params[param], unit.effect(name).params[param]
        assert a != b and abs(b) < 4 * sigma, (name, a, b)
    seeds = [m.effect("static_pattern").params["pattern_seed"] for m in (preset, unit)]
    assert seeds[0] != seeds[1]
    ideal = model_from_toml(here("model", "d455-ideal", "--unit-seed", "3").stdout)
    assert [e.name for e in ideal.effects] == [e.name for e in load_model("d455-ideal").effects]
    bad = here("model", "d455", "--unit-seed", "-1")
    assert bad.returncode == 2 and "--unit-seed" in bad.stderr
