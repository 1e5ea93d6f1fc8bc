"""Checkerboard study on exactly rendered boards: known pose, known noise and bias."""

from __future__ import annotations

import numpy as np
import pytest
from checkerboard_render import pose_for, still_frames

from depthstation.core.board import Board
from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import rodrigues
from depthstation.core.run_warnings import collecting
from depthstation.evaluate.checkerboard.errors import BoardMismatchError
from depthstation.evaluate.checkerboard.metrics import fit_plane_moments, moment_matrix, svd_plane_rms
from depthstation.evaluate.checkerboard.run import say_warnings
from depthstation.evaluate.checkerboard.study import evaluate_frames

INTR = Intrinsics(640, 360, 320.0, 320.0, 319.5, 179.5)
ALIGNED = StreamInfo(INTR, INTR, depth_units_m=1e-4, depth_aligned_to_color=True)
NOISE_REL = 0.002   # sigma_z = 2 mm at 1 m, growing with z^2
BIAS = 0.003        # measured 3 mm too far (z)


def _expected(pose_depth: np.ndarray, u: np.ndarray, v: np.ndarray, intr: Intrinsics) -> tuple[float, float]:
    """Model truth over the board pixels: orthogonal noise RMS and mean orthogonal bias."""
    n = pose_depth[:3, 2]
    dot = n[0] * (u - intr.ppx) / intr.fx + n[1] * (v - intr.ppy) / intr.fy + n[2]
    z = float(n @ pose_depth[:3, 3]) / dot
    return float(np.sqrt(np.mean((NOISE_REL * z * z * dot) ** 2))), float(np.mean(BIAS * dot))


HD = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)
HD_INFO = StreamInfo(HD, HD, depth_units_m=1e-4, depth_aligned_to_color=True)


@pytest.mark.parametrize(("distance", "inclination"), [(1.0, 0.0), (1.5, 60.0), (3.0, 30.0)])
def test_recovers_pose_noise_and_bias(distance: float, inclination: float) -> None:
    board = Board()
    pose = pose_for(board, distance, inclination, azimuth_deg=20.0)
    frames = still_frames(board, pose, HD_INFO, 4, noise_rel=NOISE_REL, bias_m=BIAS)
    r = evaluate_frames("s", frames, HD_INFO, board, frames_requested=4, collect_samples=True)
    assert r.frames_used == 4 and r.reference_plane == "average"
    f = r.figures
    assert abs(f["distance_m"] - distance) < 0.005 * distance
    assert abs(f["inclination_deg"] - inclination) < 0.5
    assert r.samples is not None
    noise, acc = _expected(pose, r.samples.u, r.samples.v, HD)
    assert f["noise_m"] == pytest.approx(noise, rel=0.05)
    # this helper renderer (bilinear warp of a 2000 px/m print, 4x supersampling, linear grey
    # levels where the detector expects a camera's sRGB response) puts its own corners 0.04-0.09 px
    # off (measured against the projection); the pose from ~20 px squares carries up to ~0.08% of
    # the distance from that. The exact-coverage simulator holds the tight checks
    # (test_checkerboard_model.py, test_checkerboard_sim.py).
    assert abs(f["accuracy_m"] - acc) < max(0.001, 0.001 * distance)
    assert f["fill_rate"] == pytest.approx(1.0)
    # the squares are classed by colour as the renderer drew them (checked on the samples)
    assert r.samples.is_black.sum() > 1000 and r.samples.is_white.sum() > 1000
    assert not np.any(r.samples.is_black & r.samples.is_white)
    # a uniform bias makes no colour difference significant... on average; p-values are defined
    assert 0.0 <= f["noise_black_white_p"] <= 1.0


def test_unaligned_depth_through_extrinsics() -> None:
    """Depth and colour cameras apart (D4xx: colour ~15 mm to the side): the mask follows."""
    board = Board()
    color = Intrinsics(640, 360, 330.0, 330.0, 322.0, 178.0)
    m = np.eye(4)
    m[:3, :3] = rodrigues(np.array([0.0, 0.01, 0.0]))
    m[:3, 3] = [-0.015, 0.0, 0.001]
    d2c = Extrinsics.from_matrix(m)
    info = StreamInfo(INTR, color, depth_to_color=d2c, depth_units_m=1e-4)
    pose_c = pose_for(board, 1.2, 25.0)
    r = evaluate_frames("s", still_frames(board, pose_c, info, 4, noise_rel=NOISE_REL, bias_m=BIAS),
                        info, board, frames_requested=4, collect_samples=True)
    pose_d = np.linalg.inv(d2c.matrix) @ pose_c
    assert r.pose_depth is not None
    assert np.allclose(r.pose_depth[:3, 3], pose_d[:3, 3], atol=0.005)
    assert r.samples is not None
    noise, acc = _expected(pose_d, r.samples.u, r.samples.v, INTR)
    assert r.figures["noise_m"] == pytest.approx(noise, rel=0.05)
    assert abs(r.figures["accuracy_m"] - acc) < 0.0015
    assert r.figures["fill_rate"] == pytest.approx(1.0)  # a leak onto the wall would show in noise too


def test_frames_without_board_are_counted_and_short_recording_noted() -> None:
    board = Board()
    frames = list(still_frames(board, pose_for(board, 1.0, 10.0), ALIGNED, 3))
    assert frames[1].color is not None
    frames[1] = FrameSet(1, frames[1].timestamp_ns, frames[1].depth, np.full_like(frames[1].color, 120))
    r = evaluate_frames("s", frames, ALIGNED, board, frames_requested=5)
    assert r.frames_used == 2
    assert r.rejected == {"board not found": 1}
    assert any("fewer frames than asked" in n for n in r.notes)


def test_a_standpoint_cut_short_is_warned_without_frames_asked() -> None:
    """No --frames: a standpoint with far fewer frames than its siblings is warned of, others not."""
    board = Board()
    pose = pose_for(board, 1.0, 10.0)
    results = [evaluate_frames(name, still_frames(board, pose, ALIGNED, n), ALIGNED, board)
               for name, n in (("a", 6), ("b", 6), ("c", 2))]
    assert all(r.frames_requested is None and not r.notes for r in results)
    with collecting() as said:
        say_warnings(results)
    assert [(w.where, w.code) for w in said] == [("c", "fewer-frames")]


class _ShortRecording:
    """A recording of n still frames: just what `evaluate_recording` reads."""

    def __init__(self, board: Board, n: int) -> None:
        self.name, self.path, self.info, self.metadata = "short", "short.mcap", ALIGNED, {}
        self._frames = list(still_frames(board, pose_for(board, 1.0, 10.0), ALIGNED, n))
        self.limits: list[int | None] = []

    def frames(self, limit: int | None = None) -> list[FrameSet]:
        self.limits.append(limit)
        return self._frames[:limit]


def test_frames_read_up_to_a_cap_are_not_warned_of_only_frames_asked_for() -> None:
    """explain reads up to 30 frames per standpoint unless told: a 4-frame standpoint is not a
    fault then (it was, for every standpoint of a 10-frame protocol, and --strict failed), only when
    the user asked for more with --frames."""
    from depthstation.evaluate.checkerboard.study import evaluate_recording

    board = Board()
    rec = _ShortRecording(board, 4)
    r = evaluate_recording(rec, board, up_to=30)  # type: ignore[arg-type]
    assert rec.limits == [30] and r.frames_used == 4 and r.frames_requested is None and not r.notes
    r = evaluate_recording(rec, board, frames=6, up_to=30)  # type: ignore[arg-type]
    assert rec.limits[-1] == 6 and any("fewer frames than asked: 4 of 6" in n for n in r.notes)


def test_standpoint_without_board_is_reported_not_fatal() -> None:
    board = Board()
    frames = [FrameSet(k, k, np.full((360, 640), 10000, np.uint16), np.full((360, 640, 3), 90, np.uint8))
              for k in range(2)]
    r = evaluate_frames("empty", frames, ALIGNED, board, frames_requested=2)
    assert not r.usable and r.rejected == {"board not found": 2}
    assert any("no usable frame" in n for n in r.notes)


def test_board_with_swapped_colours_is_a_clear_error() -> None:
    printed = Board()
    described = Board(first_square_black=False)
    frames = still_frames(printed, pose_for(printed, 1.0, 0.0), ALIGNED, 2)
    with pytest.raises(BoardMismatchError, match="first_square_black = true"):
        evaluate_frames("s", frames, ALIGNED, described, frames_requested=2)


def test_even_board_half_turn_is_resolved_by_colour() -> None:
    """An 8 x 6 board seen upside down: OpenCV's corner order flips, the colours set it right."""
    board = Board(squares_x=8, squares_y=6, square_length_m=0.06)
    pose = pose_for(board, 1.0, 10.0)
    turn = np.eye(4)
    turn[:3, :3] = rodrigues(np.array([0.0, 0.0, np.pi]))
    turn[:3, 3] = [*board.size_m, 0.0]
    upside = pose @ turn  # the board turned by 180 deg about its centre, same colours
    for p in (pose, upside):
        r = evaluate_frames("s", still_frames(board, p, ALIGNED, 2), ALIGNED, board, frames_requested=2)
        assert r.pose_depth is not None and r.frames_used == 2
        assert np.allclose(r.pose_depth[:3, 3], pose[:3, 3], atol=0.01)


def test_charuco_rendered() -> None:
    board = Board(type="charuco", squares_x=7, squares_y=5, square_length_m=0.075,
                  marker_length_m=0.05625, dictionary="DICT_4X4_50")
    pose = pose_for(board, 0.9, 20.0)
    r = evaluate_frames("s", still_frames(board, pose, ALIGNED, 3, noise_rel=NOISE_REL), ALIGNED, board,
                        frames_requested=3)
    assert r.frames_used == 3
    assert abs(r.figures["distance_m"] - 0.9) < 0.0045
    assert abs(r.figures["inclination_deg"] - 20.0) < 0.5


def test_a_charuco_board_file_with_extra_rows_is_said() -> None:
    """The detector finds the markers a 7x7 board file shares with a 7x5 print, so the pose looks
    right while the board's centre and area reach past the print onto the wall (the audit: noise
    2.6 -> 69 mm, accuracy +49 mm, exit 0, no word). The print's own file says nothing."""
    from dataclasses import replace

    printed = Board(type="charuco", squares_x=7, squares_y=5, square_length_m=0.075,
                    marker_length_m=0.05625, dictionary="DICT_4X4_50")
    frames = list(still_frames(printed, pose_for(printed, 0.9, 10.0), ALIGNED, 2, noise_rel=NOISE_REL))
    right = evaluate_frames("s", frames, ALIGNED, printed, frames_requested=2)
    assert right.frames_used == 2 and "board-extent" not in [w.code for w in right.warnings]
    wrong = evaluate_frames("s", frames, ALIGNED, replace(printed, squares_y=7), frames_requested=2)
    said = [w.message for w in wrong.warnings if w.code == "board-extent"]
    assert len(said) == 1 and "squares_y 7" in said[0] and "beyond those found" in said[0]


def test_depth_that_does_not_lie_where_the_pose_puts_the_board_is_said() -> None:
    """Depth mirrored left to right (a flipped export): the board at 15 deg seen at -15 deg by the
    depth, a 30 deg disagreement the study computed and never said (noise 6x). Unmirrored: quiet."""
    board = Board()
    frames = list(still_frames(board, pose_for(board, 1.0, 15.0), ALIGNED, 2))
    right = evaluate_frames("s", frames, ALIGNED, board, frames_requested=2)
    assert "depth-pose-disagree" not in [w.code for w in right.warnings]
    assert right.figures["pose_depth_normal_angle_deg"] < 1.0
    flipped = [FrameSet(f.index, f.timestamp_ns, np.ascontiguousarray(f.depth[:, ::-1]), f.color)
               for f in frames]
    wrong = evaluate_frames("s", flipped, ALIGNED, board, frames_requested=2)
    said = [w.message for w in wrong.warnings if w.code == "depth-pose-disagree"]
    assert len(said) == 1 and "disagree by" in said[0]


def test_moment_plane_fit_equals_svd() -> None:
    rng = np.random.default_rng(1)
    p = rng.normal(size=(5000, 3)) * [0.3, 0.2, 0.002]
    p = p @ rodrigues(np.array([0.3, -0.2, 0.1])).T + [0.1, 0.0, 2.0]
    c = p.mean(axis=0)
    a = moment_matrix(*(p - c).T)
    assert fit_plane_moments(a)[2] == pytest.approx(svd_plane_rms(p), rel=1e-9)


def test_tracking_follows_a_still_board_and_lets_go_of_a_moved_one() -> None:
    """Corners are tracked from frame to frame only while they stay on the board's X-junctions."""
    from depthstation.evaluate.checkerboard.detection import BoardDetector

    board = Board()
    det = BoardDetector(board)
    a = next(still_frames(board, pose_for(board, 1.0, 10.0), ALIGNED, 1))
    b = next(still_frames(board, pose_for(board, 1.3, 30.0, azimuth_deg=40.0), ALIGNED, 1))
    assert a.color is not None and b.color is not None
    first = det.detect(a.color)
    again = det.detect(a.color)  # tracked: the same corners
    assert first is not None and again is not None
    assert np.allclose(again.image_points, first.image_points, atol=0.02)
    moved = det.detect(b.color)  # the board jumped: a fresh search, not stale corners
    fresh = BoardDetector(board).detect(b.color)
    assert moved is not None and fresh is not None
    assert np.allclose(moved.image_points, fresh.image_points, atol=0.02)
    assert det.detect(np.full_like(a.color, 120)) is None  # blank image: nothing tracked


def test_normal_std_matches_monte_carlo_of_pnp() -> None:
    """The pose's tilt uncertainty (Cramer-Rao from corner noise) equals the scatter of PnP poses
    from noisy corners: 5 m head-on, 12 px squares at 1280x720, 0.05 px corner noise."""
    import cv2

    from depthstation.core.board_pose import solve_board_pose
    from depthstation.evaluate.checkerboard.detection import Detection
    from depthstation.evaluate.checkerboard.pose import corner_noise_px, normal_std_deg

    board = Board()
    pose = pose_for(board, 5.0, 0.0, azimuth_deg=20.0)
    obj = board.corner_points()
    uv, _ = cv2.projectPoints(obj, cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], HD.K, np.zeros(5))
    uv = uv.reshape(-1, 2)
    sigma = 0.05
    rng = np.random.default_rng(0)
    tilts, noise = [], []
    for _ in range(400):
        det = Detection(uv + rng.normal(0.0, sigma, uv.shape), obj, np.arange(len(obj)))
        p = solve_board_pose(det.object_points, det.image_points, HD)
        assert p is not None
        noise.append(corner_noise_px(p, det, HD))
        tilts.append(np.cross(pose[:3, 2], p.matrix[:3, 2]))  # small-angle tilt vector (rad)
    t = np.asarray(tilts)
    cov = np.cov(t.T)
    measured = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov)[-1])))
    predicted = normal_std_deg(pose, obj, HD, sigma)
    assert measured == pytest.approx(predicted, rel=0.15)  # 400 samples: ~7% on a std
    assert np.mean(noise) == pytest.approx(sigma, rel=0.05)
    assert normal_std_deg(pose, obj, HD, sigma, frames=100) == pytest.approx(predicted / 10, rel=1e-6)



def test_a_board_half_out_of_view_has_the_pose_uncertainty_of_the_corners_seen() -> None:
    """A ChArUco board half out of view gives its pose from the corners seen: the scatter of PnP
    poses from those noisy corners is what the prediction weighted by the corners seen says, and
    wider than the whole board's prediction (which the U95 used: it shrank instead of growing)."""
    import cv2

    from depthstation.core.board_pose import solve_board_pose
    from depthstation.evaluate.checkerboard.pose import normal_std_deg
    from depthstation.evaluate.checkerboard.uncertainty import corner_counts, pose_covariance

    board = Board()
    pose = pose_for(board, 3.0, 20.0, azimuth_deg=10.0)
    obj = board.corner_points()
    seen = np.flatnonzero(obj[:, 0] < np.median(obj[:, 0]))  # the left half of the columns
    uv, _ = cv2.projectPoints(obj[seen], cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], HD.K, np.zeros(5))
    uv = uv.reshape(-1, 2)
    sigma = 0.05
    rng = np.random.default_rng(1)
    t, tilts = [], []
    for _ in range(400):
        p = solve_board_pose(obj[seen], uv + rng.normal(0.0, sigma, uv.shape), HD)
        assert p is not None
        t.append(p.matrix[:3, 3])
        tilts.append(np.cross(pose[:3, 2], p.matrix[:3, 2]))
    counts = corner_counts([seen], board)
    assert counts.sum() == len(seen) and set(np.flatnonzero(counts)) == set(seen)
    half = pose_covariance(pose, board, HD, sigma, counts)
    whole = pose_covariance(pose, board, HD, sigma)
    measured = np.std(np.asarray(t), axis=0, ddof=1)
    np.testing.assert_allclose(measured, np.sqrt(np.diag(half)[3:]), rtol=0.15)  # 400 samples: ~7 %
    assert np.all(np.sqrt(np.diag(whole)[3:]) < 0.8 * measured)  # the whole board's: optimistic
    tilt = float(np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(np.asarray(tilts).T))[-1])))
    assert normal_std_deg(pose, obj, HD, sigma, weights=counts) == pytest.approx(tilt, rel=0.15)
    # every corner seen in every one of 10 frames: the same as the whole board's over 10 frames
    ten = corner_counts([np.arange(len(obj))] * 10, board)
    np.testing.assert_allclose(pose_covariance(pose, board, HD, sigma, ten), whole / 10, rtol=1e-9)


def test_colour_tests_give_scipy_stats_p_values_without_importing_it() -> None:
    """Welch's and the paired t-test of black against white squares, written on scipy.special:
    the p-values of scipy.stats.ttest_ind(equal_var=False) and ttest_rel, edge cases included."""
    import warnings

    from scipy import stats

    from depthstation.evaluate.checkerboard.study import colour_tests

    rng = np.random.default_rng(3)
    cases = []
    for _ in range(60):
        n = int(rng.integers(3, 40))
        b = rng.normal(0.1, rng.uniform(1e-4, 0.01), n)
        cases.append((b, b * rng.uniform(0.5, 1.5) + rng.normal(rng.uniform(-0.01, 0.01), 0.005, n)))
    cases += [(np.array([1.0, 1, 1]), np.array([1.0, 2, 3])),  # one side constant
              (np.array([1.0, 2, 3]), np.array([2.0, 3, 4])),  # a constant difference: paired p = 0
              (np.array([1.0, 2, 3]), np.array([1.0, 2, 3]))]  # identical: no difference to test
    for b, w in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            want = (stats.ttest_ind(b, w, equal_var=False).pvalue, stats.ttest_rel(b, w).pvalue)
        got = colour_tests(list(b), list(w))
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=0, equal_nan=True)
    assert all(np.isnan(colour_tests([0.1, 0.1, 0.1], [0.2, 0.2, 0.2])))  # no spread on either side
