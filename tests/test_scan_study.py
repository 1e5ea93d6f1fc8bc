"""Reference-scan study on a known world: analytic room, known error model, known registration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from depthstation.core.geometry import rodrigues, rotation_angle_deg
from depthstation.core.grid import Grid
from depthstation.core.parallel import ChunkRunner
from depthstation.evaluate.scan.chunks import run_scan_chunks
from depthstation.evaluate.scan.raycast import MeshCaster
from depthstation.evaluate.scan.reference import sample_reference_points
from depthstation.evaluate.scan.registration import register, umeyama
from depthstation.evaluate.scan.study import StudyConfig, evaluate_chunk
from depthstation.evaluate.scan.synthetic import ErrorModel, Room, make_sequence, render_truth
from depthstation.evaluate.scan.trajectory import Trajectory, compose_similarity, decompose_similarity

MODEL = ErrorModel(a_per_m=0.002, b_m=0.004, sigma_per_m=0.0015)
UNITS = 1e-4


@pytest.fixture(scope="module")
def room() -> Room:
    return Room()


@pytest.fixture(scope="module")
def mesh(room: Room) -> object:
    return room.mesh()


@pytest.fixture(scope="module")
def seq():  # type: ignore[no-untyped-def]
    return make_sequence(frames=24, width=160, height=120, model=MODEL, depth_units_m=UNITS, seed=3)


def _traj(seq) -> Trajectory:  # type: ignore[no-untyped-def]
    return Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)


def test_reference_depth_and_inclination_match_the_analytic_room(room: Room, mesh: object, seq) -> None:  # type: ignore[no-untyped-def]
    caster = MeshCaster(mesh, seq.info.depth_intrinsics, nthreads=1)
    z, inc = render_truth(room, seq.info.depth_intrinsics, seq.poses[5])
    im = caster.images(seq.poses[5], seq.depth[5], UNITS)
    assert np.isfinite(im.reference_m).all()
    # z-depth through integer pixel centres: a +0.5 px or range-vs-z slip would be mm to cm off
    assert np.median(np.abs(im.reference_m - z)) < 2e-5
    assert np.percentile(np.abs(im.inclination_deg - inc), 99) < 0.05
    err = im.error_m[np.isfinite(im.error_m)]
    assert err.mean() > 0  # the model reads too far: positive errors (DESIGN sign)


def test_grid_recovers_the_model_signature(room: Room, mesh: object, seq) -> None:  # type: ignore[no-untyped-def]
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=2.0, nthreads=1)
    caster = MeshCaster(mesh, seq.info.depth_intrinsics, nthreads=1)
    res = evaluate_chunk(caster, seq, _traj(seq), config)
    grid = res.grid
    assert res.stats[0] == 24 * 160 * 120 and len(res.used) == 24
    # expected cell statistics from the truth of the very same pixels (analytic signature)
    exp_bias, exp_var = Grid.empty(0.05, 2.0), Grid.empty(0.05, 2.0)
    for k in range(24):
        z, inc = render_truth(room, seq.info.depth_intrinsics, seq.poses[k])
        ok = seq.depth[k] > 0
        exp_bias.add(z[ok], inc[ok], MODEL.bias_m(z[ok], inc[ok]))
        exp_var.add(z[ok], inc[ok], MODEL.sigma_m(z[ok]) ** 2 + UNITS**2 / 12)
    well = (grid.count >= 200) & (exp_bias.count >= 200)
    assert well.sum() >= 40
    se = grid.stderr[well]
    diff = np.abs(grid.mean_m[well] - exp_bias.mean_m[well])
    assert np.all((diff <= 4 * se) | (diff <= 1e-3))
    assert np.mean(diff <= 3 * se) > 0.97
    expected_std = np.sqrt(exp_var.mean_m[well] + np.nan_to_num(exp_bias.var[well]))
    ratio = grid.std[well] / expected_std
    tol = 4 / np.sqrt(2 * (grid.count[well] - 1)) + 0.02
    assert np.all(np.abs(ratio - 1) <= tol)


def test_merged_chunks_in_two_processes_equal_one_pass(mesh: object, seq, tmp_path) -> None:  # type: ignore[no-untyped-def]
    import open3d as o3d

    path = tmp_path / "room.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=1.0, nthreads=1)
    with ChunkRunner(1) as serial, ChunkRunner(2) as pool:
        one = run_scan_chunks(seq, path, _traj(seq), config, serial)
        two = run_scan_chunks(seq, path, _traj(seq), config, pool, chunk_frames=5)
    np.testing.assert_array_equal(two.grid.count, one.grid.count)
    np.testing.assert_allclose(two.grid.mean, one.grid.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(two.grid.m2, one.grid.m2, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(two.stats, one.stats)
    assert sorted(two.used) == one.used
    # the frame moments merge across chunks and processes like the sums they are
    assert one.grid.moments is not None and two.grid.moments is not None
    np.testing.assert_array_equal(two.grid.moments.frames, one.grid.moments.frames)
    np.testing.assert_allclose(two.grid.moments.n2, one.grid.moments.n2, rtol=1e-12)
    np.testing.assert_allclose(two.grid.se_m, one.grid.se_m, rtol=1e-7, atol=1e-12)


class _DeviceNumbered:
    """The sequence as a RealSense recording numbers it: the device's frame counter, which starts
    anywhere and skips frames (here 169, 170, 172, 173, 175, ...), not 0, 1, 2, ..."""

    def __init__(self, seq) -> None:  # type: ignore[no-untyped-def]
        self.seq, self.info, self.name = seq, seq.info, "device-numbered"

    @property
    def frame_count(self) -> int:
        return len(self.seq.depth)

    def number(self, pos: int) -> int:
        return 169 + pos + pos // 2

    def frames(self, limit=None, start=0):  # type: ignore[no-untyped-def]
        for fs in self.seq.frames(limit=limit, start=start):
            yield dataclasses.replace(fs, index=self.number(fs.index))


@pytest.mark.parametrize("every,max_frames", [(1, 10), (3, 5), (2, None)])
def test_frames_are_chosen_by_position_not_by_device_number(mesh: object, seq, every: int,  # type: ignore[no-untyped-def]
                                                            max_frames: int | None) -> None:
    """--frames, --every and the indices a result reports count frames along the sequence: with
    device numbers from 169, selecting by number read no frame at all for --frames 10 (169 >= 10)
    and every other frame for --every 2 (by the counter's parity)."""
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=1.0, every=every, max_frames=max_frames,
                         nthreads=1)
    caster = MeshCaster(mesh, seq.info.depth_intrinsics, 1)
    plain = evaluate_chunk(caster, seq, _traj(seq), config)
    numbered = evaluate_chunk(caster, _DeviceNumbered(seq), _traj(seq), config)
    expect = list(range(0, len(seq.depth) if max_frames is None else max_frames * every, every))
    assert plain.used == expect and numbered.used == expect
    np.testing.assert_array_equal(numbered.grid.count, plain.grid.count)
    np.testing.assert_array_equal(numbered.grid.mean, plain.grid.mean)
    # a chunk that starts inside the sequence keeps counting from its start
    part = evaluate_chunk(caster, _DeviceNumbered(seq), _traj(seq), config, start=6, limit=6)
    assert part.used == [p for p in expect if 6 <= p < 12]


def test_frame_moments_of_the_pass_equal_those_of_per_frame_grids(mesh: object, seq, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The fused pass takes each frame's cell means from its sorted pixels; core.grid builds the
    same moments from the frame's own grid (Grid.add_frame): two codes, one answer."""
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=2.0, nthreads=1,
                         per_frame_dir=tmp_path / "frames")
    res = evaluate_chunk(MeshCaster(mesh, seq.info.depth_intrinsics, nthreads=1), seq, _traj(seq), config)
    built = config.empty_grid().with_frame_moments()
    for path in sorted((tmp_path / "frames").glob("frame_*.npz")):
        built.add_frame(Grid.load(path))
    fm, ref = res.grid.moments, built.moments
    assert fm is not None and ref is not None
    np.testing.assert_array_equal(fm.frames, ref.frames)
    assert fm.frames.max() == len(res.used)
    np.testing.assert_allclose(fm.n2, ref.n2, rtol=1e-12)
    np.testing.assert_allclose(fm.n2_mean, ref.n2_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fm.n2_mean2, ref.n2_mean2, rtol=1e-9, atol=1e-15)


def test_cell_uncertainty_carries_an_error_common_to_each_frame(room: Room, mesh: object, seq) -> None:  # type: ignore[no-untyped-def]
    """A depth offset shared by every pixel of a frame (a pose or exposure error) does not average
    out over a frame's pixels: se_m must carry sigma_f / sqrt(frames), which sqrt(var / n) misses."""
    sigma_f = 0.0015
    rng = np.random.default_rng(11)
    shifted = []
    for d in seq.depth:
        dz = rng.normal(0.0, sigma_f)
        z = np.where(d > 0, d * UNITS + dz, 0.0)
        shifted.append(np.round(z / UNITS).astype(np.uint16))
    moved = dataclasses.replace(seq, depth=shifted)
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=2.0, nthreads=1)
    grid = evaluate_chunk(MeshCaster(mesh, seq.info.depth_intrinsics, nthreads=1), moved, _traj(seq),
                          config).grid
    assert grid.moments is not None
    well = (grid.count >= 500) & (grid.moments.frames >= 12)
    assert well.sum() >= 20
    feff = grid.effective_frames
    assert feff is not None
    # expected: the frame-common part over the effective frames, the pixel part over the samples
    predicted = np.sqrt(sigma_f**2 / feff[well] + grid.var[well] / grid.count[well])
    ratio = grid.se_m[well] / predicted
    # a CR1 standard error from F >= 12 clusters scatters by ~1/sqrt(2 (F - 1)) ~ 21 %
    assert 0.75 < float(np.median(ratio)) < 1.3
    # sqrt(var / n) misses the common part: the design effect the model predicts is found
    naive = grid.var[well] / grid.count[well]
    predicted_deff = predicted**2 / naive
    assert float(np.median(predicted_deff)) > 2  # the setup makes the point
    assert 0.55 < float(np.median(grid.design_effect[well] / predicted_deff)) < 1.7
    assert np.median(grid.u95_m[well] / (1.96 * grid.stderr[well])) > 1.4
    s = grid.summary()["cell_uncertainty"]
    assert s["cells"] >= well.sum() and s["median_design_effect"] > 1.5


def test_registration_recovers_a_known_similarity(room: Room, mesh: object) -> None:
    s_true = 0.982
    # a trajectory frame scaled by 1/s reads depth in that frame's units: consistent data
    seq = make_sequence(frames=20, width=120, height=90, depth_units_m=UNITS, seed=5,
                        model=ErrorModel(scale=1 / s_true, a_per_m=0, b_m=0, sigma_per_m=5e-4))
    S = compose_similarity(s_true, rodrigues(np.radians([3.0, -2.0, 20.0])), np.array([1.0, -0.5, 0.2]))
    traj_f = _traj(seq).transformed(np.linalg.inv(S))
    rng = np.random.default_rng(1)
    ref_pts = np.array([[0, 0, 0], [6, 0, 0], [6, 5, 0], [0, 5, 2.8], [3, 2.5, 0.75], [6, 5, 2.8]], float)
    si = np.linalg.inv(S)
    src = ref_pts @ si[:3, :3].T + si[:3, 3] + rng.normal(0, 0.02, ref_pts.shape)
    reg = register(seq, traj_f, mesh, sample_reference_points(mesh, 300_000), mode="similarity",
                   pass_points=(src, ref_pts),
                   every=1)
    s, r, t = decompose_similarity(reg.matrix)
    s0, r0, t0 = decompose_similarity(S)
    assert abs(s / s0 - 1) < 1e-3
    assert rotation_angle_deg(r, r0) < 0.05
    assert np.linalg.norm(t - t0) < 0.005
    assert reg.mean_c2m_m is not None and reg.mean_c2m_m < 0.002
    # the posed trajectory then matches the truth poses
    back = traj_f.transformed(reg.matrix)
    assert np.abs(back.poses[:, :3, 3] - seq.poses[:, :3, 3]).max() < 0.005


def test_umeyama_exact_on_noise_free_points() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    S = compose_similarity(1.3, rodrigues(np.array([0.2, -0.4, 1.0])), np.array([0.5, 2.0, -1.0]))
    dst = src @ S[:3, :3].T + S[:3, 3]
    np.testing.assert_allclose(umeyama(src, dst), S, atol=1e-10)
