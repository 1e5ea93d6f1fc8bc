"""Depth aligned to colour: disparity physics uses the stereo imager's own pixels, not the colour's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.core.camera_model import Intrinsics, StreamInfo


def test_real_aligned_set_carries_the_stereo_intrinsics(charuco_dir: Path) -> None:
    from depthstation.core.capture.registry import open_recording

    info = open_recording(charuco_dir / "pose03").info
    assert info.depth_aligned_to_color
    assert info.depth_intrinsics.fx == pytest.approx(1377.64, abs=0.01)
    assert info.stereo.fx == pytest.approx(639.04, abs=0.01)  # camera.json depth_unaligned
    u, v = info.to_stereo_pixels(np.array([info.depth_intrinsics.ppx]), np.array([info.depth_intrinsics.ppy]))
    assert (float(u[0]), float(v[0])) == pytest.approx((info.stereo.ppx, info.stereo.ppy))
    assert StreamInfo.from_dict(info.to_dict()).stereo == info.stereo


def test_simulated_noise_of_aligned_depth_follows_the_stereo_focal_length() -> None:
    """Intel's RMS_z = z^2 s / (f B) with f the stereo imager's: aligning the depth to a colour
    camera of twice the focal length must not halve the noise."""
    from depthstation.simulate.model import load_model
    from depthstation.simulate.scene_render import GeometryMaps

    color = Intrinsics(320, 180, 276.0, 276.0, 159.5, 89.5)
    stereo = Intrinsics(160, 90, 128.0, 128.0, 79.5, 44.5)
    h, w = color.height, color.width
    z = np.full((h, w), 2.0, dtype=np.float32)
    geo = GeometryMaps(z_m=z, normal=np.dstack([np.zeros_like(z), np.zeros_like(z), -np.ones_like(z)]),
                       inclination_deg=np.zeros_like(z), albedo=np.full_like(z, 0.8),
                       surface=np.zeros((h, w), dtype=np.int32), points_world=np.zeros((h, w, 3), np.float32),
                       edge_distance_px=np.full_like(z, np.inf), intrinsics=color, cam_to_world=np.eye(4))
    model = load_model("d455-ideal")
    plain = geo.context(0.095)
    aligned = geo.context(0.095, stereo=stereo)
    assert aligned.fx == stereo.fx
    assert float(np.asarray(aligned.u)[0, -1]) == pytest.approx(stereo.ppx + (w - 1 - color.ppx) * 128 / 276)
    ratio = float(np.sqrt(np.mean(model.variance_m2(aligned)) / np.mean(model.variance_m2(plain))))
    assert ratio == pytest.approx(color.fx / stereo.fx, rel=0.05)
