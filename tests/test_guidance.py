"""Guidance: live board pose from a rendered colour image, the move instructions, stillness, end of range."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.acquire.board_detection import board_mask, board_pose, fill_rate
from depthstation.acquire.guidance import StillnessTracker, end_of_range, guide
from depthstation.core.board import Board
from depthstation.core.board_pose import pose_metrics
from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo, project
from depthstation.core.geometry import look_at
from depthstation.core.protocol import Standpoint, Tolerances

BOARD = Board()
INTR = Intrinsics(640, 360, 320.0, 320.0, 319.5, 179.5)


def pose_at(distance_m: float, azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Board-to-camera pose of a camera `distance_m` from the board centre, walked round by azimuth
    (+ = to the operator's left, i.e. towards board -x), looking at the centre, upright."""
    c = BOARD.center
    a = np.radians(azimuth_deg)
    # board z points into the board; the camera stands on the -z side
    eye = c + distance_m * np.array([-np.sin(a), 0.0, -np.cos(a)])
    cam_to_board = look_at(eye, c, up=np.array([0.0, -1.0, 0.0]))
    board_to_cam = np.linalg.inv(cam_to_board)
    return board_to_cam[:3, :3], board_to_cam[:3, 3]


def render(r: np.ndarray, t: np.ndarray, intr: Intrinsics = INTR) -> np.ndarray:
    """A flat-shaded checkerboard on a white plate, projected with the pinhole model."""
    import cv2

    img = np.full((intr.height, intr.width, 3), 90, np.uint8)
    s = BOARD.square_length_m
    m = 0.04
    w, h = BOARD.size_m
    plate = np.array([[-m, -m, 0], [w + m, -m, 0], [w + m, h + m, 0], [-m, h + m, 0]])
    uv = project(intr, plate @ r.T + t)
    cv2.fillConvexPoly(img, np.round(uv * 16).astype(np.int32), (255, 255, 255), cv2.LINE_AA, 4)
    for j in range(BOARD.squares_y):
        for i in range(BOARD.squares_x):
            if BOARD.is_black(np.array((i + 0.5) * s), np.array((j + 0.5) * s)):
                q = np.array([[i * s, j * s, 0], [(i + 1) * s, j * s, 0],
                              [(i + 1) * s, (j + 1) * s, 0], [i * s, (j + 1) * s, 0]])
                uv = project(intr, q @ r.T + t)
                cv2.fillConvexPoly(img, np.round(uv * 16).astype(np.int32), (0, 0, 0), cv2.LINE_AA, 4)
    return img


def test_pose_metrics_sign_and_values() -> None:
    for az in (-40.0, -10.0, 0.0, 25.0):
        r, t = pose_at(1.5, az)
        d, inc, signed = pose_metrics(BOARD, r, t)
        assert d == pytest.approx(1.5, abs=1e-9)
        assert inc == pytest.approx(abs(az), abs=1e-6)
        assert signed == pytest.approx(az, abs=1e-6)


@pytest.mark.parametrize(("dist", "az"), [(1.0, 0.0), (1.4, 30.0), (1.2, -20.0)])
def test_board_pose_from_rendered_image(dist: float, az: float) -> None:
    # the colour camera sits 59 mm to the right of the depth camera (D455-like)
    d2c = Extrinsics(translation=(-0.059, 0.0, 0.0))
    r, t = pose_at(dist, az)  # pose in the depth frame
    r_c, t_c = d2c.R @ r, d2c.R @ t + d2c.t
    info = StreamInfo(INTR, INTR, d2c)
    pose = board_pose(render(r_c, t_c), BOARD, info)
    assert pose is not None
    d_true, inc_true, az_true = pose_metrics(BOARD, r, t)
    # EPnP on 24 sub-pixel corners at VGA-like resolution: about 1 cm / 1 degree at 1.4 m
    assert pose.distance_m == pytest.approx(d_true, abs=0.01 * dist)
    assert pose.inclination_deg == pytest.approx(inc_true, abs=1.5)
    assert np.sign(pose.azimuth_deg) == np.sign(az_true) or abs(az_true) < 2
    assert pose.center_px[0] == pytest.approx(INTR.ppx, abs=3)


def test_no_board_is_none() -> None:
    info = StreamInfo(INTR, INTR)
    assert board_pose(np.full((360, 640, 3), 128, np.uint8), BOARD, info) is None


def test_guidance_says_how_to_move() -> None:
    tol = Tolerances(distance_m=0.05, inclination_deg=3.0)
    target = Standpoint("standpoint_02", 0, 1.4, 0.0)
    g = guide(target, tol, distance_m=1.2, inclination_deg=5.0, azimuth_deg=-5.0)
    assert g.text.startswith("1.20 m -> 1.40 m")
    assert "step back 20 cm" in g.text
    assert "to your left" in g.text and "(5°)" in g.text
    assert not g.in_tolerance
    g = guide(Standpoint("s", 1, 1.0, 30.0, "left"), tol, distance_m=1.1, inclination_deg=20.0,
              azimuth_deg=20.0)
    assert "step closer 10 cm" in g.text
    assert "left" in g.text and g.delta_azimuth_deg == pytest.approx(10.0)
    # right side target: standing on the left at 30 degrees is 60 degrees off
    g = guide(Standpoint("s", 1, 1.0, 30.0, "right"), tol, distance_m=1.0, inclination_deg=30.0,
              azimuth_deg=30.0)
    assert g.delta_azimuth_deg == pytest.approx(-60.0) and "to your right" in g.text
    g = guide(target, tol, distance_m=1.43, inclination_deg=2.0, azimuth_deg=2.0,
              center_px=(500.0, 180.0), image_size=(640, 360), fx=320.0)
    assert "turn" in g.text and "right" in g.text and not g.in_tolerance
    g = guide(target, tol, distance_m=1.43, inclination_deg=2.0, azimuth_deg=2.0,
              center_px=(330.0, 170.0), image_size=(640, 360), fx=320.0)
    assert g.in_tolerance and "hold still" in g.text
    g = guide(target, tol, distance_m=None, inclination_deg=None, azimuth_deg=None)
    assert not g.seen and "board not found" in g.text


def test_stillness_needs_the_whole_window() -> None:
    tr = StillnessTracker(seconds=1.0, translation_m=0.01, rotation_deg=0.5)
    rng = np.random.default_rng(1)
    c = np.array([0.0, 0.0, 1.5])
    still = [tr.update(int(i * 1e9 / 30), c + rng.normal(0, 0.001, 3)) for i in range(40)]
    assert not any(still[:30]) and all(still[31:])
    # a 3 cm shift restarts the window
    c2 = c + np.array([0.03, 0, 0])
    assert not tr.update(int(40 * 1e9 / 30), c2)
    still = [tr.update(int(i * 1e9 / 30), c2) for i in range(41, 80)]
    assert not any(still[:29]) and still[-1]
    # turning the camera by 1 degree moves the bearing, not the range: also restarts the window
    a = np.radians(1.0)
    c3 = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ c2
    tr2 = StillnessTracker(seconds=1.0, translation_m=0.05, rotation_deg=0.5)
    for i in range(40):
        tr2.update(int(i * 1e9 / 30), c2)
    assert not tr2.update(int(40 * 1e9 / 30), c3)
    # one missed detection does not restart the window; four in a row do
    assert not tr.update(int(81 * 1e9 / 30), None)
    assert tr.update(int(82 * 1e9 / 30), c2)
    for i in range(83, 87):
        tr.update(int(i * 1e9 / 30), None)
    assert not tr.update(int(87 * 1e9 / 30), c2)


def test_stillness_rejects_the_first_frames_of_a_step() -> None:
    """The demo's standpoint_01: standing 0.43 s at 0.945 m, then a step back whose first frame
    moves the centre 6.7 mm (inside the 1 cm of the window): the camera is leaving, not still."""
    tr = StillnessTracker(seconds=0.5, translation_m=0.01, rotation_deg=0.5)
    c = np.array([0.0, 0.0, 0.945])
    for i in range(14):
        tr.update(int(i * 1e9 / 30), c)
    step = c + np.array([0.0, 0.0, 0.0067])
    assert not tr.update(int(14 * 1e9 / 30), step)
    assert not tr.update(int(15 * 1e9 / 30), step)  # the same view again: still the window's odd one
    # where it stops, it becomes still once it stood there for the window
    stop = c + np.array([0.0, 0.0, 0.073])
    still = [tr.update(int(i * 1e9 / 30), stop) for i in range(16, 40)]
    assert not any(still[:14]) and all(still[15:])
    # tremor of 1 mm per axis at a stop does not keep a camera from being still
    rng = np.random.default_rng(3)
    tr2 = StillnessTracker(seconds=0.5, translation_m=0.01, rotation_deg=0.5)
    still = [tr2.update(int(i * 1e9 / 30), c + rng.normal(0, 0.001, 3)) for i in range(60)]
    assert sum(still[20:]) >= 35


def test_end_of_range_and_fill_rate() -> None:
    r, t = pose_at(1.0, 0.0)
    from depthstation.core.board_pose import BoardPose

    pose = BoardPose(r, t, np.zeros((0, 2)), 1.0, 0.0, 0.0, (319.5, 179.5))
    mask = board_mask(pose, BOARD, INTR)
    # the board covers 0.665 x 0.475 m at 1 m with f = 320 px: about 213 x 152 px
    assert mask.sum() == pytest.approx(0.665 * 320 * 0.475 * 320, rel=0.05)
    depth = np.zeros((360, 640), np.uint16)
    depth[mask] = 1000
    depth[::2] = 0
    assert fill_rate(depth, mask) == pytest.approx(0.5, abs=0.02)
    assert not end_of_range([0.9, 0.1, 0.1, 0.1, 0.1], 0.2)
    assert end_of_range([0.9, 0.1, 0.1, 0.1, 0.1, 0.05], 0.2)
