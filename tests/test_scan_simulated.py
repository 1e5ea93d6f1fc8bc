"""The study on the simulator's room sequence (simulate.scan): the grid recovers the sensor
model's analytic signature (bias and variance) in well-populated cells."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scan_expect import model_grids

pytest.importorskip("depthstation.simulate.scan_sequence")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from depthstation.simulate.model import load_model
    from depthstation.simulate.poses import walk_around, write_tum
    from depthstation.simulate.scan_sequence import simulate_scan

    # flying pixels depend on the distance to depth edges, which the grid does not resolve; the
    # noise all white (same total): the grid's standard errors count pixels as independent, which
    # the window-shared part of the default noise is not
    model = load_model("d455-ideal").without_effect("flying_pixels").white_noise()
    root = tmp_path_factory.mktemp("simscan")
    # 8 views spread over one turn round the table (the default walk moves 6 cm in 6 frames,
    # which leaves the rotation about the vertical unconstrained within the 0.5-2 m band)
    poses = walk_around(np.array([0.0, -0.75, 0.0]), radius_m=2.0, speed_m_s=2 * np.pi * 2.0 * 30 / 8,
                        frames=8, bob_m=0.0)
    write_tum(root / "walk.txt", np.arange(8) / 30.0, poses)
    out = root / "session"
    simulate_scan("room", root / "walk.txt", model, out, width=424, height=240, color=False, seed=4)
    return {"dir": out, "model": model}


def test_grid_matches_the_simulator_signature(simulated: dict[str, Any]) -> None:
    from depthstation.core.capture.registry import open_recording
    from depthstation.core.grid import Grid
    from depthstation.evaluate.scan.raycast import MeshCaster
    from depthstation.evaluate.scan.study import StudyConfig, evaluate_chunk
    from depthstation.evaluate.scan.trajectory import read_tum

    d: Path = simulated["dir"]
    rec = open_recording(d / "sequence.mcap")
    traj = read_tum(d / "trajectory.txt")  # true poses in the mesh frame: identity registration
    intr = rec.info.depth_intrinsics
    caster = MeshCaster(d / "scene.ply", intr, nthreads=1)
    config = StudyConfig(distance_bin_m=0.1, inclination_bin_deg=3.0, nthreads=1)
    res = evaluate_chunk(caster, rec, traj, config)
    assert len(res.used) == 8 and res.stats[3] > 0.8 * res.stats[0]

    exp_bias, exp_var = model_grids(d, simulated["model"], config.empty_grid())
    grid: Grid = res.grid
    well = (grid.count >= 300) & (exp_bias.count >= 300)
    assert well.sum() >= 15
    diff = np.abs(grid.mean_m[well] - exp_bias.mean_m[well])
    se = grid.stderr[well]
    # judged: within 3 standard errors, or 1 mm
    ok3 = (diff <= 3 * se) | (diff <= 1e-3)
    # judged per cell: within 3 standard errors, or 1 mm. Over ~150 cells a few 3-se excursions
    # are chance (0.27 % each), so: all within 4 se or 1 mm, and >= 98 % within 3 se or 1 mm
    assert np.all((diff <= 4 * se) | (diff <= 1e-3)), np.c_[diff, se][~ok3]
    assert ok3.mean() >= 0.98
    expected_std = np.sqrt(exp_var.mean_m[well] + np.nan_to_num(exp_bias.var[well]))
    ratio = grid.std[well] / expected_std
    tol = 4 / np.sqrt(2 * (grid.count[well] - 1)) + 0.1
    assert np.all((np.abs(ratio - 1) <= tol) | (np.abs(grid.std[well] - expected_std) <= 1e-3)), \
        np.c_[ratio, tol, grid.std[well], expected_std]


def test_registration_of_the_simulated_sequence_recovers_a_rigid_perturbation(
        simulated: dict[str, Any]) -> None:
    """The sequence's trajectory moved by a known transform (a camera's scale is its depth's, so a
    consistent perturbation of real data is rigid) is registered back: scale 1 within 0.1 %,
    rotation within 0.05 deg."""
    import open3d as o3d

    from depthstation.core.capture.registry import open_recording
    from depthstation.core.geometry import rodrigues, rotation_angle_deg
    from depthstation.evaluate.scan.reference import sample_reference_points
    from depthstation.evaluate.scan.registration import register
    from depthstation.evaluate.scan.trajectory import compose_similarity, decompose_similarity, read_tum

    d: Path = simulated["dir"]
    rec = open_recording(d / "sequence.mcap")
    truth = read_tum(d / "trajectory.txt")
    S = compose_similarity(1.0, rodrigues(np.radians([1.0, 25.0, -2.0])), np.array([0.4, 0.1, -0.7]))
    moved = truth.transformed(np.linalg.inv(S))
    mesh = o3d.io.read_triangle_mesh(str(d / "scene.ply"))
    bb = np.asarray(mesh.vertices)
    ref_pts = np.array([bb.min(0), bb.max(0), [bb.min(0)[0], bb.max(0)[1], bb.max(0)[2]],
                        [bb.max(0)[0], bb.min(0)[1], bb.min(0)[2]]])
    si = np.linalg.inv(S)
    rng = np.random.default_rng(2)
    src = ref_pts @ si[:3, :3].T + si[:3, 3] + rng.normal(0, 0.03, ref_pts.shape)
    reg = register(rec, moved, mesh, sample_reference_points(mesh, 300_000), mode="similarity",
                   pass_points=(src, ref_pts), every=1)
    s, r, t = decompose_similarity(reg.matrix)
    _, r0, t0 = decompose_similarity(S)
    assert abs(s - 1.0) < 1e-3
    assert rotation_angle_deg(r, r0) < 0.05
    assert np.linalg.norm(t - t0) < 0.01
