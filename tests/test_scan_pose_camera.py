"""Which camera of the rig the trajectory describes, and on which clock. RGB-D SLAM on depth
aligned to colour (ORB-SLAM3 on a RealSense, as in the paper) gives the colour camera's poses; put
on the depth camera's rays they are off by the lever arm (59 mm on a D455), an error that grows
with the inclination. The study checks the other camera's poses on the data and says so;
`--poses-of color` moves them; `--pose-offset-s` moves the poses' clock, `--pose-convention`
reads world-to-camera and w-first files, and a file that fits only read so is named."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from console import run_console as _cli
from scipy.spatial.transform import Rotation

from depthstation.core.camera_model import Extrinsics
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.geometry import rodrigues
from depthstation.core.grid import Grid
from depthstation.core.lazy_open3d import open3d
from depthstation.core.parallel import ChunkRunner
from depthstation.core.run_warnings import RunWarning, collecting
from depthstation.evaluate.scan.run import ScanJob, ScanOptions, prepare_scan, run_prepared
from depthstation.evaluate.scan.synthetic import Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A walk whose recording carries a D455-like depth-to-colour transform, and its trajectory
    written twice: as the depth camera's (the truth) and as the colour camera's."""
    root = tmp_path_factory.mktemp("rig")
    seq = make_sequence(frames=12, width=80, height=60, seed=2)
    colour_from_depth = np.eye(4)  # p_colour = R p_depth + t
    colour_from_depth[:3, :3] = rodrigues([0.002, -0.003, 0.001])
    colour_from_depth[:3, 3] = [-0.0591, 0.0001, 0.0003]
    info = dataclasses.replace(seq.info, depth_to_color=Extrinsics.from_matrix(colour_from_depth))
    write_mcap(root / "seq.mcap", info, seq.frames())
    t = np.asarray(seq.timestamps_ns) * 1e-9
    write_tum(root / "depth_poses.txt", t, seq.poses)
    write_tum(root / "colour_poses.txt", t, seq.poses @ np.linalg.inv(colour_from_depth))
    write_tum(root / "late_poses.txt", t + 2 / seq.info.fps, seq.poses)  # a clock 2 frames late
    # world-to-camera with the quaternion's w first (COLMAP's images.txt order), by the test's own hand
    w2c = np.linalg.inv(seq.poses)
    q = Rotation.from_matrix(w2c[:, :3, :3]).as_quat()  # x y z w
    rows = np.column_stack([t, w2c[:, :3, 3], q[:, 3], q[:, :3]])
    np.savetxt(root / "colmap_poses.txt", rows, fmt="%.9f", header="timestamp tx ty tz qw qx qy qz")
    np.savetxt(root / "identity.txt", np.eye(4))
    open3d().io.write_triangle_mesh(str(root / "room.ply"), Room().mesh(segments=128))
    return root


def _study(root: Path, poses: str, poses_of: str = "depth", offset_s: float = 0.0,
           convention: str = "tum") -> tuple[ScanJob, Grid, list[RunWarning]]:
    opt = ScanOptions(similarity=root / "identity.txt", distance_bin_m=0.25, inclination_bin_deg=5.0,
                      min_count_sequence=20, poses_of=poses_of, pose_offset_s=offset_s,
                      pose_convention=convention)
    with collecting() as said, ChunkRunner(1) as runner:
        job = prepare_scan(root / "seq.mcap", root / poses, root / "room.ply",
                           root / f"{poses}_{poses_of}_{offset_s:g}_{convention}", opt)
        grid = run_prepared(job, runner).grid
    return job, grid, list(said)


def _mean(g: Grid) -> float:
    return float(np.average(g.mean[g.count > 0], weights=g.count[g.count > 0]))


def test_depth_poses_are_used_as_they_are_and_checked(rig: Path) -> None:
    job, _, said = _study(rig, "depth_poses.txt")
    assert not [w for w in said if w.code == "poses-camera"], said
    cam: dict[str, Any] = job.camera
    assert cam["checked"] and cam["poses_of"] == "depth" and cam["other"] == "color"
    assert cam["lever_arm_m"] == pytest.approx(0.0591, abs=1e-3)
    assert not cam["other_fits_better"]


def test_colour_poses_taken_for_the_depth_cameras_are_said(rig: Path) -> None:
    truth = _study(rig, "depth_poses.txt")[1]
    job, grid, said = _study(rig, "colour_poses.txt")
    warned = [w for w in said if w.code == "poses-camera"]
    assert len(warned) == 1 and "--poses-of color" in warned[0].message
    assert job.camera["other_fits_better"]
    # what the warning is about: the grid is biased by the lever arm (tens of mm on inclined walls)
    assert abs(_mean(grid) - _mean(truth)) > 0.01


def test_poses_of_color_moves_them_to_the_depth_camera(rig: Path) -> None:
    truth = _study(rig, "depth_poses.txt")[1]
    job, grid, said = _study(rig, "colour_poses.txt", "color")
    assert not [w for w in said if w.code == "poses-camera"], said
    # the same grid but for the pose file's text precision (the colour poses went through TUM's text)
    assert np.abs(grid.count - truth.count).sum() <= 4
    both = (grid.count >= 20) & (truth.count >= 20)
    assert both.sum() > 50
    np.testing.assert_allclose(grid.mean[both], truth.mean[both], atol=1e-6)
    assert job.camera["poses_of"] == "color" and not job.camera["other_fits_better"]


def test_depth_poses_given_as_colour_ones_are_said(rig: Path) -> None:
    _, _, said = _study(rig, "depth_poses.txt", "colour")  # the British spelling is accepted
    assert any(w.code == "poses-camera" and "--poses-of depth" in w.message for w in said), said


def test_an_unknown_camera_is_a_usage_error(rig: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _cli(["evaluate", "scan", "--sequence", str(rig / "seq.mcap"), "--poses",
                         str(rig / "depth_poses.txt"), "--reference", str(rig / "room.ply"), "--out",
                         str(tmp_path / "r"), "--poses-of", "infrared"], capsys)
    assert code == 2 and "--poses-of" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_pose_offset_moves_the_poses_clock_onto_the_frames(rig: Path) -> None:
    truth = _study(rig, "depth_poses.txt")[1]
    job, grid, _ = _study(rig, "late_poses.txt", offset_s=-2 / 30)
    assert job.camera["offset_s"] == pytest.approx(-2 / 30)
    assert np.abs(grid.count - truth.count).sum() <= 4
    both = (grid.count >= 20) & (truth.count >= 20)
    np.testing.assert_allclose(grid.mean[both], truth.mean[both], atol=1e-6)


def test_after_icp_the_other_camera_is_not_checked_and_says_why(rig: Path) -> None:
    opt = ScanOptions(register="rigid", distance_bin_m=0.25, inclination_bin_deg=5.0, min_count_sequence=20)
    with collecting():
        job = prepare_scan(rig / "seq.mcap", rig / "colour_poses.txt", rig / "room.ply", rig / "icp", opt)
    assert job.camera["checked"] is False and "ICP" in job.camera["reason"]


@pytest.mark.parametrize("aligned", [True, False])
def test_poses_of_color_on_one_camera_or_without_extrinsics(rig: Path, tmp_path: Path, aligned: bool) -> None:
    """Depth aligned to colour is the colour camera's: nothing to move, nothing to say. A recording
    without extrinsics (identity) cannot move colour poses: said."""
    seq = make_sequence(frames=4, width=48, height=36, seed=2)
    info = dataclasses.replace(seq.info, depth_aligned_to_color=aligned)
    write_mcap(tmp_path / "seq.mcap", info, seq.frames())
    opt = ScanOptions(similarity=rig / "identity.txt", poses_of="color", min_count_sequence=20)
    with collecting() as said:
        job = prepare_scan(tmp_path / "seq.mcap", rig / "depth_poses.txt", rig / "room.ply", tmp_path / "r",
                           opt)
    assert job.camera["checked"] is False
    assert ("aligned" in job.camera["reason"]) == aligned
    assert any(w.code == "poses-camera" for w in said) == (not aligned), said


REAL_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "librealsense-d435-bag" / \
    "single_depth_color_640x480.bag"


def test_the_real_bags_rig_is_librealsenses_depth_to_colour() -> None:
    """Our reader's depth_to_color of a real RealSense Viewer bag against pyrealsense2 playing the
    same file (librealsense's own code): the transform --poses-of color and the check use."""
    if not REAL_BAG.is_file():
        pytest.skip(f"{REAL_BAG} is absent (../shared/data)")
    rs = pytest.importorskip("pyrealsense2")
    from depthstation.core.capture.registry import open_recording
    from depthstation.evaluate.scan.run import depth_to_colour

    dev = rs.context().load_device(str(REAL_BAG))
    dev.as_playback().set_real_time(False)
    profiles = {sp.stream_type(): sp for s in dev.query_sensors() for sp in s.get_stream_profiles()}
    e = profiles[rs.stream.depth].get_extrinsics_to(profiles[rs.stream.color])
    expected = np.eye(4)
    expected[:3, :3] = np.asarray(e.rotation).reshape(3, 3).T  # librealsense stores it column-major
    expected[:3, 3] = e.translation
    rec = open_recording(REAL_BAG)
    ours = depth_to_colour(rec)
    assert ours is not None
    np.testing.assert_allclose(ours, expected, atol=1e-6)
    p = np.array([0.1, -0.2, 1.5])
    np.testing.assert_allclose(ours[:3, :3] @ p + ours[:3, 3], rs.rs2_transform_point_to_point(e, list(p)),
                               atol=1e-6)


def test_world_to_camera_poses_with_w_first_are_named_and_read(rig: Path) -> None:
    truth = _study(rig, "depth_poses.txt")[1]
    job, _, said = _study(rig, "colmap_poses.txt")
    named = [w for w in said if w.code == "pose-convention"]
    assert len(named) == 1 and "--pose-convention inverse-wxyz" in named[0].message, said
    assert job.camera["convention"]["fits_as"] == "inverse-wxyz"
    job, grid, said = _study(rig, "colmap_poses.txt", convention="inverse-wxyz")
    assert job.fit is not None and job.fit.fits and not [w for w in said if w.code == "pose-convention"]
    assert np.abs(grid.count - truth.count).sum() <= 4
    both = (grid.count >= 20) & (truth.count >= 20)
    np.testing.assert_allclose(grid.mean[both], truth.mean[both], atol=1e-6)
