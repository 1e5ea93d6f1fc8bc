"""Registration that measures, not hides (`evaluate scan --register`).

A simulated walk whose depth is 0.5 % too long (a depth-scale error, what the study exists to
measure): with exact poses and the default flags the grid shows the injected bias; with a SLAM
trajectory built on that depth (translations 0.5 % too long too, as RGB-D SLAM would make them)
`--register similarity` reports the depth-scale error its scale stands for, and with the poses put
back the grid still shows the bias; a trajectory in another frame is said not to fit the reference.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scan_expect import model_grids

from depthstation.core.errors import InputError
from depthstation.core.grid import Grid
from depthstation.core.run_warnings import collecting
from depthstation.evaluate.scan.registration import Registration
from depthstation.evaluate.scan.run import ScanOptions, run_scan, say_registration
from depthstation.evaluate.scan.trajectory import read_tum, write_tum

pytest.importorskip("open3d")
SCALE_ERROR = 0.005
BINS = {"distance_bin_m": 0.1, "inclination_bin_deg": 5.0}


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from depthstation.simulate.model import load_model
    from depthstation.simulate.poses import walk_around
    from depthstation.simulate.poses import write_tum as write_poses
    from depthstation.simulate.scan_sequence import simulate_scan

    model = load_model("d455-ideal").without_effect("flying_pixels").with_effect("depth_scale",
                                                                           scale_error=SCALE_ERROR)
    root = tmp_path_factory.mktemp("walk")
    n = 16
    poses = walk_around(np.array([0.0, -0.75, 0.0]), radius_m=2.0, speed_m_s=2 * np.pi * 2.0 * 30 / n,
                        frames=n, bob_m=0.0)
    write_poses(root / "walk.txt", np.arange(n) / 30.0, poses)
    out = root / "session"
    simulate_scan("room", root / "walk.txt", model, out, width=640, height=480, color=False, seed=7)
    # what RGB-D SLAM run on this depth would estimate: the whole trajectory 0.5 % too large
    truth = read_tum(out / "trajectory.txt")
    slam = truth.transformed(np.diag([1 + SCALE_ERROR] * 3 + [1.0]))
    write_tum(root / "slam.txt", slam.timestamps_s, slam.poses)
    return {"dir": out, "model": model, "slam": root / "slam.txt"}


def expected_grid(d: Path, model: Any, grid: Grid) -> Grid:
    """The model's own bias per cell (injected scale error included), evaluated at the pixels used."""
    return model_grids(d, model, grid)[0]


def test_default_flags_show_the_injected_bias(walk: dict[str, Any], tmp_path: Path) -> None:
    d = walk["dir"]
    with collecting() as found:
        s = run_scan(d / "sequence.mcap", d / "trajectory.txt", d / "scene.ply", tmp_path / "o",
                     ScanOptions(min_count_sequence=100, **BINS))  # type: ignore[arg-type]
    assert s["registration"]["mode"] == "none" and s["registration"]["absorbed"] is None
    assert not [w for w in found if w.code in ("registration-fit", "absorbed-scale")], found
    grid = Grid.load(tmp_path / "o" / "grid.npz")
    exp = expected_grid(d, walk["model"], grid)
    well = grid.count >= 5000
    assert well.sum() >= 10
    diff = np.abs(grid.mean_m - exp.mean_m)
    # the default model shares its matching noise over a window: the pixels of a frame are not
    # independent, and the frames-as-clusters standard error is the honest one (n^-1/2 is not)
    se = grid.se_m
    # within 1 mm wherever the cell mean is pinned down that far (3 SE < 1 mm); beyond, within 4 SE
    # where at least 5 effective frames saw the cell (fewer clusters give no usable SE: beyond 5 m
    # this 16-frame walk sees some cells in 3 or 4 frames; their u95_m says so: t with 2-3 dof)
    sharp = well & (3 * se < 1e-3)
    assert sharp.sum() >= 10
    assert np.all(diff[sharp] <= 1e-3), np.c_[grid.distance_centers_m[np.nonzero(sharp)[0]], diff[sharp]]
    feff = grid.effective_frames
    assert feff is not None
    seen = well & (feff >= 5)
    assert seen.sum() >= 0.75 * well.sum()
    assert np.all(diff[seen] <= np.maximum(1e-3, 4 * se[seen]))
    assert np.all(diff[well] <= np.maximum(1e-3, 2 * grid.u95_m[well]))
    # the bias the study exists to measure is there: 0.5 % of the distance
    assert np.nanmax(grid.mean_m[well]) > 0.01


def test_similarity_reports_the_depth_scale_error_it_absorbs(walk: dict[str, Any], tmp_path: Path) -> None:
    d = walk["dir"]
    with collecting() as found:
        s = run_scan(d / "sequence.mcap", walk["slam"], d / "scene.ply", tmp_path / "o",
                     ScanOptions(register="similarity", min_count_sequence=100, **BINS))  # type: ignore[arg-type]
    absorbed = s["registration"]["absorbed"]
    assert absorbed is not None
    assert absorbed["depth_scale_error"] == pytest.approx(SCALE_ERROR, abs=5e-4)
    lo, hi = absorbed["depth_scale_error_band95"]
    # the band: the 2 frames registered (every 10th of 16) as 2 clusters, t with 1 dof: wide
    # (0.434 to 0.607 % round 0.520 %)
    assert lo < SCALE_ERROR < hi and hi - lo < 4e-3
    band = s["registration"]["band95"]
    assert band["blocks"] == 2 and len(band["rotation_u95_deg"]) == len(band["translation_u95_m"]) == 3
    said = [w for w in found if w.code == "absorbed-scale"]
    assert len(said) == 1
    assert re.search(r"absorbs a depth-scale error of \+0\.(4[6-9]|5[0-4])", said[0].message), said[0].message
    assert "absorbs" in s["registration_caption"]
    # the scale put the SLAM trajectory back on the true poses: the grid shows the depth error, a
    # bias growing as 0.5 % of the distance (a registration good to ~0.01 % leaves mm at grazing
    # angles, so the slope of the cell means, not each cell, is the check)
    grid = Grid.load(tmp_path / "o" / "grid.npz")
    exp = expected_grid(d, walk["model"], grid)
    well = grid.count >= 5000
    dist = np.broadcast_to(grid.distance_centers_m[:, None], grid.shape)[well]
    slope = float(np.sum(dist * grid.mean_m[well]) / np.sum(dist * dist))
    slope_exp = float(np.sum(dist * exp.mean_m[well]) / np.sum(dist * dist))
    assert slope == pytest.approx(slope_exp, abs=5e-4) and slope > 0.8 * SCALE_ERROR


def test_a_trajectory_in_another_frame_is_said_not_to_fit(walk: dict[str, Any], tmp_path: Path) -> None:
    d = walk["dir"]
    truth = read_tum(d / "trajectory.txt")
    moved = truth.transformed(np.array([[1, 0, 0, 0.3], [0, 1, 0, 0.0], [0, 0, 1, 0.2], [0, 0, 0, 1.0]]))
    write_tum(tmp_path / "moved.txt", moved.timestamps_s, moved.poses)
    with collecting() as found:
        run_scan(d / "sequence.mcap", tmp_path / "moved.txt", d / "scene.ply", tmp_path / "o",
                 ScanOptions(min_count_sequence=100, frames=4, **BINS))  # type: ignore[arg-type]
    said = [w for w in found if w.code == "registration-fit"]
    assert len(said) == 1 and "does not fit the reference" in said[0].message
    assert "--register" in said[0].message


@pytest.mark.parametrize("mistake", ["y-up", "millimetres", "one wall"])
def test_a_reference_in_other_axes_or_units_is_said_not_to_fit(walk: dict[str, Any], tmp_path: Path,
                                                                mistake: str) -> None:
    """The scene turned Y-up, scaled to millimetres (every ray meets a wall ~1000x too far: the
    noise allowance grew with the reference's depth) or cut to one wall (most rays meet no surface:
    those never counted as off)."""
    import open3d as o3d

    d = walk["dir"]
    mesh = o3d.io.read_triangle_mesh(str(d / "scene.ply"))
    if mistake == "y-up":
        mesh.rotate(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), center=np.zeros(3))
    elif mistake == "millimetres":
        mesh.scale(1000.0, center=np.array([0.0, -0.75, 0.0]))  # about the walk: every ray still hits
    else:
        v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        x = v[t].mean(axis=1)[:, 0]
        mesh.remove_triangles_by_mask(x < x.max() - 0.05)
        mesh.remove_unreferenced_vertices()
    o3d.io.write_triangle_mesh(str(tmp_path / "wrong.ply"), mesh)
    with collecting() as found:
        run_scan(d / "sequence.mcap", d / "trajectory.txt", tmp_path / "wrong.ply", tmp_path / "o",
                 ScanOptions(min_count_sequence=100, frames=4, **BINS))  # type: ignore[arg-type]
    said = [w for w in found if w.code == "registration-fit"]
    assert len(said) == 1 and "does not fit the reference" in said[0].message, found
    fit = json.loads((tmp_path / "o" / "summary.json").read_text())["fit_check"]
    assert not fit["fits"]
    if mistake == "one wall":
        assert fit["miss_share"] > 0.5 and "see no reference surface" in said[0].message


def test_a_mesh_with_a_nan_vertex_is_refused_naming_it(walk: dict[str, Any], tmp_path: Path) -> None:
    """One NaN vertex on the table top opened holes the rays passed through to the floor: the grid
    moved (mean +0.7 -> -3.5 mm) with exit 0 and no word. Now bad input, naming the vertex."""
    import open3d as o3d

    from depthstation.core.errors import InputError

    d = walk["dir"]
    mesh = o3d.io.read_triangle_mesh(str(d / "scene.ply"))
    v = np.asarray(mesh.vertices).copy()
    v[7] = np.nan
    mesh.vertices = o3d.utility.Vector3dVector(v)
    o3d.io.write_triangle_mesh(str(tmp_path / "nan.ply"), mesh)
    with pytest.raises(InputError, match=r"nan\.ply: 1 of \d+ vertices are not finite .* vertex 7"):
        run_scan(d / "sequence.mcap", d / "trajectory.txt", tmp_path / "nan.ply", tmp_path / "o",
                 ScanOptions(frames=4, **BINS))  # type: ignore[arg-type]
    assert not (tmp_path / "o" / "grid.npz").exists()


def test_frames_without_a_pose_are_said_and_poses_between_the_frames_are_bad_input(
        walk: dict[str, Any], tmp_path: Path) -> None:
    """A tracker that lost every other frame: the grid holds half the walk, said
    (`frames-without-pose`, with the counts). Poses stamped between the frames (another rate, an
    offset of 13 ms against a 10 ms tolerance): bad input naming the trajectory, not an internal
    'nothing for registration' with exit 1."""
    from depthstation.core.errors import InputError

    d = walk["dir"]
    truth = read_tum(d / "trajectory.txt")
    write_tum(tmp_path / "half.txt", truth.timestamps_s[::2], truth.poses[::2])
    with collecting() as found:
        run_scan(d / "sequence.mcap", tmp_path / "half.txt", d / "scene.ply", tmp_path / "o",
                 ScanOptions(min_count_sequence=100, **BINS))  # type: ignore[arg-type]
    said = [w for w in found if w.code == "frames-without-pose"]
    n = len(truth.timestamps_s)
    assert len(said) == 1 and said[0].message.startswith(f"{n // 2} of {n} frames have no pose")
    assert said[0].where == str(tmp_path / "half.txt")
    info = json.loads((tmp_path / "o" / "result.json").read_text())
    assert "frames-without-pose" in [w["code"] for w in info["warnings"]]
    # poses for the odd frames only: none on the frames registration samples (every 10th), yet the
    # study has half the walk to evaluate (it must not be refused as "no frame has a pose")
    write_tum(tmp_path / "odd.txt", truth.timestamps_s[1::2], truth.poses[1::2])
    with collecting() as found:
        run_scan(d / "sequence.mcap", tmp_path / "odd.txt", d / "scene.ply", tmp_path / "o3",
                 ScanOptions(min_count_sequence=100, **BINS))  # type: ignore[arg-type]
    assert [w.code for w in found].count("frames-without-pose") == 1
    write_tum(tmp_path / "between.txt", truth.timestamps_s + 0.013, truth.poses)
    with pytest.raises(InputError, match=r"between\.txt: no frame has a pose within 0\.01 s .*13\.0 ms"):
        run_scan(d / "sequence.mcap", tmp_path / "between.txt", d / "scene.ply", tmp_path / "o2",
                 ScanOptions(**BINS))  # type: ignore[arg-type]


def test_a_registration_on_the_cameras_own_depth_says_it_absorbs_its_error(tmp_path: Path) -> None:
    """Rigid (and similarity) registration fits the trajectory on the depth it then evaluates: an
    audit's 1 % + 2 mm depth error read -0.3 mm in the 0.5-1.5 m band and 30 mm at 4 m (truth 15
    and 42 mm), with no word. Independent poses (none, pass-points) are not said to absorb."""
    for mode, said in (("rigid", True), ("similarity", True), ("none", False), ("pass-points", False)):
        reg = Registration(np.eye(4), mode, icp={"band_m": [0.5, 2.0]}, mode=mode)
        with collecting() as warnings:
            say_registration(reg, None, tmp_path / "seq")
        codes = [w.code for w in warnings]
        assert ("registration-absorbs" in codes) == said, (mode, codes)
        if said:
            text = next(w.message for w in warnings if w.code == "registration-absorbs")
            assert "0.5-2 m" in text and "--register pass-points" in text


def test_a_trajectory_too_far_to_register_is_bad_input(walk: dict[str, Any], tmp_path: Path) -> None:
    """Rigid registration from a trajectory 20 m and 30 deg off: nothing to start from. An input
    the user can mend (a start by --similarity or pass points), exit 2; before, exit 1."""
    d = walk["dir"]
    truth = read_tum(d / "trajectory.txt")
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    far = truth.transformed(np.array([[c, -s, 0, 20.0], [s, c, 0, 0.0], [0, 0, 1, 0.5], [0, 0, 0, 1.0]]))
    write_tum(tmp_path / "far.txt", far.timestamps_s, far.poses)
    with pytest.raises(InputError, match="--similarity FILE or --pass-points FILE") as err:
        run_scan(d / "sequence.mcap", tmp_path / "far.txt", d / "scene.ply", tmp_path / "o",
                 ScanOptions(min_count_sequence=100, frames=4, register="rigid", **BINS))  # type: ignore[arg-type]
    assert err.value.path == tmp_path / "far.txt"
