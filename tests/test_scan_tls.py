"""Reference scans as surveyors deliver them: survey coordinates (a local shift keeps the study's
float32 ray casting exact), E57 with georeferenced stations and LAS/LAZ through the `[tls]` extra,
intensity/colour carried to the mesh; `capture export --to tum` of a walk read back by the study."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.grid import Grid
from depthstation.core.parallel import ChunkRunner
from depthstation.evaluate.scan.run import ScanOptions, prepare_scan, run_prepared, run_scan
from depthstation.evaluate.scan.synthetic import Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum

SURVEY = np.array([412345.6, 5523456.7, 110.0])  # UTM-like easting, northing, height (m)
GEOREF = np.array([412345.5, 5523456.75, 110.0])  # an E57 station frame's georeference (exact in binary)
STATIONS = np.array([[1.25, 1.0, 1.5], [4.75, 1.0, 1.5], [1.25, 4.0, 1.5], [4.75, 4.0, 1.5]])
QUANTUM = 2.0**-16  # m: cloud coordinates on this grid are exact in E57's float32 and in LAS integers


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A short walk round the table (our MCAP), its poses, the room mesh and a cloud of it."""
    o3d = pytest.importorskip("open3d")
    root = tmp_path_factory.mktemp("tls")
    seq = make_sequence(frames=6, width=80, height=60, seed=2)
    write_mcap(root / "seq.mcap", seq.info, seq.frames())
    t = np.asarray(seq.timestamps_ns) * 1e-9
    mesh = Room().mesh(segments=128)
    o3d.utility.random.seed(0)
    cloud = np.round(np.asarray(mesh.sample_points_uniformly(20_000).points) / QUANTUM) * QUANTUM
    np.savetxt(root / "identity.txt", np.eye(4))
    return {"root": root, "seq": seq, "t": t, "mesh": mesh, "cloud": cloud}


def _study(w: dict[str, Any], name: str, reference: Path, offset: np.ndarray | None = None,
           sequence: Path | None = None, write: bool = False) -> tuple[Grid, dict[str, Any]]:
    """The scan study (poses translated by `offset`) with coarse cells: many samples each. Its
    one prepare/run path; the result folder (figures) only when `write`, to keep the test short."""
    root: Path = w["root"]
    poses = w["seq"].poses.copy()
    if offset is not None:
        poses[:, :3, 3] += offset
    write_tum(root / f"{name}_poses.txt", w["t"], poses)
    opt = ScanOptions(similarity=root / "identity.txt", icp=False, distance_bin_m=0.25,
                      inclination_bin_deg=5.0, min_count_sequence=20, poisson_depth=6,
                      reference_mode="mesh")  # the readers' points meshed alike (a mesh is used as is)
    seq, traj = sequence or root / "seq.mcap", root / f"{name}_poses.txt"
    if write:
        summary = run_scan(seq, traj, reference, root / name, opt)
        return Grid.load(root / name / "grid.npz"), summary
    with ChunkRunner(1) as runner:
        job = prepare_scan(seq, traj, reference, root / name, opt)
        result = run_prepared(job, runner)
    reg = job.registration.to_dict()
    return result.grid, {"reference_mesh": job.mesh_info, "registration": reg,
                         "local_shift": reg.get("local_shift"),
                         "sequence": {"depth_units_m": job.source.info.depth_units_m}}


def _room(w: dict[str, Any]) -> tuple[Grid, Path]:
    """The study against the room mesh itself, untranslated (computed once per module)."""
    path = w["root"] / "room.ply"
    if "room_grid" not in w:
        from depthstation.core.lazy_open3d import open3d

        open3d().io.write_triangle_mesh(str(path), w["mesh"])
        w["room_grid"] = _study(w, "near", path)[0]
    return w["room_grid"], path


def _close(a: Grid, b: Grid, tol_m: float, min_count: int = 30, outliers: float = 0.0) -> None:
    """Same cells; means within `tol_m` where both cells hold `min_count` samples, but for a
    fraction `outliers` of them (cells where one pixel changed its hit), and on average within
    a tenth of it."""
    assert a.count.sum() > 0
    assert abs(int(a.count.sum()) - int(b.count.sum())) <= 0.002 * a.count.sum()
    both = (a.count >= min_count) & (b.count >= min_count)
    assert both.sum() >= 10
    diff = np.abs(a.mean[both] - b.mean[both])
    assert np.mean(diff > tol_m) <= outliers, (np.sort(diff)[-5:], tol_m)
    assert np.average(diff, weights=a.count[both]) <= tol_m / 10


def test_survey_coordinates_give_the_same_grid(walk: dict[str, Any]) -> None:
    o3d = pytest.importorskip("open3d")
    root: Path = walk["root"]
    far = o3d.geometry.TriangleMesh(walk["mesh"])
    far.translate(SURVEY)
    o3d.io.write_triangle_mesh(str(root / "room_survey.ply"), far)
    near, _ = _room(walk)
    moved, s_far = _study(walk, "survey", root / "room_survey.ply", SURVEY, write=True)
    _close(near, moved, 1e-4)
    shift = np.asarray(s_far["local_shift"]["reference_m"])
    assert np.all(np.abs(shift - SURVEY) < 10.0)  # the centre of the room, whole metres
    assert np.all(shift == np.round(shift))
    np.testing.assert_allclose(s_far["registration"]["matrix"], np.eye(4), atol=1e-9)  # as given


def test_e57_and_las_references_give_the_grid_of_the_ply(walk: dict[str, Any]) -> None:
    o3d = pytest.importorskip("open3d")
    pye57 = pytest.importorskip("pye57")
    laspy = pytest.importorskip("laspy")
    root: Path = walk["root"]
    pts: np.ndarray = walk["cloud"]
    o3d.io.write_point_cloud(str(root / "cloud.ply"),
                             o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    intensity = 0.2 + 0.8 * (pts[:, 2] / 2.8)
    # E57: four georeferenced stations, each with its own points in scanner coordinates
    station = np.argmin(np.linalg.norm(pts[:, None, :] - STATIONS[None], axis=2), axis=1)
    e57 = pye57.E57(str(root / "cloud.e57"), mode="w")
    for k, origin in enumerate(STATIONS):
        mine = pts[station == k] - origin
        e57.write_scan_raw({"cartesianX": mine[:, 0], "cartesianY": mine[:, 1], "cartesianZ": mine[:, 2],
                            "intensity": intensity[station == k]},
                           name=f"station {k}", rotation=np.array([1.0, 0.0, 0.0, 0.0]),
                           translation=origin + GEOREF)
    e57.close()
    # LAZ: integer coordinates (scale 2^-16 m), 16-bit intensity and RGB
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = np.zeros(3)
    header.scales = np.full(3, QUANTUM)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.intensity = (intensity * 60000).astype(np.uint16)
    las.red = las.green = (intensity * 65535).astype(np.uint16)
    las.blue = np.full(len(pts), 20000, np.uint16)
    las.write(str(root / "cloud.laz"))

    # the readers give the points exactly (float64; E57's stations and georeference applied)
    from depthstation.evaluate.scan.reference import load_reference

    np.testing.assert_array_equal(np.asarray(load_reference(root / "cloud.laz")[1].points), pts)
    e57_pts = np.asarray(load_reference(root / "cloud.e57")[1].points)
    order = np.argsort(station, kind="stable")
    np.testing.assert_array_equal(e57_pts, pts[order] + GEOREF)
    ply, _ = _study(walk, "ply", root / "cloud.ply")
    from_e57, s_e57 = _study(walk, "e57", root / "cloud.e57", GEOREF)
    from_laz, s_laz = _study(walk, "laz", root / "cloud.laz", write=True)
    # Poisson on one thread (the default) is repeatable: the LAZ gives the PLY's points in the PLY's
    # order, hence the same mesh and the same grid, bit for bit
    np.testing.assert_array_equal(from_laz.count, ply.count)
    np.testing.assert_array_equal(from_laz.mean, ply.mean)
    # the E57 holds the points station by station, offset by fractions of a metre: the octree lies
    # differently on them, which moves the surface by micrometres and, at a silhouette, a pixel's
    # hit (measured: 2 of 164 cells by more than 0.1 mm). The formats may differ by no more than that.
    _close(ply, from_e57, 1e-4, outliers=0.04)
    assert np.all(np.abs(np.asarray(s_e57["local_shift"]["reference_m"]) - GEOREF) < 10.0)
    assert s_e57["reference_mesh"]["appearance"] == "intensity"
    assert s_e57["reference_mesh"]["normals"] == "towards the nearest camera centre of the trajectory"
    assert s_laz["reference_mesh"]["appearance"] == "rgb"
    mesh = o3d.io.read_triangle_mesh(str(root / "laz" / "reference_mesh.ply"))
    assert mesh.has_vertex_colors()
    # the figure shows the scan's colour on the surface each pixel sees: mostly (0.2..1, same, 0.3)
    from depthstation.evaluate.scan.reference import appearance_image

    look = appearance_image(mesh, walk["seq"].info.depth_intrinsics, walk["seq"].poses[3])
    assert look is not None
    seen = look[np.isfinite(look[..., 0])]
    assert seen.shape[0] > 0.8 * look.shape[0] * look.shape[1]  # Poisson trimming leaves holes
    assert np.median(np.abs(seen[:, 2] - 20000 / 65535)) < 0.01
    assert np.median(np.abs(seen[:, 0] - seen[:, 1])) < 0.01
    assert (root / "laz" / "fig8_frame.png").is_file()


def test_tum_export_of_a_walk_gives_the_same_grid(walk: dict[str, Any],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("open3d")
    import sys

    from depthstation.app import cli

    root: Path = walk["root"]
    original, room = _room(walk)
    old = sys.argv
    sys.argv = ["depthstation", "capture", "export", str(root / "seq.mcap"), "--to", "tum",
                "--out", str(root / "tum")]
    try:
        cli.main()  # returns on success, exits on failure
    finally:
        sys.argv = old
    assert "seq: 6 frames" in capsys.readouterr().out
    folder = root / "tum" / "seq"
    assert len((folder / "depth.txt").read_text().splitlines()) == 3 + 6  # 3 comment lines (TUM)
    assert not (folder / "associations.txt").exists()  # a depth-only walk has no image to pair
    tum, s_tum = _study(walk, "from_tum", room, sequence=folder)
    np.testing.assert_array_equal(tum.count, original.count)
    np.testing.assert_allclose(tum.mean, original.mean, atol=1e-9)
    assert s_tum["sequence"]["depth_units_m"] == pytest.approx(walk["seq"].info.depth_units_m)  # 0.1 mm kept
    assert json.loads((folder / "camera.json").read_text())["fx"] == walk["seq"].info.depth_intrinsics.fx


def test_meshed_surface_off_the_scanned_points_is_measured() -> None:
    """Two walls meeting in a corner, scanned with 2 mm noise: vertices on the walls lie on the
    points' planes, vertices of a chamfered corner 20-40 mm off (what Poisson invents there)."""
    from depthstation.evaluate.scan.reference import SURFACE_GAP_M, surface_to_points

    rng = np.random.default_rng(4)
    a, b = rng.uniform(0.0, 1.0, (2, 20_000))
    wall_x = np.stack([np.zeros_like(a), a, b], axis=1)           # x = 0, normal (1, 0, 0)
    wall_y = np.stack([a, np.zeros_like(a), b], axis=1)           # y = 0, normal (0, 1, 0)
    points = np.concatenate([wall_x, wall_y]) + rng.normal(0, 0.002, (40_000, 3))
    normals = np.concatenate([np.tile([1.0, 0, 0], (20_000, 1)), np.tile([0, 1.0, 0], (20_000, 1))])
    on_walls = np.concatenate([wall_x[:900], wall_y[:900]])
    s = rng.uniform(0.02, 0.04, 200)                              # a chamfer across the corner
    rounded = np.stack([s, s, rng.uniform(0.2, 0.8, 200)], axis=1)  # 20-40 mm off each wall
    stats = surface_to_points(np.concatenate([on_walls, rounded]), points, normals)
    assert stats["share_beyond_gap"] == pytest.approx(200 / 2000, abs=0.01)
    assert stats["median_m"] < 0.002 and stats["max_m"] > SURFACE_GAP_M
