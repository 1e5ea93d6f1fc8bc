"""One standpoint of the checkerboard study: first N frames -> averaged pose, noise, accuracy, colours."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import stdtr

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, StreamInfo, ray_xy
from depthstation.core.capture.recording import Recording
from depthstation.core.errors import EvaluationError
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import average_poses, inclination_deg
from depthstation.core.run_warnings import RunWarning
from depthstation.evaluate.checkerboard.detection import OUTLIER_FLOOR_PX, unconfirmed
from depthstation.evaluate.checkerboard.dqt import DQT_COLUMNS, standpoint_figures
from depthstation.evaluate.checkerboard.frame import FrameEvaluator, FramePixels, FrameResult
from depthstation.evaluate.checkerboard.mask import BLACK, WHITE
from depthstation.evaluate.checkerboard.metrics import plane_distance_stats
from depthstation.evaluate.checkerboard.pose import normal_std_deg
from depthstation.evaluate.checkerboard.uncertainty import (
    NOISE_TYPE_B,
    STATIC_FLOOR_PX,
    corner_counts,
    corner_errors,
    coverage_factor,
    folded_angle,
    pose_covariance,
    pose_spread,
    propagate,
)

FrameCallback = Callable[[FrameSet, FrameResult], None]

# |accuracy| above this share of the distance is a wrong board size or depth unit, not the camera
BOARD_SCALE_TOLERANCE = 0.05


DEFAULT_FRAMES = 150  # the paper's frames per standpoint: read at most this many unless told

@dataclass
class PixelSamples:
    """Per-pixel samples of a standpoint (contract 3, for explain); one entry per valid board pixel."""

    frame: NDArray[np.int32]          # frame index in the recording
    u: NDArray[np.int32]              # depth pixel column
    v: NDArray[np.int32]              # depth pixel row
    z_ref_m: NDArray[np.float32]      # reference-plane z-depth along the pixel's ray
    z_meas_m: NDArray[np.float32]     # measured z-depth
    error_m: NDArray[np.float32]      # signed orthogonal distance to the reference plane (+ = behind)
    inclination_deg: NDArray[np.float32]
    is_black: NDArray[np.bool_]
    is_white: NDArray[np.bool_]       # False on square edges and ChArUco markers (neither class)
    timestamp_ns: NDArray[np.int64]
    temperature_c: NDArray[np.float32]  # NaN where the frame had none

    def to_dict(self) -> dict[str, NDArray[Any]]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def __len__(self) -> int:
        return int(self.u.size)


@dataclass
class ExampleFrame:
    """One frame's per-pixel residuals (paper Fig. 5): NaN off the board."""

    index: int
    noise_map_m: NDArray[np.float32]     # signed distance to the frame's own fitted plane
    accuracy_map_m: NDArray[np.float32]  # signed distance to the reference plane
    v0: int
    u0: int


@dataclass
class StandpointResult:
    """A standpoint's figures (DESIGN §2 conventions) plus its frames and optional samples."""

    name: str
    path: str
    frames_requested: int | None  # None: the user asked for no number (up to DEFAULT_FRAMES read)
    frames_read: int
    frames: list[FrameResult]
    rejected: dict[str, int]
    notes: list[str] = field(default_factory=list)
    warnings: list[RunWarning] = field(default_factory=list)  # the notes a user must see, with codes
    pose_depth: NDArray[np.float64] | None = None       # averaged board -> depth camera
    camera_in_board: NDArray[np.float64] | None = None  # averaged colour camera pose in the board frame
    figures: dict[str, float] = field(default_factory=dict)
    reference_plane: str = "average"                    # 'average' (still camera) or 'frame' (moved)
    example: ExampleFrame | None = None
    samples: PixelSamples | None = None
    truth: dict[str, Any] | None = None

    def note(self, code: str, message: str) -> None:
        """A note that is also a warning of the run (said on the console, listed in result.json)."""
        self.notes.append(message)
        self.warnings.append(RunWarning(message, self.name, code))

    @property
    def frames_used(self) -> int:
        return sum(1 for f in self.frames if f.ok)

    @property
    def usable(self) -> bool:
        return self.frames_used > 0

    def row(self) -> dict[str, Any]:
        """One row of standpoints.csv."""
        return {"standpoint": self.name, "frames": self.frames_used,
                "frames_read": self.frames_read, **self.figures}


def _mean_std(values: list[float]) -> tuple[float, float]:
    a = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    if a.size == 0:
        return float("nan"), float("nan")
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else float("nan")


def frame_corner_noise_px(r: FrameResult) -> float:
    """Per-coordinate corner noise (px) of one frame from its reprojection residuals.

    The same figure as `pose.corner_noise_px` (residual sum of squares over 2N - 6 degrees of
    freedom), recovered exactly from the frame's RMS over its N corners, so no residual has to be
    kept. It holds random noise plus the part of a static corner error the pose cannot absorb.
    """
    if not np.isfinite(r.reprojection_px) or r.corners < 1:
        return float("nan")
    return float(r.reprojection_px * np.sqrt(r.corners / max(2 * r.corners - 6, 1)))


def frame_inclination_deg(r: FrameResult, board: Board) -> float:
    """Inclination (deg) from this frame's own pose alone: depth-camera ray to the centre vs normal."""
    if r.pose_depth is None:
        return float("nan")
    return float(inclination_deg(r.pose_depth[:3, :3] @ board.center + r.pose_depth[:3, 3],
                                 r.pose_depth[:3, 2]))


def pose_uncertainty(ok: list[FrameResult], board: Board, intr: Intrinsics,
                     camera_in_board: NDArray[np.float64]) -> dict[str, float]:
    """The reference pose's own uncertainty from random corner noise (paper Fig. 4's concern).

    inclination_std_deg: Cramer-Rao std of the averaged pose's normal direction (the worse tilt
    axis) from the mean per-frame corner noise over the frames used; an upper bound of the
    inclination's std (equal when the worse tilt lies in the plane of ray and normal).
    inclination_frame_std_deg: the empirical std of the per-frame pose inclinations (single
    frame; compare with inclination_std_deg x sqrt(frames)). Neither contains a static corner
    bias, which is the same in every frame and does not average.
    """
    noise = _mean_std([frame_corner_noise_px(r) for r in ok])[0]
    f = {"corner_noise_px": noise}
    if np.isfinite(noise):
        pose = np.asarray(np.linalg.inv(camera_in_board), dtype=np.float64)  # board -> colour
        ids = [r.corner_ids for r in ok if r.corner_ids is not None]
        f["inclination_std_deg"] = normal_std_deg(pose, board.corner_points(), intr, noise, frames=len(ok),
                                                  weights=corner_counts(ids, board) * len(ok) / len(ids)
                                                  if ids else None)
    else:
        f["inclination_std_deg"] = float("nan")
    f["inclination_frame_std_deg"] = _mean_std([frame_inclination_deg(r, board) for r in ok])[1]
    return f


def expanded_uncertainties(ok: list[FrameResult], board: Board, info: StreamInfo,
                           camera_in_board: NDArray[np.float64], f: dict[str, float],
                           use_frame: bool) -> dict[str, float]:
    """U95 of distance, inclination, noise and accuracy (see `uncertainty.py` for the sources)."""
    intr = _colour_intrinsics(info)
    n = len(ok)
    k = coverage_factor(n)
    d2c = np.eye(4) if info.depth_aligned_to_color else info.depth_to_color.matrix
    pose_c = np.asarray(np.linalg.inv(camera_in_board), dtype=np.float64)  # board -> colour
    seen = [r for r in ok
            if r.corner_ids is not None and r.corners_px is not None and r.pose_color is not None]
    ce = corner_errors([r.corner_ids for r in seen], [r.corners_px for r in seen],  # type: ignore[misc]
                       [r.pose_color for r in seen], board, intr)  # type: ignore[misc]
    out: dict[str, float] = {"corner_random_px": ce.random_px, "corner_static_px": ce.static_px}
    nan = float("nan")
    if not (np.isfinite(ce.random_px) and np.isfinite(ce.static_px)):
        return {**out, "distance_m_u95": nan, "inclination_deg_u95": nan, "noise_m_u95": nan,
                "accuracy_m_u95": nan}
    static = max(ce.static_px, STATIC_FLOOR_PX)
    # each corner counts as often as frames saw it (a ChArUco board partly out of view): the random
    # part averages over those sightings, the static one weighs each corner by its share of frames
    counts = corner_counts([r.corner_ids for r in seen], board)  # type: ignore[misc]
    share = counts / len(seen)
    rnd = propagate(pose_c, d2c, board, pose_covariance(pose_c, board, intr, ce.random_px, share * n))
    sta = propagate(pose_c, d2c, board, pose_covariance(pose_c, board, intr, static, share))
    # the pose's random part: the corners' noise (Cramer-Rao) or the frames' own scatter of the
    # pose, whichever is larger (the scatter holds what else moves a frame's pose)
    spread = pose_spread([r.pose_depth for r in ok if r.pose_depth is not None], board, rnd["basis"])
    lift = max(ce.random_px, STATIC_FLOOR_PX) / ce.random_px if ce.random_px > 0 else float("inf")
    d_emp = f["reference_distance_std_m"] / np.sqrt(n) if n > 1 else nan
    u_d = np.sqrt(max(rnd["distance_var"], d_emp ** 2 if np.isfinite(d_emp) else 0.0) + sta["distance_var"])
    _, u_inc = folded_angle(rnd["tilt"], rnd["tilt_cov"] + sta["tilt_cov"], k)
    if np.all(np.isfinite(spread["tilt_cov"])):
        u_inc = max(u_inc, folded_angle(rnd["tilt"], spread["tilt_cov"] / n + sta["tilt_cov"], k)[1])
    u_noise = np.sqrt(f["noise_std_m"] ** 2 / n + (NOISE_TYPE_B * f["noise_m"]) ** 2) if n > 1 else nan
    # the reference plane: with the averaged pose its random error is not in the frames' scatter
    acc_a = f["accuracy_std_m"] / np.sqrt(n) if n > 1 else nan
    plane = max(rnd["offset_var"], spread["offset_var"] / n if np.isfinite(spread["offset_var"]) else 0.0)
    u_acc = np.sqrt(acc_a ** 2 + sta["offset_var"] + (0.0 if use_frame else plane))
    out.update(distance_m_u95=float(k * u_d), inclination_deg_u95=float(u_inc),
               noise_m_u95=float(k * u_noise), accuracy_m_u95=float(k * u_acc),
               pose_spread_ratio=spread_ratio(rnd, spread, n, lift))
    return out


def spread_ratio(cramer_rao: dict[str, Any], spread: dict[str, Any], frames: int,
                 floor: float = 1.0) -> float:
    """How many times the frames' scatter of the pose (distance, tilt) exceeds what the corners'
    noise predicts for one frame (Cramer-Rao of the mean x frames): about 1 where the corners' noise
    is all that moves the pose; NaN with fewer than 3 frames. The larger of the two. `floor`: the
    factor that lifts the corners' noise to the smallest the station tells apart (STATIC_FLOOR_PX:
    identical simulated frames scatter by nothing against nothing)."""
    if frames < 3 or not np.isfinite(floor):
        return float("nan")
    ratios = []
    d_cr = cramer_rao["distance_var"] * frames * floor ** 2
    if d_cr > 0 and np.isfinite(spread["distance_var"]):
        ratios.append(np.sqrt(spread["distance_var"] / d_cr))
    t_cr = np.asarray(cramer_rao["tilt_cov"]) * frames * floor ** 2
    t_sp = np.asarray(spread["tilt_cov"])
    if np.all(np.isfinite(t_sp)) and np.all(np.isfinite(t_cr)) and np.linalg.det(t_cr) > 0:
        # the largest ratio of variances over all tilt directions (generalised eigenvalue)
        ratios.append(np.sqrt(max(float(np.max(np.linalg.eigvals(np.linalg.solve(t_cr, t_sp)).real)), 0.0)))
    return float(max(ratios)) if ratios else float("nan")


def _t_p(t: float, dof: float) -> float:
    """Two-sided p of a t statistic (scipy.stats' t tail, from scipy.special: scipy.stats took
    0.5-1 s to import, in a standpoint's thread, holding the GIL the other standpoints wait for)."""
    if np.isnan(t) or np.isnan(dof):
        return float("nan")
    return float(2.0 * stdtr(dof, -abs(t)))


def colour_tests(black: list[float], white: list[float]) -> tuple[float, float]:
    """p-values that black and white squares differ: Welch t over frames, paired t per frame
    (`scipy.stats.ttest_ind(equal_var=False)` and `ttest_rel`, written out)."""
    b = np.asarray(black, dtype=np.float64)
    w = np.asarray(white, dtype=np.float64)
    keep = np.isfinite(b) & np.isfinite(w)
    b, w = b[keep], w[keep]
    if b.size < 3 or (np.ptp(b) == 0 and np.ptp(w) == 0):
        return float("nan"), float("nan")
    n = b.size
    with np.errstate(divide="ignore", invalid="ignore"):
        vb, vw = np.var(b, ddof=1) / n, np.var(w, ddof=1) / n
        welch_t = (np.mean(b) - np.mean(w)) / np.sqrt(vb + vw)
        welch_dof = (vb + vw) ** 2 / (vb ** 2 / (n - 1) + vw ** 2 / (n - 1))
        d = b - w
        paired_t = np.mean(d) / np.sqrt(np.var(d, ddof=1) / n)
    return _t_p(float(welch_t), float(welch_dof)), _t_p(float(paired_t), float(n - 1))


def evaluate_frames(name: str, frames: Iterable[FrameSet], info: StreamInfo, board: Board, *,
                    frames_requested: int | None = None, collect_samples: bool = False,
                    sample_stride: int = 1, refine: bool = True, margin_m: float = 0.01,
                    path: str = "", on_frame: FrameCallback | None = None,
                    reference: str = "auto", roi: float | None = None) -> StandpointResult:
    """The study of one standpoint from any frame source (one pass over the frames); `roi`: the
    Depth Quality Tool's centred ROI (fraction of each side) besides the board mask."""
    ev = FrameEvaluator(info, board, refine=refine, margin_m=margin_m, source=path or name, roi=roi)
    results: list[FrameResult] = []
    kept: list[tuple[FrameResult, FramePixels]] = []
    example: tuple[FrameResult, FramePixels] | None = None
    for fs in frames:
        want = collect_samples or example is None
        res, pixels = ev.evaluate(fs, keep_pixels=want)
        results.append(res)
        if pixels is not None:
            if example is None:
                example = (res, pixels)
            if collect_samples:
                if sample_stride > 1:
                    sl = slice(None, None, sample_stride)
                    pixels = FramePixels(pixels.u[sl], pixels.v[sl], pixels.z_m[sl], pixels.colour[sl])
                kept.append((res, pixels))
        if on_frame is not None:
            on_frame(fs, res)
    units = info.depth_units_m
    return aggregate(name, results, info, board, frames_requested=frames_requested, path=path,
                     kept=kept if collect_samples else None, example=example, reference=reference,
                     temporal_pct={"dqt_": ev.temporal.noise_pct(units),
                                   "dqt_roi_": ev.temporal_roi.noise_pct(units)})


def evaluate_recording(rec: Recording, board: Board, *, frames: int | None = None,
                       up_to: int = DEFAULT_FRAMES, collect_samples: bool = False, sample_stride: int = 1,
                       refine: bool = True, margin_m: float = 0.01, on_frame: FrameCallback | None = None,
                       reference: str = "auto", roi: float | None = None) -> StandpointResult:
    """Contract 3: the checkerboard study of one recording (its first `frames` frames, or up to
    `up_to` when none were asked for: then a short recording is not warned of here).

    reference: 'average' (the standpoint's averaged pose, the paper's method), 'frame' (each
    frame's own pose) or 'auto' (average unless the camera moved during the standpoint).
    """
    result = evaluate_frames(rec.name, rec.frames(limit=frames or up_to), rec.info, board,
                             frames_requested=frames, collect_samples=collect_samples,
                             sample_stride=sample_stride, refine=refine, margin_m=margin_m,
                             path=str(rec.path), on_frame=on_frame, reference=reference, roi=roi)
    truth = rec.metadata.get("truth") if isinstance(rec.metadata, dict) else None
    if isinstance(truth, dict):
        result.truth = truth
    return result


def aggregate(name: str, results: list[FrameResult], info: StreamInfo, board: Board, *,
              frames_requested: int | None, path: str = "",
              kept: list[tuple[FrameResult, FramePixels]] | None = None,
              example: tuple[FrameResult, FramePixels] | None = None, reference: str = "auto",
              max_corner_shift_px: float = 2.0,
              temporal_pct: dict[str, float] | None = None) -> StandpointResult:
    """Standpoint figures from per-frame results: averaged pose, then accuracy against its plane.

    The paper's standpoints are still, so the averaged pose is the better reference (pose noise
    averages out). When the corners moved by more than `max_corner_shift_px` the camera was not
    still and, with reference='auto', each frame is compared with its own pose instead.
    """
    rejected = Counter(r.status for r in results if not r.ok)
    out = StandpointResult(name, path, frames_requested, len(results), results, dict(rejected))
    if frames_requested is not None and len(results) < frames_requested:
        out.note("fewer-frames", f"fewer frames than asked: {len(results)} of {frames_requested} (--frames)")
    ok = [r for r in results if r.ok]
    posed = [r for r in results if r.pose_depth is not None]
    if not ok:
        out.note("no-usable-frame", "no usable frame" + (
            f" ({', '.join(f'{k}: {v}' for k, v in rejected.items())})" if rejected else ""))
        out.figures = {"distance_m": float("nan"), "inclination_deg": float("nan")}
        return out
    pose = average_poses(np.stack([r.pose_depth for r in ok]))  # type: ignore[misc]
    out.pose_depth = pose
    out.camera_in_board = average_poses(np.stack([np.linalg.inv(r.pose_color) for r in ok]))  # type: ignore[arg-type]
    r_avg, t_avg = pose[:3, :3], pose[:3, 3]
    centre = r_avg @ board.center + t_avg
    normal = r_avg[:, 2]  # board z: into the board, away from the camera
    shift = max((r.corner_shift_px for r in ok if np.isfinite(r.corner_shift_px)), default=0.0)
    moved = shift > max_corner_shift_px
    use_frame = reference == "frame" or (reference == "auto" and moved)
    out.reference_plane = "frame" if use_frame else "average"
    if moved:
        out.note("camera-moved",
                 f"the camera moved during the standpoint (corners shifted up to {shift:.1f} px)"
                 + ("; accuracy is taken against each frame's own pose" if use_frame else ""))
    for r in ok:
        assert r.pose_depth is not None
        n_own = r.pose_depth[:3, 2]
        off_own = float(n_own @ (r.pose_depth[:3, 3] - r.origin))
        r.accuracy_own_m, r.accuracy_own_rms_m = plane_distance_stats(r.moments["all"], n_own, off_own)
        n_ref, off = (n_own, off_own) if use_frame else (normal, float(normal @ (t_avg - r.origin)))
        r.accuracy_m, r.accuracy_rms_m = plane_distance_stats(r.moments["all"], n_ref, off)
        r.accuracy_black_m = plane_distance_stats(r.moments["black"], n_ref, off)[0]
        r.accuracy_white_m = plane_distance_stats(r.moments["white"], n_ref, off)[0]
    f: dict[str, float] = {}
    f["distance_m"] = float(centre[2])
    # DESIGN §2: the standpoint's inclination is the ray to the board centre against the board
    # normal, both from the averaged board POSE (independent of the depth it is used to judge)
    f["inclination_deg"] = float(inclination_deg(centre, normal))
    # diagnostic: the tilt of the depth itself (a plane fitted in disparity space) and its angle to
    # the pose's normal; a depth wedge (e.g. a left/right focal mismatch) shows here, not above
    if moved:  # one plane per frame, each against its own pose (a moving camera sees many planes)
        f["inclination_deg"] = float(np.mean([inclination_deg(r.pose_depth[:3, :3] @ board.center  # type: ignore[index]
                                                              + r.pose_depth[:3, 3], r.pose_depth[:3, 2])  # type: ignore[index]
                                              for r in ok]))
        per_frame = [(_depth_normal([r], r.origin), r) for r in ok]
        incl = [inclination_deg(r.origin, n) for n, r in per_frame if n is not None]
        gap = [_angle_deg(n, r.pose_depth[:3, 2]) for n, r in per_frame  # type: ignore[index]
               if n is not None]
        f["inclination_depth_deg"] = float(np.mean(incl)) if incl else float("nan")
        f["pose_depth_normal_angle_deg"] = float(np.mean(gap)) if gap else float("nan")
    else:  # one plane through the pixels of all frames: the most precise tilt of the depth
        depth_normal = _depth_normal(ok, centre)
        if depth_normal is None:
            f["inclination_depth_deg"] = float("nan")
            f["pose_depth_normal_angle_deg"] = float("nan")
        else:
            f["inclination_depth_deg"] = float(inclination_deg(centre, depth_normal))
            f["pose_depth_normal_angle_deg"] = _angle_deg(depth_normal, normal)
    f["reference_distance_std_m"] = _mean_std([r.reference_distance_m for r in ok])[1]
    f["reprojection_px"] = _mean_std([r.reprojection_px for r in ok])[0]
    f.update(pose_uncertainty(ok, board, _colour_intrinsics(info), out.camera_in_board))
    f["fill_rate"], f["fill_rate_std"] = _mean_std([r.fill_rate for r in posed])
    for key in ("noise", "accuracy", "accuracy_rms", "noise_black", "noise_white",
                "accuracy_black", "accuracy_white"):
        mean, std = _mean_std([getattr(r, key + "_m") for r in ok])
        f[key + "_m"], f[key + "_std_m"] = mean, std
    f["noise_black_white_p"], f["noise_black_white_paired_p"] = colour_tests(
        [r.noise_black_m for r in ok], [r.noise_white_m for r in ok])
    f["accuracy_black_white_p"], f["accuracy_black_white_paired_p"] = colour_tests(
        [r.accuracy_black_m for r in ok], [r.accuracy_white_m for r in ok])
    f["accuracy_frame_pose_m"] = _mean_std([r.accuracy_own_m for r in ok])[0]
    f["corner_shift_px"] = shift
    f["pixels_per_frame"] = _mean_std([float(r.valid_pixels) for r in ok])[0]
    f.update(expanded_uncertainties(ok, board, info, out.camera_in_board, f, use_frame))
    f.update(_dqt_figures(ok, info, pose, use_frame, temporal_pct or {}))
    out.figures = f
    dropped = {k: v for k, v in rejected.items() if unconfirmed(k)}
    if dropped:
        out.note("corner-unconfirmed",
                 f"{sum(dropped.values())} of {len(results)} frames dropped for a board corner no detector "
                 f"confirmed ({max(dropped, key=lambda k: dropped[k])}"
                 f"{', and others' if len(dropped) > 1 else ''}): the board is hard to detect here and the "
                 f"pose rests on the other {len(ok)} frames; their U95 holds the pose's scatter, not a "
                 f"corner error below the check's bound ({OUTLIER_FLOOR_PX} px)")
    spread = f.get("pose_spread_ratio", float("nan"))
    # NaN compares False: too few frames to tell; a camera that moved scatters by its motion (said)
    if spread > POSE_SPREAD_RATIO and not moved:
        out.note("pose-spread",
                 f"the board's pose scatters {spread:.1f}x more from frame to frame than its corners' noise "
                 f"explains (distance {f['reference_distance_std_m'] * 1000:.2f} mm, inclination "
                 f"{f['inclination_frame_std_deg']:.3f} deg per frame): the pose is unstable here (a far "
                 "or steep board, a corner that comes and goes, vibration); the U95 of distance, inclination "
                 "and accuracy hold that scatter, not a bias it may hide")
    tilt = f.get("pose_depth_normal_angle_deg", float("nan"))
    if tilt > DEPTH_POSE_TILT_DEG:  # NaN compares False: no depth plane, nothing to say
        out.note("depth-pose-disagree",
                 f"the depth's plane and the board's pose disagree by {tilt:.1f} deg: the depth does not lie "
                 "where the colour image puts the board (a wrong depth_to_color, mirrored or flipped depth, "
                 "another camera's intrinsics) or the board file does not describe the print; noise and "
                 "accuracy are measured against the pose's plane and would hold that disagreement")
    if board.type == "charuco" and (unseen := corners_never_seen(ok, board, _colour_intrinsics(info))):
        never, in_view = unseen
        out.note("board-extent",
                 f"{len(never)} of the {in_view} board corners the board file puts in view, in rows or "
                 f"columns beyond those found, were found in no frame (corner ids {_id_list(never)}): the "
                 f"board file may describe more rows or columns than the print (squares_x "
                 f"{board.squares_x}, squares_y {board.squares_y}), and then the board's centre and area, "
                 "and every figure here, are wrong; else part of the board was covered or out of the light")
    if abs(f["accuracy_m"]) > BOARD_SCALE_TOLERANCE * f["distance_m"]:
        # the pose's distance scales with the board's printed size: a wrong square length moves the
        # reference plane by the same ratio, which the depth does not follow
        ratio = (f["distance_m"] + f["accuracy_m"]) / f["distance_m"]
        out.note("board-scale",
                 f"the board's size does not fit the depth: mean accuracy {f['accuracy_m'] * 1000:.0f} mm is "
                 f"{100 * abs(ratio - 1):.0f}% of the distance; the depth implies square_length_m "
                 f"{board.square_length_m * ratio:.4f} m where the board file says {board.square_length_m} m "
                 "(likely cause: a wrong square_length_m; else the depth units)")
    if example is not None:
        ex_pose = example[0].pose_depth if use_frame else pose
        assert ex_pose is not None
        out.example = _example(example, info, board, ex_pose)
    if kept is not None:
        out.samples = _samples(kept, info, pose, use_frame)
    return out


def _dqt_figures(ok: list[FrameResult], info: StreamInfo, pose: NDArray[np.float64], use_frame: bool,
                 temporal_pct: dict[str, float]) -> dict[str, float]:
    """The Depth Quality Tool's figures of the standpoint; the ground truth of each frame's Z
    accuracy is the reference plane (the one accuracy uses) along that frame's pivot ray."""
    out = {c: float("nan") for c in DQT_COLUMNS}
    for prefix, attr in (("dqt_", "dqt"), ("dqt_roi_", "dqt_roi")):
        frames = [(r, getattr(r, attr)) for r in ok if getattr(r, attr) is not None]
        if not frames:
            continue
        gts = []
        for r, d in frames:
            ref = r.pose_depth if use_frame and r.pose_depth is not None else pose
            n = ref[:3, 2]
            denom = float(n @ np.asarray(d.pivot_ray))
            gts.append(float(n @ ref[:3, 3]) / denom * 1000.0 if denom > 0 else float("nan"))
        out.update(standpoint_figures([d for _, d in frames], gts, temporal_pct.get(prefix, float("nan")),
                                      info.stereo.fx, info.baseline_m, prefix))
    return out


# the pose's frame-to-frame scatter against the Cramer-Rao prediction from the corners' noise: 0.9-1.9
# on the tests' camera-like colour images at 1.5-5.6 m, 0-60 deg (tests/test_checkerboard_outliers.py);
# noise alone exceeds 3 with 3 frames about once in 3000 (chi-square, 2 degrees of freedom, 3 figures)
POSE_SPREAD_RATIO = 3.0
DEPTH_POSE_TILT_DEG = 10.0  # real D435 standpoints: 1-1.7 deg, 5.3 with the camera moving 120 px
UNSEEN_SHARE = 0.1  # of the corners in view, never found in any frame: the board file's extent is suspect
UNSEEN_MIN = 4


def corners_never_seen(ok: list[FrameResult], board: Board,
                       intr: Intrinsics) -> tuple[list[int], int] | None:
    """ChArUco corners a frame's pose puts well inside the image (3 % from its border), in rows or
    columns beyond those any frame found, that no frame found; and how many are in view. None when
    few. Why: the detector finds the markers a board file with extra rows shares with the print, so
    the pose looks right while the board's centre and mask (reaching past the print onto the wall)
    are not: noise 2.6 -> 69 mm, no word."""
    frames = [r for r in ok if r.pose_color is not None and r.corner_ids is not None]
    if not frames:
        return None
    obj = board.corner_points()
    k, dist = intr.K, intr.opencv_distortion()
    mu, mv = 0.03 * intr.width, 0.03 * intr.height
    in_view = np.zeros(len(obj), bool)
    seen = np.zeros(len(obj), bool)
    for r in frames:
        pose = r.pose_color
        assert pose is not None and r.corner_ids is not None
        cam = obj @ pose[:3, :3].T + pose[:3, 3]
        uv, _ = cv2.projectPoints(obj, cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3], k, dist)
        u, v = uv.reshape(-1, 2).T
        inside = (u >= mu) & (u <= intr.width - 1 - mu) & (v >= mv) & (v <= intr.height - 1 - mv)
        in_view |= (cam[:, 2] > 0) & inside
        seen[r.corner_ids] = True
    if not seen.any():
        return None
    # only corners beyond the found part (rows or columns past those any frame found): extra rows
    # of a board file lie there; a corner missed inside the found part is the detector's, not the file's
    cols_n = board.inner_corners[0]
    col, row = np.arange(len(obj)) % cols_n, np.arange(len(obj)) // cols_n
    c_lo, c_hi = col[seen].min(), col[seen].max()
    r_lo, r_hi = row[seen].min(), row[seen].max()
    beyond = (col < c_lo) | (col > c_hi) | (row < r_lo) | (row > r_hi)
    never = np.flatnonzero(in_view & ~seen & beyond)
    n_view = int(in_view.sum())
    if len(never) < UNSEEN_MIN or len(never) < UNSEEN_SHARE * n_view:
        return None
    return [int(i) for i in never], n_view


def _id_list(ids: list[int], most: int = 12) -> str:
    return ", ".join(map(str, ids[:most])) + (f", ... ({len(ids)} in all)" if len(ids) > most else "")


def _colour_intrinsics(info: StreamInfo) -> Intrinsics:
    """The intrinsics the poses were estimated with (as FrameEvaluator picks them)."""
    return info.color_intrinsics or info.depth_intrinsics


def _angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Angle between two unit normals (deg), sign of either ignored."""
    return float(np.degrees(np.arccos(np.clip(abs(float(a @ b)), 0.0, 1.0))))


def _depth_normal(ok: list[FrameResult], centre: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Normal of one plane fitted to the board's depth pixels of all frames, in disparity space.

    A diagnostic of the depth, never the reference (the reference must not move with the depth
    errors it judges). Thousands of depth pixels fix the plane's tilt to a few hundredths of a
    degree, so a wedge in the depth shows against the pose's normal. Why not the SVD normal:
    stereo noise lies along the rays, not across
    the plane, so a total-least-squares fit tilts towards the rays on an inclined board (0.8 deg
    at 5 m / 60 deg for the D455). On a plane n.p = 1, 1/z = n.(rx, ry, 1) exactly, with the
    noise in 1/z alone (disparity), so ordinary least squares there is unbiased.
    """
    total = np.zeros((4, 4))
    for r in ok:
        a = r.moments.get("inverse_depth")
        if a is not None:
            total += a
    if total[0, 0] < 3:
        return None
    try:
        coef = np.linalg.solve(total[:3, :3], total[:3, 3])  # 1/z = c0 + c1 rx + c2 ry
    except np.linalg.LinAlgError:
        return None
    n = np.array([coef[1], coef[2], coef[0]])
    norm = float(np.linalg.norm(n))
    if not np.isfinite(norm) or norm == 0:
        return None
    n /= norm
    return n if float(n @ centre) > 0 else -n


def _example(item: tuple[FrameResult, FramePixels], info: StreamInfo, board: Board,
             pose: NDArray[np.float64]) -> ExampleFrame:
    """Per-pixel noise and accuracy residuals of one frame, as images over the board's box."""
    res, px = item
    rx, ry = ray_xy(info.depth_intrinsics, px.u, px.v)
    z = px.z_m.astype(np.float64)
    p = np.stack([z * rx, z * ry, z], axis=1)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2] if vt[2] @ c > 0 else -vt[2]
    noise = (p - c) @ n
    normal = pose[:3, 2]
    acc = (p - pose[:3, 3]) @ normal
    u0, v0 = int(px.u.min()), int(px.v.min())
    shape = (int(px.v.max()) - v0 + 1, int(px.u.max()) - u0 + 1)
    nm = np.full(shape, np.nan, dtype=np.float32)
    am = np.full(shape, np.nan, dtype=np.float32)
    nm[px.v - v0, px.u - u0] = noise
    am[px.v - v0, px.u - u0] = acc
    return ExampleFrame(res.index, nm, am, v0, u0)


def _samples(kept: list[tuple[FrameResult, FramePixels]], info: StreamInfo,
             pose: NDArray[np.float64], use_frame: bool = False) -> PixelSamples:
    """Per-pixel samples against the reference plane (averaged pose, or each frame's own)."""
    intr = info.depth_intrinsics
    if not kept:
        raise EvaluationError("no pixels to sample")
    u = np.concatenate([p.u for _, p in kept])
    v = np.concatenate([p.v for _, p in kept])
    z = np.concatenate([p.z_m for _, p in kept]).astype(np.float64)
    colour = np.concatenate([p.colour for _, p in kept])
    sizes = [p.u.size for _, p in kept]
    frame = np.repeat(np.array([r.index for r, _ in kept], dtype=np.int32), sizes)
    ts = np.repeat(np.array([r.timestamp_ns for r, _ in kept], dtype=np.int64), sizes)
    temp = np.repeat(np.array([r.temperature_c for r, _ in kept], dtype=np.float32), sizes)
    rx, ry = ray_xy(intr, u, v)
    if use_frame:
        poses = np.repeat(np.stack([r.pose_depth for r, _ in kept]), sizes, axis=0)  # type: ignore[misc]
        n, nt = poses[:, :3, 2], np.einsum("ij,ij->i", poses[:, :3, 2], poses[:, :3, 3])
    else:
        n, nt = pose[None, :3, 2], np.full(u.size, float(pose[:3, 2] @ pose[:3, 3]))
    dot = n[:, 0] * rx + n[:, 1] * ry + n[:, 2]
    z_ref = nt / dot
    ray_norm = np.sqrt(rx * rx + ry * ry + 1.0)
    error = (z - z_ref) * dot  # n.(z r) - n.t, with n away from the camera
    incl = np.degrees(np.arccos(np.clip(np.abs(dot) / ray_norm, 0.0, 1.0)))
    return PixelSamples(frame, u.astype(np.int32), v.astype(np.int32), z_ref.astype(np.float32),
                        z.astype(np.float32), error.astype(np.float32), incl.astype(np.float32),
                        colour == BLACK, colour == WHITE, ts, temp)
