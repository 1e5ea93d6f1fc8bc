"""Core maths: camera model, rotations and pose averaging, plane fit, boards, protocols."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.core.board import Board
from depthstation.core.camera_model import Extrinsics, Intrinsics, deproject, project
from depthstation.core.errors import InputError, ProtocolError
from depthstation.core.geometry import (
    average_rotations,
    fit_plane,
    inclination_deg,
    matrix_to_quaternion,
    quaternion_to_matrix,
    rodrigues,
    rotation_angle_deg,
)
from depthstation.core.protocol import PROTOCOL_DIR, load_board, load_protocol


def test_project_deproject_round_trip() -> None:
    intr = Intrinsics(1280, 720, 640.0, 641.0, 639.5, 359.2)
    rng = np.random.default_rng(1)
    u, v, z = rng.uniform(0, 1279, 100), rng.uniform(0, 719, 100), rng.uniform(0.5, 6, 100)
    uv = project(intr, deproject(intr, u, v, z))
    np.testing.assert_allclose(uv[:, 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], v, atol=1e-9)


def test_principal_point_pixel_sees_optical_axis() -> None:
    intr = Intrinsics(640, 480, 400.0, 400.0, 320.0, 240.0)
    p = deproject(intr, np.array([320.0]), np.array([240.0]), np.array([2.0]))
    np.testing.assert_allclose(p, [[0.0, 0.0, 2.0]])


def test_librealsense_rotation_is_column_major() -> None:
    r = rodrigues([0.1, -0.2, 0.3])
    ext = Extrinsics.from_librealsense(r.T.ravel(), [0.05, 0, 0])
    np.testing.assert_allclose(ext.R, r, atol=1e-12)
    rot, _ = ext.to_librealsense()
    np.testing.assert_allclose(np.reshape(rot, (3, 3)).T, r, atol=1e-12)
    np.testing.assert_allclose(ext.inverse().apply(ext.apply(np.ones((1, 3)))), np.ones((1, 3)))


def test_karcher_mean_of_symmetric_perturbations_is_centre() -> None:
    base = rodrigues([0.3, 0.2, -1.0])
    rng = np.random.default_rng(0)
    deltas = rng.normal(0, 0.05, (50, 3))
    rots = [base @ rodrigues(d) for d in deltas] + [base @ rodrigues(-d) for d in deltas]
    assert rotation_angle_deg(average_rotations(rots), base) < 1e-6


def test_quaternion_round_trip() -> None:
    r = rodrigues([2.5, -0.4, 0.9])
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(r)), r, atol=1e-12)


def test_plane_fit_recovers_normal_and_noise() -> None:
    rng = np.random.default_rng(2)
    n_true = np.array([0.0, -np.sin(0.5), -np.cos(0.5)])
    a, b = np.cross(n_true, [1, 0, 0]), np.cross(n_true, np.cross(n_true, [1, 0, 0]))
    s, t = rng.uniform(-0.5, 0.5, (2, 20000))
    noise = np.outer(rng.normal(0, 0.002, s.size), n_true)
    pts = np.array([0, 0, 2.0]) + np.outer(s, a) + np.outer(t, b) + noise
    c, n = fit_plane(pts)
    assert abs(abs(n @ n_true) - 1) < 1e-6
    rms = np.sqrt(np.mean(((pts - c) @ n) ** 2))
    assert rms == pytest.approx(0.002, rel=0.03)


def test_inclination_folds_into_0_90() -> None:
    assert inclination_deg(np.array([0, 0, 1.0]), np.array([0, 0, -1.0])) == pytest.approx(0.0)
    assert inclination_deg(np.array([0, 0, 1.0]), np.array([0, 0, 1.0])) == pytest.approx(0.0)
    n = np.array([0, np.sin(np.radians(30)), -np.cos(np.radians(30))])
    assert inclination_deg(np.array([0, 0, 1.0]), n) == pytest.approx(30.0)


def test_board_colours_alternate_and_corners() -> None:
    b = Board(squares_x=7, squares_y=5, square_length_m=0.1)
    assert b.corner_points().shape == (24, 3)
    assert bool(b.is_black(np.array(0.05), np.array(0.05)))
    assert not bool(b.is_black(np.array(0.15), np.array(0.05)))
    assert not bool(b.is_black(np.array(-0.05), np.array(0.05)))


def test_real_board_json_loads(charuco_dir: Path) -> None:
    b = load_board(charuco_dir / "board.json")
    assert (b.type, b.squares_x, b.squares_y, b.dictionary) == ("charuco", 7, 5, "DICT_4X4_50")


def test_board_errors_name_the_key(tmp_path: Path) -> None:
    p = tmp_path / "board.json"
    p.write_text('{"type": "circles", "squares_x": 7, "squares_y": 5, "square_length_m": 0.05}')
    with pytest.raises(InputError, match=r"board\.type"):
        load_board(p)


def test_protocols_load_and_plan() -> None:
    proto = load_protocol("checkerboard-d455")
    sps = proto.plan.standpoints()
    assert sps[0].distance_m == 1.0 and sps[1].distance_m == pytest.approx(1.4)
    assert {s.inclination_deg for s in sps} == {0.0, 15.0, 30.0, 45.0, 60.0}
    assert proto.board.square_length_m == 0.095


_DEMO = (PROTOCOL_DIR / "demo-d455.toml").read_text()


@pytest.mark.parametrize(("change", "key"), [
    (("step_m = 0.8", 'step_m = "far"'), "plan.step_m"),
    (("[plan]\n", "[plan]\nstepp = 1\n"), "plan.stepp"),
    (("fps = 30", "fps = -1"), "streams.fps"),
    (('name = "demo-d455"\n', ""), "missing key 'name'"),
    (("[board]", "[boardx]"), "board"),
])
def test_protocol_errors_name_the_key(tmp_path: Path, change: tuple[str, str], key: str) -> None:
    """A complete protocol with one fault: the error names that key."""
    assert change[0] in _DEMO
    p = tmp_path / "p.toml"
    p.write_text(_DEMO.replace(*change, 1))
    with pytest.raises(ProtocolError, match=key.replace(".", r"\.")):
        load_protocol(p)


def test_opencv_distortion_of_librealsense_models() -> None:
    """Brown-Conrady variants map to OpenCV's k1 k2 p1 p2 k3; 'none' and unknown models to zeros."""
    c = (-0.055, 0.065, 0.0004, 0.0007, -0.021)
    for model in ("brown_conrady", "inverse_brown_conrady", "modified_brown_conrady", "opencv"):
        intr = Intrinsics(1280, 720, 640, 640, 640, 360, model, c)
        np.testing.assert_array_equal(intr.opencv_distortion(), c)
    for model in ("none", "kannala_brandt4", "ftheta"):
        assert not Intrinsics(1280, 720, 640, 640, 640, 360, model, c).opencv_distortion().any()
