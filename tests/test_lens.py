"""Lenses as users' files describe them: every depth pixel on the ray its lens gives it.

The standpoints are written by `lens_render` (numpy and OpenCV only, its own lens inversion), so
the truth does not come from the code under test. Each case was a wrong figure without a word
before: depth aligned to a D455's distorted colour camera deprojected as a pinhole, a camera.json
whose distortion has no `model` (dropped), a ROS `rational_polynomial` CameraInfo (dropped),
image_proc's rectified topics (the raw images' distortion applied again) and 32FC1 metres finer
than a millimetre (rounded to 1 mm).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import lens_render
import numpy as np
import pytest
from console import run_console as _cli

from depthstation.core.camera_model import Intrinsics, StreamInfo, ray_planes
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.ros_bag import transport_base
from depthstation.core.capture.rosmsgs import is_rectified_topic
from depthstation.core.protocol import load_board
from depthstation.core.run_warnings import collecting
from depthstation.evaluate.checkerboard.mask import board_mask


@pytest.fixture(scope="module")
def standpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("lens")
    return out, lens_render.render(out)


def _figures(out: Path) -> dict[str, float]:
    with (out / "standpoints.csv").open() as fh:
        row = next(csv.DictReader(fh))
    keys = ("distance_m", "noise_m", "accuracy_m")
    return {k: float(v) for k, v in row.items() if k in keys or k.removesuffix("_u95") in keys}


def _within_u95(fig: dict[str, float], truth: dict[str, Any]) -> None:
    """Each figure within its U95 of the truth, and the noise within 1 %: it is the scatter of the
    same depth samples about a plane, the truth's along the true rays (the pixel sets differ by the
    mask's margin only); pinhole rays through the D455 colour lens read it 2 % high."""
    for key in ("distance_m", "noise_m", "accuracy_m"):
        assert abs(fig[key] - truth[key]) <= fig[f"{key}_u95"], (key, fig[key], truth[key], fig[f"{key}_u95"])
    assert fig["noise_m"] == pytest.approx(truth["noise_m"], rel=0.01)


def test_the_board_plane_is_met_along_the_lens_rays(standpoint: tuple[Path, dict[str, Any]]) -> None:
    """The mask's reference depth of each pixel is where the pixel's true ray meets the board:
    with the D455 colour lens a pinhole ray is off by up to ~1e-2 relative at the image's edge."""
    out, truth = standpoint
    k = truth["k"]
    intr = Intrinsics(truth["width"], truth["height"], k[0, 0], k[1, 1], k[0, 2], k[1, 2], "brown_conrady",
                      tuple(truth["lens"]))
    rays = lens_render.rays(k, truth["lens"], truth["width"], truth["height"])
    xs, ys = ray_planes(intr)
    assert np.abs(xs - rays[..., 0]).max() < 1e-9 and np.abs(ys - rays[..., 1]).max() < 1e-9
    board = load_board(out / "board.json")
    th = np.radians(50.0)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]]
    size = np.array([7 * 0.075 / 2, 5 * 0.075 / 2, 0.0])
    pose[:3, 3] = np.array([0.5, 0.15, 1.0]) - pose[:3, :3] @ size
    mask = board_mask(pose, intr, board)
    assert mask is not None and mask.inside.sum() > 5000
    n, t = pose[:3, 2], pose[:3, 3]
    box = rays[mask.box]
    z_true = (n @ t) / (box @ n)
    assert np.abs(mask.z_ref_m - z_true)[mask.inside].max() < 2e-6


def test_aligned_depth_through_a_distorted_colour_lens(standpoint: tuple[Path, dict[str, Any]],
                                                       tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    src, truth = standpoint
    lens_render.write_camera_json(src, truth)
    code, _, err = _cli(["evaluate", "checkerboard", str(src / "sp"), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    _within_u95(_figures(tmp_path / "r"), truth)


def test_a_camera_json_distortion_without_a_model_is_opencvs(standpoint: tuple[Path, dict[str, Any]],
                                                              tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    src, truth = standpoint
    lens_render.write_camera_json(src, truth, model=None)
    code, _, err = _cli(["evaluate", "checkerboard", str(src / "sp"), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    _within_u95(_figures(tmp_path / "r"), truth)
    colour = open_recording(src / "sp").info.color_intrinsics
    assert colour is not None and colour.model == "opencv" and colour.has_distortion


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_ros_bags_with_either_lens_model(standpoint: tuple[Path, dict[str, Any]], tmp_path: Path, model: str,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    src, truth = standpoint
    if model == "rational_polynomial":  # its own lens: k4-k6 bend the rays too
        src = tmp_path / "rational"
        truth = lens_render.render(src, lens=(*lens_render.D455_COLOUR_LENS, 0.05, -0.03, 0.01), frames=2)
    bag = tmp_path / "bag"
    lens_render.write_ros2_bag(src, bag, truth, distortion_model=model, d=tuple(truth["lens"]))
    code, _, err = _cli(["evaluate", "checkerboard", str(bag), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    _within_u95(_figures(tmp_path / "r"), truth)


def test_a_lens_the_station_cannot_invert_is_refused(standpoint: tuple[Path, dict[str, Any]], tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    src, truth = standpoint
    bag = tmp_path / "fisheye"
    lens_render.write_ros2_bag(src, bag, truth, distortion_model="equidistant", d=(0.1, 0.01, 0.0, 0.0))
    code, _, err = _cli(["evaluate", "checkerboard", str(bag), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 2
    assert str(bag) in err and "kannala_brandt4" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_a_lens_model_none_with_coefficients_is_said(standpoint: tuple[Path, dict[str, Any]], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A CameraInfo whose distortion_model is empty (no model) but whose D is the lens: read as the
    model says (no lens), and the user told, since unrectified images would sit on wrong rays."""
    src, truth = standpoint
    bag = tmp_path / "nomodel"
    lens_render.write_ros2_bag(src, bag, truth, distortion_model="", d=tuple(truth["lens"]))
    code, _, err = _cli(["evaluate", "checkerboard", str(bag), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    assert "lens model 'none' with non-zero coefficients" in err and str(bag) in err
    info = json.loads((tmp_path / "r" / "result.json").read_text())
    assert any(w["code"] == "lens-model-none" for w in info["warnings"])


def test_rectified_topics_are_read_without_the_raw_distortion(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """image_proc's `image_rect_color` and `depth_registered/image_rect` beside a CameraInfo whose
    D describes the raw images: the rectified images are a pinhole (REP 104)."""
    src = tmp_path / "pinhole"
    truth = lens_render.render(src, lens=(0.0,) * 5, frames=2)
    bag = tmp_path / "bag"
    raw_k = truth["k"] * np.array([[1.05, 1, 1], [1, 1.05, 1], [1, 1, 1]])   # the raw camera: not P's
    lens_render.write_ros2_bag(src, bag, truth, colour_topic="/camera/color/image_rect_color",
                               depth_topic="/camera/depth_registered/image_rect",
                               d=lens_render.D455_COLOUR_LENS, k_info=raw_k)
    code, _, err = _cli(["evaluate", "checkerboard", str(bag), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    _within_u95(_figures(tmp_path / "r"), truth)
    assert "is rectified" in err
    for topic in ("/camera/color/image_rect_color/compressed",
                  "/camera/depth_registered/image_rect/compressedDepth"):
        assert is_rectified_topic(transport_base(topic))   # as recorded: compressed
    assert not is_rectified_topic("/camera/camera/depth/image_rect_raw")   # realsense-ros: D is zero


def test_float_depth_finer_than_a_millimetre_keeps_its_noise(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A D405-like 0.2 mm noise published as 32FC1 metres: rounded to 1 mm it read as 0.33 mm."""
    src = tmp_path / "fine"
    truth = lens_render.render(src, lens=(0.0,) * 5, distance_m=0.45, inclination_deg=30.0,
                               shift_m=(0.0, 0.0), noise_m=0.0002, units_m=1e-5, focal_px=200.0, frames=2)
    bag = tmp_path / "bag"
    lens_render.write_ros2_bag(src, bag, truth, encoding="32FC1", d=(0.0,) * 5)
    code, _, err = _cli(["evaluate", "checkerboard", str(bag), "--board", str(src / "board.json"),
                         "--out", str(tmp_path / "r"), "--no-figures"], capsys)
    assert code == 0, err
    fig = _figures(tmp_path / "r")
    # 0.1 mm counts add (0.1 mm)^2 / 12 to the variance: 0.2 mm -> 0.2021 mm, inside the U95
    assert abs(fig["noise_m"] - truth["noise_m"]) <= fig["noise_m_u95"] + truth["noise_m"] * 0.011
    rec = open_recording(bag)
    assert rec.info.depth_units_m == pytest.approx(1e-4)
    with collecting() as said:   # beyond the 16-bit range of 0.1 mm counts: said, not lost silently
        counts = rec._depth(np.array([[7.0, 0.45]], dtype=np.float32))  # type: ignore[attr-defined]
    assert counts.tolist() == [[0, 4500]] and [w.code for w in said] == ["ros-reading"]


def test_aligned_depth_pixels_reach_the_stereo_imager_along_their_lens_ray() -> None:
    """Explain's disparity lives in the stereo imager's pixels: an aligned depth pixel is carried
    there along its own ray, which the colour lens bends (a pinhole scaling put it ~3.5 px off
    at the corners of a D455 colour image)."""
    k = np.array([[320.0, 0, 319.5], [0, 320.0, 179.5], [0, 0, 1]])
    colour = Intrinsics(640, 360, 320.0, 320.0, 319.5, 179.5, "inverse_brown_conrady",
                        lens_render.D455_COLOUR_LENS)
    stereo = Intrinsics(848, 480, 424.0, 424.0, 423.5, 239.5)
    info = StreamInfo(colour, colour, depth_aligned_to_color=True, stereo_intrinsics=stereo)
    u, v = np.array([0, 319, 639, 10]), np.array([0, 179, 359, 300])
    us, vs = info.to_stereo_pixels(u, v)
    rays = lens_render.rays(k, np.asarray(lens_render.D455_COLOUR_LENS), 640, 360)[v, u]
    np.testing.assert_allclose(us, 423.5 + 424.0 * rays[:, 0], atol=1e-6)
    np.testing.assert_allclose(vs, 239.5 + 424.0 * rays[:, 1], atol=1e-6)
