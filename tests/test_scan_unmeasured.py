"""Reference surface nobody scanned: Poisson rounds corners and closes holes, and a pixel that sees
such surface compares the camera with the meshing. Those triangles stay in the mesh (they hide
what lies behind them, as the real object did); the pixels that see them leave the grid and are
counted, with either renderer, and the command says so."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.camera_model import Intrinsics
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.grid import Grid
from depthstation.core.lazy_open3d import open3d
from depthstation.core.run_warnings import RunWarning, collecting
from depthstation.evaluate.scan.rasterise import make_renderer
from depthstation.evaluate.scan.raycast import STAT_NAMES, CellAccumulator
from depthstation.evaluate.scan.reference import UNMEASURED_CACHE, unmeasured_triangles
from depthstation.evaluate.scan.run import ScanOptions, run_scan
from depthstation.evaluate.scan.synthetic import Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum

INTR = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
UNMEASURED = STAT_NAMES.index("unmeasured_surface")
PANEL_HALF_M = 0.31


def test_a_triangle_with_a_vertex_beyond_the_gap_is_unmeasured() -> None:
    tri = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5]])
    off = np.array([0.001, 0.002, 0.003, 0.011, 0.0, 0.0])
    assert unmeasured_triangles(tri, off, 0.01).tolist() == [False, True, True]
    assert unmeasured_triangles(tri, off, 0.0).tolist() == [False, False, False]  # 0: keep all


def _wall_and_panel() -> tuple[np.ndarray, np.ndarray]:
    """A wall at z = 3 m filling the view, and a 0.62 m square panel at z = 2 m in front of its
    centre (triangles 2 and 3): the panel is the 'unmeasured' surface."""
    h = PANEL_HALF_M
    v = np.array([[-5, -5, 3], [5, -5, 3], [5, 5, 3], [-5, 5, 3],
                  [-h, -h, 2], [h, -h, 2], [h, h, 2], [-h, h, 2]], dtype=np.float64)
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], dtype=np.int64)
    return v, t


def _panel_pixels(intr: Intrinsics) -> np.ndarray:
    """The test's own projection: pixel centres whose ray passes inside the panel (none on its edge)."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    x = (u - intr.ppx) / intr.fx * 2.0
    y = (v - intr.ppy) / intr.fy * 2.0
    h = PANEL_HALF_M
    assert np.min(np.abs(np.abs(x) - h)) > 1e-4 and np.min(np.abs(np.abs(y) - h)) > 1e-4
    return np.asarray((np.abs(x) < h) & (np.abs(y) < h)).ravel()


@pytest.mark.parametrize("name", ["raster", "raycast"])
def test_unmeasured_surface_still_hides_the_wall_and_its_pixels_leave_the_grid(name: str) -> None:
    o3d = open3d()
    v, t = _wall_and_panel()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    pose = np.eye(4)
    panel = _panel_pixels(INTR)
    assert 50 < panel.sum() < INTR.width * INTR.height / 2
    mask = np.array([False, False, True, True])
    config_grid = Grid.empty(0.05, 1.0, 6.0, 90.0)
    depth = np.full((INTR.height, INTR.width), 2500, np.uint16)  # 2.5 m everywhere (units 1 mm)

    def run(unmeasured: np.ndarray | None) -> tuple[Any, Any, np.ndarray, CellAccumulator]:
        r = make_renderer(name, mesh, INTR, 1, unmeasured=unmeasured)
        t_hit, normals = r.cast(pose)
        t_hit, normals = t_hit.copy(), normals.copy()
        cells, stats = CellAccumulator.for_grid(config_grid), np.zeros(len(STAT_NAMES), np.int64)
        r.bin_frame(pose, depth, 0.001, cells, stats)
        return t_hit, normals, stats, cells

    t_all, n_all, s_all, c_all = run(None)
    t_um, n_um, s_um, c_um = run(mask)
    # the panel still occludes: its pixels keep the panel's depth (2 m), not the wall's (3 m)
    np.testing.assert_array_equal(t_um, t_all)
    assert np.allclose(t_um[panel], 2.0, atol=1e-5) and np.allclose(t_um[~panel], 3.0, atol=1e-5)
    assert np.all(np.isnan(n_um[panel])) and np.all(np.isfinite(n_um[~panel]))
    assert np.all(np.isfinite(n_all))
    # counted, and out of the grid: the grid holds the wall's pixels only
    assert s_all[UNMEASURED] == 0 and s_all[4] == panel.size
    assert s_um[UNMEASURED] == panel.sum()
    assert s_um[4] == panel.size - panel.sum() and s_um[3] == panel.size
    g_all, g_um = c_all.to_grid(), c_um.to_grid()
    assert g_um.total == panel.size - panel.sum()
    near = round(2.5 / 0.05)  # the panel's cells lie below 2.5 m, the wall's above
    assert g_um.count[:near].sum() == 0 and g_all.count[:near].sum() == panel.sum()
    np.testing.assert_array_equal(g_um.count[near:], g_all.count[near:])


@pytest.mark.parametrize(("below_m", "width", "height"), [(1e-6, 64, 48), (1.0, 24, 18)],
                         ids=["floor", "below-1m"])
def test_both_renderers_leave_out_the_same_pixels_of_a_walk(below_m: float, width: int, height: int) -> None:
    """A room whose floor (or all below 1 m) is marked unmeasured: the raster and ray-cast studies
    agree pixel for pixel on what is left out, and the grids are equal. The second marks more
    triangles than a quarter of the pixels: the rasteriser then blanks the normals of those hit
    (by rank), not of every marked triangle."""
    mesh = Room().mesh(segments=64)
    floor = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)[:, 2] < below_m
    assert 0 < floor.sum() < len(floor)
    assert (floor.sum() > width * height // 4) == (below_m > 0.5)
    seq = make_sequence(frames=3, width=width, height=height, seed=5)
    grid = Grid.empty(0.1, 5.0, 6.0, 90.0)
    out: dict[str, tuple[np.ndarray, Grid]] = {}
    for name in ("raster", "raycast"):
        r = make_renderer(name, mesh, seq.info.depth_intrinsics, 1, unmeasured=floor)
        cells, stats = CellAccumulator.for_grid(grid), np.zeros(len(STAT_NAMES), np.int64)
        for fs, pose in zip(seq.frames(), seq.poses, strict=True):
            r.bin_frame(pose, fs.depth, seq.info.depth_units_m, cells, stats)
        out[name] = (stats, cells.to_grid())
    assert out["raster"][0][UNMEASURED] > 100
    np.testing.assert_array_equal(out["raster"][0], out["raycast"][0])
    np.testing.assert_array_equal(out["raster"][1].count, out["raycast"][1].count)
    np.testing.assert_allclose(out["raster"][1].mean, out["raycast"][1].mean, atol=1e-12)


@pytest.fixture(scope="module")
def table_scanned_from_above(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A walk round the table, and a TLS cloud of the room that never saw the table's side (the
    scanner stood above it): Poisson closes the side with a surface of its own."""
    o3d = open3d()
    root = tmp_path_factory.mktemp("unmeasured")
    seq = make_sequence(frames=6, width=80, height=60, seed=2)
    write_mcap(root / "seq.mcap", seq.info, seq.frames())
    write_tum(root / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    np.savetxt(root / "identity.txt", np.eye(4))
    room = Room()
    mesh = room.mesh(segments=128)
    o3d.io.write_triangle_mesh(str(root / "room.ply"), mesh)
    o3d.utility.random.seed(0)
    pts = np.asarray(mesh.sample_points_uniformly(100_000).points)
    r = np.hypot(pts[:, 0] - room.table_center_m[0], pts[:, 1] - room.table_center_m[1])
    side = (np.abs(r - room.table_radius_m) < 0.02) & (pts[:, 2] < room.table_height_m - 0.02)
    side |= (r < room.table_radius_m) & (pts[:, 2] < 0.01)  # nor the floor under it
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[~side]))
    o3d.io.write_point_cloud(str(root / "cloud.ply"), cloud)
    return {"root": root, "room": room, "seq": seq}


def _scan(w: dict[str, Any], name: str, reference: str, **kw: Any) -> tuple[dict[str, Any], list[RunWarning]]:
    root: Path = w["root"]
    opt = ScanOptions(similarity=root / "identity.txt", distance_bin_m=0.25, inclination_bin_deg=5.0,
                      min_count_sequence=20, poisson_depth=8, density_quantile=0.0,
                      reference_mode="mesh", **kw)  # the cloud's mesh itself: the rule under test
    with collecting() as caught:
        summary = run_scan(root / "seq.mcap", root / "poses.txt", root / reference, root / name, opt)
    return summary, list(caught)


def test_the_study_leaves_out_what_poisson_invented_and_says_so(table_scanned_from_above: dict[str, Any],
                                                                ) -> None:
    w = table_scanned_from_above
    left, said = _scan(w, "left", "cloud.ply")
    kept, _ = _scan(w, "kept", "cloud.ply", surface_gap_m=0.0)
    truth, _ = _scan(w, "truth", "room.ply")
    px_left, px_kept = left["pixels"], kept["pixels"]
    assert truth["pixels"]["unmeasured_surface"] == 0 and px_kept["unmeasured_surface"] == 0
    assert px_left["unmeasured_surface"] > 0
    # the same pixels are evaluated; those on unmeasured surface only leave the grid
    assert px_left["evaluated"] == px_kept["evaluated"]
    assert px_left["binned"] == px_kept["binned"] - px_left["unmeasured_surface"]
    assert Grid.load(w["root"] / "left" / "grid.npz").total == px_left["binned"]
    um = left["reference_mesh"]["unmeasured"]
    assert um["triangles"] > 0 and um["gap_m"] == 0.01
    assert (w["root"] / "left" / UNMEASURED_CACHE).is_file()
    assert kept["reference_mesh"]["unmeasured"]["triangles"] == 0
    assert not (w["root"] / "kept" / UNMEASURED_CACHE).exists()
    assert any(x.code == "reference-meshing" and "left out of the grid" in x.message for x in said), said
    share = px_left["unmeasured_surface"] / (px_left["binned"] + px_left["unmeasured_surface"])
    assert (share > 0.01) == any(x.code == "unmeasured-surface" for x in said), (share, said)
    info = json.loads((w["root"] / "left" / "result.json").read_text())
    assert info["parameters"]["surface_gap_m"] == 0.01


def test_the_pixels_left_out_are_those_whose_reference_is_off(table_scanned_from_above: dict[str, Any],
                                                              ) -> None:
    """Against the true room, pixel by pixel: a reference more than 10 mm off the truth is far more
    common among the pixels left out than among those kept (the rule is about the surface's
    normal offset, so grazing views of kept surface can still be off along the ray)."""
    w = table_scanned_from_above
    _scan(w, "left", "cloud.ply") if not (w["root"] / "left").exists() else None
    folder: Path = w["root"] / "left"
    seq = w["seq"]
    intr = seq.info.depth_intrinsics
    mesh_tris = len(open3d().io.read_triangle_mesh(str(folder / "reference_mesh.ply")).triangles)
    mask = np.load(folder / UNMEASURED_CACHE)
    assert mask.shape == (mesh_tris,)
    cloud_r = make_renderer("raster", folder / "reference_mesh.ply", intr, 1, unmeasured=mask)
    true_r = make_renderer("raster", w["root"] / "room.ply", intr, 1)
    off_left = off_kept = n_left = n_kept = 0
    for fs, pose in zip(seq.frames(), seq.poses, strict=True):
        a = cloud_r.images(pose, fs.depth, seq.info.depth_units_m)
        b = true_r.images(pose, fs.depth, seq.info.depth_units_m)
        off = np.abs(a.reference_m - b.reference_m) > 0.01
        left = a.unmeasured
        kept = np.isfinite(a.inclination_deg)
        off_left += int(np.sum(off & left))
        off_kept += int(np.sum(off & kept))
        n_left += int(left.sum())
        n_kept += int(kept.sum())
    assert n_left > 50 and n_kept > 10 * n_left
    assert off_left / n_left > 10 * (off_kept / n_kept), (off_left, n_left, off_kept, n_kept)


def test_ties_on_a_shared_edge_leave_out_the_same_pixels_with_either_renderer() -> None:
    """A plane split along a diagonal that runs through pixel centres: rays on it meet both
    triangles at one depth, and ray casting's choice decides whether the pixel is left out."""
    o3d = open3d()
    v = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], dtype=np.float64)
    t = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    depth = np.full((INTR.height, INTR.width), 2000, np.uint16)
    for mask in (np.array([True, False]), np.array([False, True])):
        seen = {}
        for name in ("raster", "raycast"):
            r = make_renderer(name, mesh, INTR, 1, unmeasured=mask)
            _, normals = r.cast(np.eye(4))
            cells = CellAccumulator.for_grid(Grid.empty(0.05, 1.0, 6.0, 90.0))
            stats = np.zeros(len(STAT_NAMES), np.int64)
            r.bin_frame(np.eye(4), depth, 0.001, cells, stats)
            seen[name] = (np.isnan(normals[:, 0]).copy(), stats)
        np.testing.assert_array_equal(seen["raster"][0], seen["raycast"][0])
        np.testing.assert_array_equal(seen["raster"][1], seen["raycast"][1])
        assert 0 < seen["raster"][1][UNMEASURED] == seen["raster"][0].sum()


def test_threads_and_worker_processes_leave_out_the_same_pixels(tmp_path: Path) -> None:
    """The mask travels to worker processes as a file beside the mesh, and to thread siblings."""
    from depthstation.core.parallel import ChunkRunner
    from depthstation.evaluate.scan.chunks import clear_cache, run_scan_chunks
    from depthstation.evaluate.scan.study import StudyConfig
    from depthstation.evaluate.scan.trajectory import Trajectory

    mesh = Room().mesh(segments=64)
    open3d().io.write_triangle_mesh(str(tmp_path / "room.ply"), mesh)
    floor = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)[:, 2] < 1e-6
    np.save(tmp_path / "mask.npy", floor)
    seq = make_sequence(frames=6, width=48, height=36, seed=3)
    write_mcap(tmp_path / "seq.mcap", seq.info, seq.frames())
    traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    out = {}
    for workers in (1, 2):
        clear_cache()
        config = StudyConfig(0.1, 5.0, 6.0, 90.0, nthreads=0 if workers == 1 else 1,
                             unmeasured=tmp_path / "mask.npy")
        with ChunkRunner(workers) as runner:
            res = run_scan_chunks(tmp_path / "seq.mcap", tmp_path / "room.ply", traj, config, runner,
                                  chunk_frames=2)
        out[workers] = res
    assert out[1].stats[UNMEASURED] > 100
    np.testing.assert_array_equal(out[1].stats, out[2].stats)
    np.testing.assert_array_equal(out[1].grid.count, out[2].grid.count)
    np.testing.assert_allclose(out[1].grid.mean, out[2].grid.mean, atol=1e-12)


def test_the_fit_check_counts_neither_miss_nor_error_on_unmeasured_surface() -> None:
    from depthstation.evaluate.scan.study import fit_check
    from depthstation.evaluate.scan.trajectory import Trajectory

    mesh = Room().mesh(segments=64)
    floor = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)].mean(axis=1)[:, 2] < 1e-6
    seq = make_sequence(frames=4, width=48, height=36, seed=3)
    traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    plain = fit_check(make_renderer("raster", mesh, seq.info.depth_intrinsics), seq, traj, frames=4)
    masked_r = make_renderer("raster", mesh, seq.info.depth_intrinsics, unmeasured=floor)
    masked = fit_check(masked_r, seq, traj, frames=4)
    assert plain is not None and masked is not None
    on_floor = sum(int(masked_r.images(p, fs.depth, seq.info.depth_units_m).unmeasured.sum())
                   for fs, p in zip(seq.frames(), seq.poses, strict=True))
    assert on_floor > 100 and masked.pixels == plain.pixels - on_floor
    assert masked.miss_share == plain.miss_share == 0.0


def test_the_mask_is_kept_with_the_cached_mesh_and_checked(table_scanned_from_above: dict[str, Any],
                                                            tmp_path: Path) -> None:
    from depthstation.core.errors import EvaluationError
    from depthstation.evaluate.scan.reference import (
        PoissonParams,
        load_unmeasured,
        reference_mesh,
        unmeasured_file,
    )

    cloud = table_scanned_from_above["root"] / "cloud.ply"
    params = PoissonParams(depth=7, density_quantile=0.0)
    inside = np.array([[3.0, 2.5, 1.5]])  # where the cloud's normals face (else a slow orientation)
    mesh, path, info = reference_mesh(cloud, tmp_path, params, viewpoints=inside)
    assert not info["cached"] and info["unmeasured"]["triangles"] > 0
    mask_path = unmeasured_file(path, info)
    assert mask_path == tmp_path / UNMEASURED_CACHE and mask_path.is_file()
    assert load_unmeasured(mask_path, len(mesh.triangles)).sum() == info["unmeasured"]["triangles"]
    assert reference_mesh(cloud, tmp_path, params, viewpoints=inside)[2]["cached"]
    mask_path.unlink()  # a cache without its mask is meshed again
    _, _, again = reference_mesh(cloud, tmp_path, params, viewpoints=inside)
    assert not again["cached"] and mask_path.is_file()
    with pytest.raises(EvaluationError, match="triangles"):
        load_unmeasured(mask_path, len(mesh.triangles) + 1)
    no_gap = PoissonParams(depth=7, density_quantile=0.0, surface_gap_m=0.0)
    _, _, kept = reference_mesh(cloud, tmp_path, no_gap, viewpoints=inside)
    assert kept["unmeasured"]["triangles"] == 0 and not mask_path.exists()


def test_a_negative_gap_is_bad_input() -> None:
    from depthstation.core.errors import InputError

    with pytest.raises(InputError, match="--surface-gap-m"):
        ScanOptions(surface_gap_m=-0.01).check()


def test_registration_fits_to_the_measured_part_only(tmp_path: Path) -> None:
    from depthstation.evaluate.scan.reference import measured_part

    o3d = open3d()
    v, t = _wall_and_panel()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    np.save(tmp_path / "m.npy", np.array([False, False, True, True]))
    part = measured_part(mesh, tmp_path / "m.npy")
    assert len(part.triangles) == 2 and np.allclose(np.asarray(part.vertices)[:, 2], 3.0)
    assert len(mesh.triangles) == 4  # the study's own mesh keeps the panel as an occluder
    assert measured_part(mesh, None) is mesh
