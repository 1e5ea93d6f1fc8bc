"""Fused kernel details: inclination bins without arccos equal the exact ones; pixel centres."""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np
import pytest

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.grid import Grid
from depthstation.core.raster import fill_rays
from depthstation.evaluate.scan.raycast import (
    GUESS_CELLS,
    _axis_products,
    _inclination_bin,
    cos_edges,
    inclination_guess,
    pixel_bins_kernel,
)


def _pass_bins(c: np.ndarray, g: Grid) -> Any:
    """The inclination bins `_pixel_bins` gives pixels whose cos(inclination) is exactly `c`: each
    looks along x at a normal along x, 1 m away, and its ray-norm factor (float64 here) is c."""
    n = c.size
    d_lo, d_step, nd, _, _, ni = g.bins
    ce = cos_edges(g)
    dirs = np.zeros((n, 3), np.float32)
    dirs[:, 0] = 1.0
    kk, sj, se = np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n)
    start, stats = np.empty(nd + 1, np.int64), np.zeros(6, np.int64)
    pixel_bins_kernel(False)(
        np.ones(n, np.float32), np.zeros(n, np.int32), np.array([[1.0, 0.0, 0.0]], np.float32), dirs,
        np.empty((0, 3)), np.empty((0, 3)), np.eye(3), c.astype(np.float64), np.full(n, 1000, np.uint16),
        0.001, d_lo, d_step, nd, ce, inclination_guess(ce), ni, kk, sj, se, start, stats)
    assert stats[3] == n  # all evaluated, in one distance bin: sj keeps the pixels' order
    return sj


def test_inclination_bin_equals_exact_arccos_binning() -> None:
    g = Grid.empty()
    ce = cos_edges(g)
    rng = np.random.default_rng(0)
    ang = np.concatenate([rng.uniform(0, 90, 200_000), np.arange(0, 90, 0.1) + 1e-7,
                          np.arange(0.1, 90, 0.1) - 1e-7, [0.0, 90.0]])
    c = np.cos(np.radians(ang))
    got = np.array([_inclination_bin(x, ce, 0.0, 0.1, 900) for x in c])
    want = np.minimum(np.floor(np.degrees(np.arccos(np.clip(c, 0, 1))) / 0.1).astype(int), 899)
    # exact up to the rounding of cos at the edges themselves
    assert np.mean(got == want) > 0.99999
    assert np.all(np.abs(got - want) <= 1)
    sub = Grid.empty(inclination_bin_deg=5.0, inclination_max_deg=60.0)
    assert _inclination_bin(np.cos(np.radians(70.0)), cos_edges(sub), 0.0, 5.0, 12) == -1


def test_ray_directions_pass_through_integer_pixel_centres() -> None:
    intr = Intrinsics(8, 6, 10.0, 12.0, 3.0, 2.0)
    d = pixel_rays(intr)
    np.testing.assert_allclose(d[2, 3], [0.0, 0.0, 1.0])  # principal point at integer (3, 2)
    np.testing.assert_allclose(d[0, 0], [-0.3, -2.0 / 12.0, 1.0], rtol=1e-6)


@pytest.mark.parametrize("grid", [{}, {"inclination_bin_deg": 0.01}, {"inclination_bin_deg": 1.0},
                                  {"inclination_bin_deg": 5.0, "inclination_min_deg": 10.0,
                                   "inclination_max_deg": 60.0}])
def test_the_pass_gives_the_inclination_bin_of_the_edge_walk(grid: dict[str, float]) -> None:
    """The pass's bin (table guess, one comparison where its cell holds one edge) is the walk along
    the exact edge cosines for every c: the edges and their neighbouring doubles, the table's cell
    bounds and theirs, random values, just above 1, below the grid, NaN."""
    g = Grid.empty(**grid)
    ce = cos_edges(g)
    ni = ce.size - 1
    rng = np.random.default_rng(1)
    cells = np.arange(GUESS_CELLS + 1) / GUESS_CELLS
    near = np.concatenate([ce, cells])
    c = np.concatenate([near, np.nextafter(near, 2.0), np.nextafter(near, -1.0), rng.uniform(0, 1, 200_000),
                        np.cos(np.radians(rng.uniform(0, 2, 50_000))), [1.0 + 2e-16, -0.1, 0.0, np.nan]])
    got = _pass_bins(c, g)
    e = g.inclination_edges_deg
    lo, step = float(e[0]), float(e[1] - e[0])
    want = np.array([_inclination_bin(x, ce, lo, step, ni) if np.isfinite(x) else -1 for x in c])
    np.testing.assert_array_equal(got, want)
    if step >= 0.1:  # bins of 0.1 deg and more: every cell in the grid from 1 deg on is one comparison
        # (but a cell starting on the grid's last, closed, edge: cos(60 deg) is 0.5, a cell bound)
        inside = (cells > ce[-1]) & (cells <= min(ce[0], np.cos(np.radians(1.0))))
        assert np.all(inclination_guess(ce)[inside] >= 0)


def test_pinhole_rays_from_column_and_row_products_bin_every_pixel_as_per_pixel_rays() -> None:
    """The pass's pinhole kernel builds each ray from per-column and per-row products; it must give
    the floats `fill_rays` gives, so every pixel lands in the same cell as with per-pixel rays (the
    lens kernel), here with normals chosen so that ~1 % of the pixels lie within 1e-6 of a bin edge."""
    intr = Intrinsics(97, 61, 71.3, 70.9, 47.2, 31.7)
    rng = np.random.default_rng(3)
    n = intr.width * intr.height
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    angle = 0.7
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    dirs = pixel_rays(intr).reshape(-1, 3)
    world = dirs.astype(np.float64) @ rot.T
    world /= np.linalg.norm(world, axis=1)[:, None]
    g = Grid.empty(0.05, 1.0, 6.0, 90.0)
    # a normal per pixel at a random inclination, 1 % of them 1e-7 deg off an edge of the grid
    inc = np.radians(np.where(rng.random(n) < 0.01, rng.integers(1, 89, n) + rng.normal(0, 1e-7, n),
                              rng.uniform(0, 90, n)))
    side = np.cross(world, rng.normal(size=(n, 3)))
    side /= np.linalg.norm(side, axis=1)[:, None]
    normals = (np.cos(inc)[:, None] * world + np.sin(inc)[:, None] * side).astype(np.float32)
    t_hit = rng.uniform(0.3, 5.9, n).astype(np.float32)
    depth = rng.integers(0, 6000, n).astype(np.uint16)
    inv_norm = (1.0 / np.linalg.norm(dirs.astype(np.float64), axis=1)).astype(np.float32)
    d_lo, d_step, nd, _, _, ni = g.bins
    ce = cos_edges(g)
    xs, ys = dirs[: intr.width, 0].copy(), dirs[:: intr.width, 1].copy()
    cols, rows = np.empty((intr.width, 3)), np.empty((intr.height, 3))
    _axis_products(rot, xs, ys, cols, rows)
    out = []
    for pinhole in (False, True):
        kk, sj, se = np.empty(n, np.int32), np.full(n, -7, np.int32), np.zeros(n)
        start, stats = np.empty(nd + 1, np.int64), np.zeros(6, np.int64)
        c_, r_ = (cols, rows) if pinhole else (np.empty((0, 3)), np.empty((0, 3)))
        pixel_bins_kernel(pinhole)(t_hit, np.arange(n, dtype=np.int32), normals, dirs, c_, r_, rot, inv_norm,
                                   depth, 0.001, d_lo, d_step, nd, ce, inclination_guess(ce), ni, kk, sj, se,
                                   start, stats)
        out.append((kk, sj, se, start, stats))
    assert out[0][4][4] > n // 2  # most pixels binned
    for a, b in zip(*out, strict=True):
        np.testing.assert_array_equal(a, b)


def _rotation_at_a_rounding_midpoint(x: float, y: float, target: float, differs: Any) -> np.ndarray:
    """A rotation row (r00, r01, r02) whose ray direction x component r00 x + r01 y + r02 lies next
    to the midpoint between two float32 values around `target`, chosen so that `differs(a, b, c)`
    (another order or fusion of the sum a + b + c) rounds to the other float32."""
    f = np.float32(target)
    lo = float(f) if float(f) < target else float(np.nextafter(f, np.float32(-1)))
    mid = (lo + float(np.nextafter(np.float32(lo), np.float32(2)))) / 2
    rng = np.random.default_rng(2)
    for _ in range(100_000):
        r00, r01 = rng.uniform(-1, 1, 2)
        a, b = r00 * x, r01 * y
        c0 = mid - (a + b)
        for k in range(-8, 9):
            c = c0 + k * np.spacing(c0)
            if differs(a, b, c, r01):
                return np.array([[r00, r01, c], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    raise AssertionError("no such rotation found")


@pytest.mark.parametrize("order", ["fused", "reassociated"])
def test_the_pass_bins_the_direction_fill_rays_builds_even_at_a_float32_rounding_midpoint(order: str) -> None:
    """The pass rebuilds each pixel's ray direction; it must be `fill_rays`' float32 direction, not a
    fused or reordered sum that rounds the other way (numba compiles a helper with its caller's
    fast-maths flags unless the helper sets its own: inside the pass the lens kernel's sum was
    fused into an FMA, the pinhole kernel's summed as (row + r02) + column). One pixel looking along
    x at a normal along x: its cos(inclination) is exactly the direction's x component, placed
    where the two orders round to different float32 values on either side of a bin's cosine."""
    intr = Intrinsics(1, 1, 500.0, 500.0, 0.3, -0.2)
    dirs = pixel_rays(intr).reshape(-1, 3)
    x, y = float(dirs[0, 0]), float(dirs[0, 1])
    g = Grid.empty(0.05, 1.0, 6.0, 90.0)
    d_lo, d_step, nd, _, _, ni = g.bins
    ce = cos_edges(g)

    def fma(p: float, q: float, r: float) -> float:  # p q + r rounded once
        return float(Fraction(p) * Fraction(q) + Fraction(r))

    differs = {
        "fused": lambda a, b, c, r01: np.float32(a + b + c) != np.float32(fma(r01, y, a) + c),
        "reassociated": lambda a, b, c, r01: np.float32(a + b + c) != np.float32((b + c) + a),
    }[order]
    rot = _rotation_at_a_rounding_midpoint(x, y, float(ce[ni // 2]), differs)
    rays = np.empty((1, 6), np.float32)
    fill_rays(rays, np.zeros(3), rot, dirs)
    c = abs(float(rays[0, 3]))
    want = next(j for j in range(ni) if ce[j] >= c > ce[j + 1])
    cols, rows = np.empty((1, 3)), np.empty((1, 3))
    _axis_products(rot, dirs[:1, 0].copy(), dirs[:1, 1].copy(), cols, rows)
    for pinhole in (False, True):
        kk, sj, se = np.empty(1, np.int32), np.empty(1, np.int32), np.empty(1)
        start, stats = np.empty(nd + 1, np.int64), np.zeros(6, np.int64)
        c_, r_ = (cols, rows) if pinhole else (np.empty((0, 3)), np.empty((0, 3)))
        pixel_bins_kernel(pinhole)(np.array([2.0], np.float32), np.zeros(1, np.int32),
                                   np.array([[1.0, 0.0, 0.0]], np.float32), dirs, c_, r_, rot,
                                   np.ones(1, np.float32), np.array([2000], np.uint16), 0.001, d_lo, d_step,
                                   nd, ce, inclination_guess(ce), ni, kk, sj, se, start, stats)
        assert stats[4] == 1
        assert int(sj[0]) == want, (order, pinhole, int(sj[0]), want)
