"""The distance x inclination grid: Welford per cell, Chan merge, file round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.core.errors import InputError
from depthstation.core.grid import Grid, display_grid, pack_grid, unpack_grid


def _samples(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.0, 1.0, n)
    a = rng.uniform(0.0, 90.0, n)
    x = 0.01 * d + rng.normal(0.0, 0.002, n) + 1.0  # offset tests the numerics of M2
    return d, a, x


def test_default_bins_follow_design() -> None:
    g = Grid.empty()
    assert g.shape == (1200, 900)
    assert g.distance_edges_m[0] == 0.0 and g.distance_edges_m[-1] == pytest.approx(6.0)
    assert np.diff(g.inclination_edges_deg) == pytest.approx(0.1)


def test_cell_statistics_equal_numpy() -> None:
    g = Grid.empty(distance_bin_m=0.25, inclination_bin_deg=30.0, distance_max_m=1.0)
    d, a, x = _samples(20000, 1)
    assert g.add(d, a, x) == d.size
    kd = np.floor(d / 0.25).astype(int)
    ka = np.floor(a / 30.0).astype(int)
    for k in range(4):
        for j in range(3):
            sel = x[(kd == k) & (ka == j)]
            assert g.count[k, j] == sel.size
            assert g.mean_m[k, j] == pytest.approx(sel.mean(), abs=1e-12)
            assert g.var[k, j] == pytest.approx(sel.var(ddof=1), rel=1e-9)


def test_out_of_range_and_nan_are_skipped_and_top_edge_kept() -> None:
    g = Grid.empty(distance_bin_m=0.5, inclination_bin_deg=45.0, distance_max_m=1.0)
    n = g.add([-0.1, 1.5, np.nan, 0.2, 0.2], [10.0, 10.0, 10.0, 90.0, np.nan], [1, 2, 3, 4, 5])
    assert n == 1
    assert g.count[0, 1] == 1  # inclination exactly 90 lands in the last bin


def test_merge_of_chunks_equals_single_pass() -> None:
    d, a, x = _samples(30000, 2)
    whole = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=10.0, distance_max_m=1.0)
    whole.add(d, a, x)
    merged = whole.like()
    for idx in np.array_split(np.arange(d.size), 7):
        part = whole.like()
        part.add(d[idx], a[idx], x[idx])
        merged.merge(part)
    np.testing.assert_array_equal(merged.count, whole.count)
    np.testing.assert_allclose(merged.mean_m, whole.mean_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(merged.var, whole.var, rtol=1e-9)


def test_merge_rejects_other_bins() -> None:
    with pytest.raises(ValueError, match="different bins"):
        Grid.empty().merge(Grid.empty(distance_bin_m=0.01))


def test_save_load_roundtrip(tmp_path: Path) -> None:
    g = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=10.0, distance_max_m=1.0)
    g.add(*_samples(5000, 3))
    path = g.save(tmp_path / "grid.npz")
    with np.load(path) as z:
        assert {"distance_edges_m", "inclination_edges_deg", "count", "mean_m", "var_m2"} <= set(z.files)
        assert z["count"].shape == (10, 9)
    h = Grid.load(path)
    np.testing.assert_array_equal(h.count, g.count)
    np.testing.assert_array_equal(h.m2, g.m2)
    assert h.summary() == g.summary()


def test_load_rejects_non_grid(tmp_path: Path) -> None:
    bad = tmp_path / "x.npz"
    np.savez(bad, count=np.zeros((2, 2)))
    with pytest.raises(InputError, match="missing"):
        Grid.load(bad)


def test_masked_views_hide_thin_cells() -> None:
    g = Grid.empty(distance_bin_m=0.5, inclination_bin_deg=45.0, distance_max_m=1.0)
    g.add([0.1] * 12 + [0.7] * 3, [10.0] * 15, np.arange(15.0))
    count, mean, std = g.masked(min_count=10)
    assert not mean.mask[0, 0] and mean.mask[1, 0]
    assert std[0, 0] == pytest.approx(np.std(np.arange(12.0), ddof=1))
    assert count[1, 0] == 3


def test_coarsened_equals_binning_at_the_coarse_bins() -> None:
    """Merging 2 x 3 blocks of cells gives the grid binned directly at the coarse size."""
    fine = Grid.empty(distance_bin_m=0.05, inclination_bin_deg=5.0, distance_max_m=1.0)
    coarse = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=15.0, distance_max_m=1.0)
    d, a, x = _samples(20000, 7)
    fine.add(d, a, x)
    coarse.add(d, a, x)
    c = fine.coarsened(2, 3)
    np.testing.assert_array_equal(c.count, coarse.count)
    np.testing.assert_allclose(c.mean_m, coarse.mean_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(c.std, coarse.std, rtol=1e-9)
    with pytest.raises(ValueError, match="divide"):
        fine.coarsened(3, 1)


def test_display_grid_coarsens_a_sparse_grid_only_as_far_as_needed() -> None:
    g = Grid.empty(distance_bin_m=0.01, inclination_bin_deg=1.0, distance_max_m=1.0)
    d, a, x = _samples(4000, 3)  # ~0.4 samples per fine cell
    g.add(d, a, x)
    shown, (fd, fi) = display_grid(g, min_count=10)
    assert (fd, fi) != (1, 1)
    held = shown.count[shown.count >= 10].sum()
    assert held >= 0.5 * g.total and shown.total == g.total
    dense = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=10.0, distance_max_m=1.0)
    dense.add(d, a, x)  # ~44 per cell: shown as analysed
    assert display_grid(dense, min_count=10)[1] == (1, 1)


def _clustered_grid(rng: np.random.Generator, frames: int, bias: float) -> Grid:
    """One cell seen by `frames` frames: each frame moves all its pixels by a common offset
    (pose error, exposure) on top of independent pixel noise; 20-400 pixels per frame."""
    g = Grid.empty(distance_bin_m=1.0, inclination_bin_deg=90.0, distance_max_m=1.0).with_frame_moments()
    frame = g.like()
    for _ in range(frames):
        n = int(rng.integers(20, 400))
        x = bias + rng.normal(0.0, 0.002) + rng.normal(0.0, 0.003, n)
        frame.add(np.full(n, 0.5), np.full(n, 10.0), x)
        g.add_frame(frame)
    return g


def test_frame_clustered_standard_error_covers_the_cell_mean() -> None:
    """Pixels of a frame share its error: sqrt(var / n) covers the true mean in few cells, the
    frame-clustered U95 (t with effective frames - 1 dof) in about 95%, and is not inflated."""
    rng = np.random.default_rng(11)
    bias, frames, trials = 0.004, 8, 400
    hits_naive = hits = 0
    u95, errors = [], []
    for _ in range(trials):
        g = _clustered_grid(rng, frames, bias)
        err = abs(g.mean[0, 0] - bias)
        assert g.frames is not None and g.frames[0, 0] == frames
        hits_naive += err <= 1.96 * g.stderr[0, 0]
        hits += err <= g.u95_m[0, 0]
        u95.append(g.u95_m[0, 0])
        errors.append(g.mean[0, 0] - bias)
    assert hits_naive / trials < 0.5           # the independent-pixel error bar misleads
    assert 0.93 <= hits / trials <= 0.99
    spread = 1.96 * np.std(errors)
    assert 0.8 < np.median(u95) / spread < 2.0  # honest, not inflated


def test_frame_moments_survive_merge_pack_and_file(tmp_path: Path) -> None:
    """Two chunks of frames merged give the moments of one pass; pack/unpack and grid.npz keep them."""
    rng = np.random.default_rng(5)
    one = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=10.0, distance_max_m=1.0).with_frame_moments()
    halves = [one.like().with_frame_moments(), one.like().with_frame_moments()]
    frame = one.like()
    for k in range(12):
        d, a, x = _samples(3000, 100 + k)
        x = x + rng.normal(0.0, 0.001)  # a frame-wide offset
        for g in (one, halves[k % 2]):
            frame.add(d, a, x)
            g.add_frame(frame)
        assert frame.total == 0
    merged = unpack_grid(pack_grid(halves[0])).merge(unpack_grid(pack_grid(halves[1])))
    assert merged.frames is not None and one.frames is not None
    np.testing.assert_array_equal(merged.frames, one.frames)
    np.testing.assert_allclose(merged.se_m, one.se_m, rtol=1e-9)
    back = Grid.load(merged.save(tmp_path / "grid.npz"))
    np.testing.assert_allclose(back.se_m, one.se_m, rtol=1e-9)
    with np.load(tmp_path / "grid.npz") as z:
        assert {"frames", "se_m"} <= set(z.files)
    ok = one.frames > 1
    assert (one.design_effect[ok] > 1.5).mean() > 0.5  # the frame offset shows as a design effect
    # without frame moments the independent-sample error is all there is
    plain = Grid.empty(distance_bin_m=0.1, inclination_bin_deg=10.0, distance_max_m=1.0)
    plain.add(*_samples(3000, 1))
    assert plain.frames is None
    np.testing.assert_array_equal(plain.se_m, plain.stderr)
