"""The default D455 model against Intel's figures: plane-fit noise, depth unit and disparity step."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from depthstation.core.camera_model import deproject
from depthstation.core.geometry import fit_plane
from depthstation.simulate.model import load_model
from depthstation.simulate.scene import Scene, Surface, quad
from depthstation.simulate.scene_render import render_geometry

W, H = 640, 360  # the demo protocol's mode; the test uses that resolution's own f


def _wall(z: float, tilt_deg: float = 0.0) -> Scene:
    """A wall facing the camera at z, turned by tilt_deg about the vertical through (0, 0, z)."""
    x = np.array([-50.0, 50.0, 50.0, -50.0])
    y = np.array([-50.0, -50.0, 50.0, 50.0])
    a = np.radians(tilt_deg)
    v, t = quad(np.stack([x * np.cos(a), y, z + x * np.sin(a)], axis=1))
    return Scene([Surface("wall", v, t, 0.8)])


def _frames(z: float, n: int, seed: int = 0, tilt_deg: float = 0.0) -> tuple[np.ndarray, Any]:
    model = load_model("d455-ideal")
    intr = model.camera.depth_intrinsics(W, H)
    g = render_geometry(_wall(z, tilt_deg), intr, np.eye(4))
    ctx = g.context(model.camera.baseline_m)
    rng = np.random.default_rng(seed)
    zs = np.stack([np.rint(model.sample(ctx, g.z_m, rng) * 1000.0) / 1000.0 for _ in range(n)])
    return zs, intr


@pytest.mark.parametrize("z", [0.6, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
def test_frontal_wall_noise_follows_intel(z: float) -> None:
    model = load_model("d455-ideal")
    # A wall turned by 3 deg: its z spans many depth units across the patch, so the 1 mm unit and
    # the 1/32 px step average over their phase as on any real wall (a perfectly frontal wall at
    # one z can sit on an unlucky phase of the two lattices and read up to 15 % high at 0.6 m).
    zs, intr = _frames(z, 3, tilt_deg=3.0)
    fb = intr.fx * model.camera.baseline_m
    intel = z * z * 0.08 / fb
    v, u = np.mgrid[H // 2 - 60:H // 2 + 60, W // 2 - 80:W // 2 + 80]
    rms = []
    for frame in zs:
        d = frame[v, u]
        ok = np.isfinite(d)
        pts = deproject(intr, u[ok], v[ok], d[ok])
        c, n = fit_plane(pts)
        rms.append(np.sqrt(np.mean(((pts - c) @ n) ** 2)))
    measured = float(np.mean(rms))
    assert abs(measured / intel - 1) < 0.10, f"z={z}: RMS {measured * 1e3:.3f} vs Intel {intel * 1e3:.3f} mm"
    # and the model's own signature (noise + quantisation) explains it more closely still
    from depthstation.simulate.effects.base import PixelContext

    ctx = PixelContext(z_m=z, fx=intr.fx, ppx=intr.ppx, ppy=intr.ppy, baseline_m=model.camera.baseline_m)
    assert abs(measured / float(np.sqrt(model.variance_m2(ctx))) - 1) < 0.06


def test_depth_unit_and_disparity_step_show_in_values() -> None:
    model = load_model("d455-ideal")
    fb = model.camera.depth_intrinsics(W, H).fx * model.camera.baseline_m
    # near: the disparity step (0.35 mm at 0.6 m) is finer than the 1 mm unit -> 1 mm steps
    zs, _ = _frames(0.6, 2)
    mm = np.unique(np.rint(zs[np.isfinite(zs)] * 1000).astype(int))
    np.testing.assert_allclose(zs[np.isfinite(zs)] * 1000, np.rint(zs[np.isfinite(zs)] * 1000), atol=1e-3)
    assert np.median(np.diff(mm)) == 1
    # far: every value is f B / (k / 32) rounded to mm, and neighbours are a disparity step apart
    zs, _ = _frames(4.0, 2)
    mm = np.unique(np.rint(zs[np.isfinite(zs)] * 1000).astype(int))
    k = np.rint(fb / (mm / 1000.0) * 32)
    np.testing.assert_array_equal(mm, np.rint(1000.0 * fb / (k / 32)).astype(int))
    near_4m = mm[(mm > 3900) & (mm < 4100)]
    step_mm = 4.0**2 / fb / 32 * 1000  # 15.6 mm at 4 m, 640x360
    assert np.all(np.abs(np.diff(near_4m) / step_mm - 1) < 0.1)


def test_min_z_drops_depth() -> None:
    model = load_model("d455-ideal")
    zmin = model.camera.min_z_m(1280, 720)
    assert 0.50 < zmin < 0.53  # Intel: about 0.52 m at 1280x720
    zs, _ = _frames(0.9 * model.camera.min_z_m(W, H), 1)
    assert np.isnan(zs).all()
