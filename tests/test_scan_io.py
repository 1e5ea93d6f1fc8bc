"""Scan study inputs and the command: TUM trajectories and folders, registration files, reference
clouds (Poisson + cache), and a whole result folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from depthstation.core.capture.registry import open_recording
from depthstation.core.errors import InputError
from depthstation.core.geometry import rodrigues
from depthstation.evaluate.scan.reference import PoissonParams, load_reference, reference_mesh
from depthstation.evaluate.scan.registration import read_pass_points, read_similarity
from depthstation.evaluate.scan.run import ScanOptions
from depthstation.evaluate.scan.synthetic import Room, make_sequence, write_tum_folder
from depthstation.evaluate.scan.trajectory import compose_similarity, read_tum, write_tum


def test_tum_roundtrip_and_matching(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (5, 1, 1))
    for k in range(5):
        poses[k, :3, :3] = rodrigues(rng.normal(size=3))
        poses[k, :3, 3] = rng.normal(size=3)
    t = 1.7e9 + np.arange(5) / 30.0
    path = write_tum(tmp_path / "traj.txt", t[::-1], poses[::-1])  # unsorted on disk
    traj = read_tum(path)
    np.testing.assert_allclose(traj.poses, poses, atol=1e-8)
    assert traj.match(t[2] + 0.004, 0.005) is not None
    assert traj.match(t[2] + 0.016, 0.005) is None
    np.testing.assert_allclose(traj.match(t[3] - 0.001, 0.01), poses[3], atol=1e-8)


def test_tum_rejects_bad_lines(tmp_path: Path) -> None:
    p = tmp_path / "bad.txt"
    p.write_text("# header\n1.0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match="line 2: expected 8 values"):
        read_tum(p)
    # two trackers' files joined: one time, two poses, is refused naming both lines; the same line
    # twice is harmless and kept once
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.0 0.5 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"lines 1 and 3 give two different poses at t=1\.000000000"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    assert len(read_tum(p)) == 2
    # a lost-tracking row of NaN is not a pose: refused naming the line and the value
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 nan 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="line 2: tx not finite"):
        read_tum(p)


def test_similarity_and_pass_point_files(tmp_path: Path) -> None:
    S = compose_similarity(0.98, rodrigues(np.array([0.1, 0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    np.savetxt(tmp_path / "s.txt", S)
    np.testing.assert_allclose(read_similarity(tmp_path / "s.txt"), S)
    bad = S.copy()
    bad[0, 1] += 0.1
    np.savetxt(tmp_path / "bad.txt", bad)
    with pytest.raises(InputError, match="not a scaled rotation"):
        read_similarity(tmp_path / "bad.txt")
    (tmp_path / "nan.txt").write_text("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")  # was: "no grid cell"
    with pytest.raises(InputError, match="row 1, column 4 is nan: the matrix must be finite"):
        read_similarity(tmp_path / "nan.txt")
    (tmp_path / "pp.csv").write_text("x,y,z,x_ref,y_ref,z_ref\n" + "\n".join(
        f"{i},{i * 2},{i * 3},{i + 1},{i},{-i}" for i in range(4)))
    src, dst = read_pass_points(tmp_path / "pp.csv")
    assert src.shape == dst.shape == (4, 3) and dst[2, 0] == 3.0
    (tmp_path / "few.csv").write_text("1,2,3,4,5,6\n")
    with pytest.raises(InputError, match="at least 3"):
        read_pass_points(tmp_path / "few.csv")


def test_unsupported_reference_formats_give_clear_errors(tmp_path: Path) -> None:
    for name in ("scan.e57", "scan.las"):
        p = tmp_path / name
        p.write_bytes(b"\0" * 16)
        try:
            import laspy  # noqa: F401
            import pye57  # noqa: F401
        except ImportError:
            with pytest.raises(InputError, match="optional package"):
                load_reference(p)
    (tmp_path / "x.foo").write_text("1")
    with pytest.raises(InputError, match="unknown reference format"):
        load_reference(tmp_path / "x.foo")


def test_cloud_reference_is_meshed_trimmed_and_cached(tmp_path: Path) -> None:
    import open3d as o3d

    mesh = Room().mesh(segments=64)
    o3d.utility.random.seed(0)
    cloud = mesh.sample_points_uniformly(40_000, use_triangle_normal=True)
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), cloud)
    out = tmp_path / "res"
    m1, path1, info1 = reference_mesh(tmp_path / "cloud.ply", out,
                                      params=PoissonParams(depth=6))
    assert info1["kind"] == "cloud" and not info1["cached"] and path1.is_file()
    assert info1["triangles"] > 1000
    # trimmed mesh lies on the room: vertices within a few cm of the true surface
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    d = scene.compute_distance(o3d.core.Tensor(np.asarray(m1.vertices, dtype=np.float32))).numpy()
    assert np.median(d) < 0.03
    _, path2, info2 = reference_mesh(tmp_path / "cloud.ply", out,
                                     params=PoissonParams(depth=6))
    assert info2["cached"] and path2 == path1
    # one Poisson thread (the default): the same cloud gives the same mesh, bit for bit, so a
    # study repeated in a fresh folder repeats its grid exactly
    m3, _, info3 = reference_mesh(tmp_path / "cloud.ply", tmp_path / "again", params=PoissonParams(depth=6))
    assert not info3["cached"] and info3["poisson"]["threads"] == 1
    np.testing.assert_array_equal(np.asarray(m3.vertices), np.asarray(m1.vertices))
    np.testing.assert_array_equal(np.asarray(m3.triangles), np.asarray(m1.triangles))
    with pytest.raises(InputError, match="--poisson-threads"):
        ScanOptions(poisson_threads=-1).check()


def test_scan_command_writes_a_result_folder(tmp_path: Path) -> None:
    import open3d as o3d
    import typer
    from typer.testing import CliRunner

    from depthstation.evaluate.scan.cli import scan

    seq = make_sequence(frames=8, width=80, height=60, seed=2)
    write_tum_folder(seq, tmp_path / "seq")
    t = np.asarray(seq.timestamps_ns) * 1e-9
    keep = np.arange(8) != 5  # the tracker lost frame 5
    write_tum(tmp_path / "poses.txt", t[keep], seq.poses[keep])
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), Room().mesh(segments=128))
    np.savetxt(tmp_path / "identity.txt", np.eye(4))
    assert open_recording(tmp_path / "seq").frame_count == 8

    app = typer.Typer()
    app.command()(scan)
    app.command("noop")(lambda: None)
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["scan", "--sequence", str(tmp_path / "seq"), "--poses",
                                   str(tmp_path / "poses.txt"), "--reference", str(tmp_path / "room.ply"),
                                   "--out", str(out), "--similarity", str(tmp_path / "identity.txt"),
                                   "--no-icp", "--distance-bin-m", "0.05", "--inclination-bin-deg", "1",
                                   "--min-count-sequence", "20", "--rrd", str(out / "scan.rrd"),
                                   "--per-frame-grids"])
    assert res.exit_code == 0, res.output
    with np.load(out / "grid.npz") as z:
        assert z["count"].shape == (120, 90) and z["mean_m"].shape == z["var_m2"].shape
        assert int(z["count"].sum()) > 0.99 * 7 * 80 * 60 - 200
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"]["used"] == 7 and s["frames"]["skipped_no_pose"] == 1
    assert s["registration"]["scale"] == pytest.approx(1.0)
    assert s["pixels"]["pixels"] == 7 * 80 * 60
    assert s["pixels"]["evaluated"] + s["pixels"]["no_depth"] >= s["pixels"]["pixels"] - s["pixels"]["no_hit"]
    # the model reads too far (positive bias a z^2 + b (inc/90)^2): the pooled mean error is > 0
    assert s["grid"]["mean_m"] > 0.002
    for f in ("fig8_frame.png", "fig9_frame_grid.png", "fig10_sequence_grid.png", "result.json", "scan.rrd"):
        assert (out / f).is_file(), f
    assert json.loads((out / "result.json").read_text())["kind"] == "scan"
    frame_grids = sorted((out / "frame_grids").glob("frame_*.npz"))
    assert len(frame_grids) == 7
    from depthstation.core.grid import Grid

    merged = Grid.load(frame_grids[0])
    for f in frame_grids[1:]:
        merged.merge(Grid.load(f))
    whole = Grid.load(out / "grid.npz")
    np.testing.assert_array_equal(merged.count, whole.count)
    np.testing.assert_allclose(merged.mean, whole.mean, atol=1e-12)


def test_scan_rejects_conflicting_registration_inputs(tmp_path: Path) -> None:
    from depthstation.evaluate.scan.run import ScanOptions, run_scan

    with pytest.raises(InputError, match="either --similarity or --pass-points"):
        run_scan(tmp_path, tmp_path / "p.txt", tmp_path / "r.ply", tmp_path / "o",
                 ScanOptions(similarity=tmp_path / "s.txt", pass_points=tmp_path / "p.csv"))
    with pytest.raises(InputError, match="sequence not found"):
        run_scan(tmp_path / "nope", tmp_path / "p.txt", tmp_path / "r.ply", tmp_path / "o")


def test_tum_folder_images_of_another_size_than_the_intrinsics(tmp_path: Path) -> None:
    """An intrinsics file for another resolution (or a PNG listed but gone) is bad input naming
    the file; the study's kernels read past the image or failed with an internal IndexError."""
    seq = make_sequence(frames=2, width=80, height=60, seed=2)
    folder = write_tum_folder(seq, tmp_path / "seq")
    cam = json.loads((folder / "camera.json").read_text())
    wrong = tmp_path / "intr.json"
    wrong.write_text(json.dumps({**cam, "width": 160, "height": 120}))
    with pytest.raises(InputError, match="gives 160x120 pixels, but the depth images are 80x60") as err:
        open_recording(folder, intrinsics=wrong)
    assert err.value.path == wrong
    last = sorted((folder / "depth").iterdir())[-1]
    last.unlink()
    rec = open_recording(folder)
    with pytest.raises(InputError, match="listed in the association file but not found"):
        list(rec.frames())


@pytest.mark.parametrize("clock", ["milliseconds", "relative"])
def test_poses_on_another_clock_are_bad_input(tmp_path: Path, clock: str) -> None:
    """Pose time stamps in milliseconds, or counted from the first frame, match no frame: said as
    bad input naming the pose file, with both spans (it was an internal registration failure)."""
    import open3d as o3d

    from depthstation.evaluate.scan.run import run_scan

    seq = make_sequence(frames=3, width=80, height=60, seed=2)
    folder = write_tum_folder(seq, tmp_path / "seq")
    t = np.asarray(seq.timestamps_ns) * 1e-9
    t = t * 1000.0 if clock == "milliseconds" else t - t[0]
    write_tum(tmp_path / "poses.txt", t, seq.poses)
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), Room().mesh(segments=32))
    with pytest.raises(InputError, match="no pose time lies within the frames' times") as err:
        run_scan(folder, tmp_path / "poses.txt", tmp_path / "room.ply", tmp_path / "o")
    assert err.value.path == tmp_path / "poses.txt"


def test_figure_frame_outside_the_sequence_is_bad_input(tmp_path: Path) -> None:
    """--figure-frame -1 drew a figure titled 'frame -1'; past the end, Fig. 8 and 9 went missing."""
    import open3d as o3d

    from depthstation.evaluate.scan.run import run_scan

    with pytest.raises(InputError, match="counts from 0"):
        ScanOptions(figure_frame=-1).check()
    for bad, words in (({"tolerance_s": float("nan")}, "--pose-tolerance-s"),
                       ({"tolerance_s": -1.0}, "0 or more"),
                       ({"distance_max_m": 0.0}, "--distance-max-m"),
                       ({"distance_bin_m": -0.1}, "--distance-bin-m")):
        with pytest.raises(InputError, match=words):
            ScanOptions(**bad).check()  # type: ignore[arg-type]
    seq = make_sequence(frames=3, width=80, height=60, seed=2)
    folder = write_tum_folder(seq, tmp_path / "seq")
    write_tum(tmp_path / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), Room().mesh(segments=32))
    with pytest.raises(InputError, match=r"--figure-frame 9: the sequence has 3 frames \(0 to 2\)"):
        run_scan(folder, tmp_path / "poses.txt", tmp_path / "room.ply", tmp_path / "o",
                 ScanOptions(figure_frame=9))


@pytest.mark.parametrize(("name", "text", "says"), [
    ("intrinsics.txt", "60 60 39.5 29.5 80 60 0", "depth_factor must be depth counts per metre"),
    ("intrinsics.txt", "fx fy cx cy\n60 60 39.5 29.5", "line 1: 'fx' is no number"),
    ("intrinsics.txt", "-60 60 39.5 29.5", "fx must be a positive focal length"),
    ("camera.json", '{"fx": 60, "fy": 60, "cx": 39.5, "cy": 29.5, "factor": 0}',
     "factor must be depth counts"),
    ("camera.json", '{"fx": 60, "fy": 60, "cx": 39.5, "cy": 29.5, "depth_units_m": 0}',
     "metres per count must lie in 1e-6 to 0.1"),
    ("camera.json", '{"fx": 60, "fy": 60, "cx": 39.5, "cy": 29.5, "depth_scale": 5000}',
     "Open3D's depth_scale\\? write depth_units_m = 1/5000"),
    ("camera.json", '{"fx": 60, "fy": 60, "cx": 39.5, "cy": 29.5, "depth_units_m": 0.001, "factor": 5000}',
     "the depth units disagree"),
])
def test_a_tum_folders_bad_intrinsics_are_bad_input_naming_the_file(tmp_path: Path, name: str, text: str,
                                                                    says: str) -> None:
    """A zero depth factor was a ZeroDivisionError (exit 1), a header line a ValueError, units of 0 or
    Open3D's 5000 counts per metre gave grids in metres or kilometres: each now names its file."""
    seq = make_sequence(frames=2, width=80, height=60, seed=2)
    folder = write_tum_folder(seq, tmp_path / "seq")
    (folder / "camera.json").unlink()
    (folder / name).write_text(text)
    with pytest.raises(InputError, match=says) as err:
        open_recording(folder)
    assert err.value.path == folder / name


def test_a_tum_depth_list_with_one_time_stamp_twice_is_bad_input(tmp_path: Path) -> None:
    """Two depth images at one time: one of them was posed with the other's pose, without a word."""
    seq = make_sequence(frames=3, width=80, height=60, seed=2)
    folder = write_tum_folder(seq, tmp_path / "seq")
    for assoc in [p for p in folder.glob("*.txt") if p.name != "depth.txt"]:
        assoc.unlink()
    lines = (folder / "depth.txt").read_text().splitlines()
    rows = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    stamp = lines[rows[0]].split()[0]
    lines[rows[1]] = stamp + " " + lines[rows[1]].split()[1]
    (folder / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=f"lines {rows[0] + 1} and {rows[1] + 1} have the same time stamp"):
        open_recording(folder)


def test_a_clouds_normals_facing_both_ways_are_reoriented_and_said(tmp_path: Path) -> None:
    """Normals half of which point out of the room (a cloud sampled with unoriented normals):
    Poisson turned surfaces inside out and the grid's mean moved by 40-110 mm with a passing fit
    check. Now they are turned towards the walk's cameras, and said (`reference-normals`)."""
    import open3d as o3d

    from depthstation.core.run_warnings import collecting

    mesh = Room().mesh(segments=64)
    o3d.utility.random.seed(0)
    cloud = mesh.sample_points_uniformly(40_000, use_triangle_normal=True)
    n = np.asarray(cloud.normals).copy()
    views = np.array([[0.3, -0.75, 0.2], [-0.3, -0.75, -0.2]])
    pts = np.asarray(cloud.points)
    inward = np.einsum("ij,ij->i", n, views[0] - pts) >= 0
    n[~inward] *= -1.0  # all facing the cameras first, then every other one flipped
    n[::2] *= -1.0
    cloud.normals = o3d.utility.Vector3dVector(n)
    o3d.io.write_point_cloud(str(tmp_path / "both.ply"), cloud)
    with collecting() as said:
        m, _, info = reference_mesh(tmp_path / "both.ply", tmp_path / "res", params=PoissonParams(depth=6),
                                    viewpoints=views)
    assert [(w.code, w.where) for w in said] == [("reference-normals", str(tmp_path / "both.ply"))]
    assert info["normals"].startswith("given, 50 % facing away")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    d = scene.compute_distance(o3d.core.Tensor(np.asarray(m.vertices, dtype=np.float32))).numpy()
    assert np.median(d) < 0.03


def test_a_session_folder_given_as_the_sequence_names_its_recording(tmp_path: Path) -> None:
    """`simulate scan` writes a session folder; given as the sequence (explain --scan, evaluate
    scan) it was 'folder is no recording', without a word of the sequence.mcap inside."""
    from depthstation.core.capture.session import Session

    Session.create(tmp_path / "scan16")
    (tmp_path / "scan16" / "sequence.mcap").write_bytes(b"")
    with pytest.raises(InputError, match=r"is a capture session, and this takes one recording: give one of "
                                         r"its recordings \(sequence.mcap\)"):
        open_recording(tmp_path / "scan16")


def test_a_scan_session_given_to_the_checkerboard_study_is_named_a_scan(tmp_path: Path) -> None:
    """A scan walk holds no board: the checkerboard study (and explain) said "the board was found in
    no frame ... does this board file describe the printed board?", blaming the board file."""
    from depthstation.core.capture.session import Session
    from depthstation.evaluate.checkerboard.run import prepare_checkerboard

    Session.create(tmp_path / "walk", scan={"scene": {"kind": "room"}, "trajectory": "walk"})
    board = Path(__file__).parents[1] / "protocols" / "demo-d455.toml"
    with pytest.raises(InputError, match=r"walk: is a scan session .* `evaluate scan` or `explain --scan`"):
        prepare_checkerboard([tmp_path / "walk"], board)
