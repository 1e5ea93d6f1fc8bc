"""Fused kernel details: inclination bins without arccos equal the exact ones; pixel centres."""

from __future__ import annotations

import numpy as np

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.grid import Grid
from depthstation.evaluate.scan.raycast import _inclination_bin, cos_edges


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
