"""Expanded uncertainties (U95, GUM style) of a standpoint's distance, inclination, noise and accuracy.

Why each source is here:
- random corner noise of the colour image moves every frame's pose; it averages over the frames of
  a still standpoint (Cramer-Rao from the corners' Jacobian, sigma from the residuals);
- a static corner error (the same in every frame: detector bias, print, lens model) does not
  average. The part of it no pose can absorb shows as the corners' mean residual over the frames,
  measured here; through the same Jacobian it tilts and shifts the reference pose;
- the frames' scatter of the depth figures (noise, accuracy) gives their Type A uncertainty;
- the reference pose's uncertainty moves the reference plane, hence accuracy;
- at inclinations near 0 the reported angle is folded (a magnitude): its interval comes from the
  2-D spread of the tilt (Rayleigh), so that it covers a head-on truth.

Every U95 is k * u with k = t(0.975, frames - 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import stdtrit

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics
from depthstation.core.geometry import rodrigues
from depthstation.evaluate.checkerboard.pose import pose_jacobian, weighted_information

F64 = NDArray[np.float64]
# The static corner error of the X-junction refinement on the simulator's exact-coverage colour:
# 0.008-0.015 px RMS at 1-5 m (docs/checkerboard-study.md, bench_checkerboard.py --corners). A
# static error at least this large is assumed (Type B) where the residuals show less: the part of
# a static pattern shaped like a change of pose never shows in the residuals it is measured from.
STATIC_FLOOR_PX = 0.01
# The noise estimator's own systematic error against the simulator's truth: within +-0.7 % over
# 1-5 m and 0-60 deg (benchmarks/bench_uncertainty.py); a rectangular +-0.7 % as Type B.
NOISE_TYPE_B = 0.007 / np.sqrt(3.0)
FOLD_SIGMAS = 4.0  # above this many tilt standard deviations the folded angle is plain Gaussian
RAYLEIGH_95 = float(np.sqrt(-2.0 * np.log(0.05)))  # 2.448: 95 % of 2-D unit Gaussian magnitudes


@dataclass(frozen=True)
class CornerErrors:
    """Per-coordinate corner errors (px): random (per frame) and static (the same every frame)."""

    random_px: float
    static_px: float
    corners: int
    frames: int


def corner_errors(corner_ids: list[NDArray[np.int64]], corners_px: list[NDArray[np.float32]],
                  poses: list[F64], board: Board, intr: Intrinsics) -> CornerErrors:
    """Random and static corner errors from every frame's residuals against its own pose.

    Random: the pooled scatter of each corner's residual around its mean over the frames. Static:
    the RMS of those means, less what the random part leaves in a mean of n frames, scaled by
    2N / (2N - 6) for the six pose parameters that absorb part of any pattern.
    """
    obj = board.corner_points()
    k, dist = intr.K, intr.opencv_distortion()
    per_corner: dict[int, list[F64]] = {}
    for ids, px, pose in zip(corner_ids, corners_px, poses, strict=True):
        rvec = cv2.Rodrigues(pose[:3, :3])[0]
        uv, _ = cv2.projectPoints(obj[ids], rvec, pose[:3, 3], k, dist)
        res = np.asarray(px, dtype=np.float64) - uv.reshape(-1, 2)
        for i, r in zip(ids.tolist(), res, strict=True):
            per_corner.setdefault(int(i), []).append(r)
    ss = dof = 0.0
    means, counts = [], []
    for rs in per_corner.values():
        a = np.asarray(rs)
        m = a.mean(axis=0)
        means.append(m)
        counts.append(len(a))
        ss += float(((a - m) ** 2).sum())
        dof += 2.0 * (len(a) - 1)
    n_frames = len(poses)
    random = float(np.sqrt(ss / dof)) if dof > 0 else float("nan")
    n_c = len(means)
    if n_c == 0:
        return CornerErrors(random, float("nan"), 0, n_frames)
    ms = float(np.mean(np.sum(np.asarray(means) ** 2, axis=1)) / 2.0)  # per coordinate
    leftover = random ** 2 * float(np.mean(1.0 / np.asarray(counts))) if np.isfinite(random) else 0.0
    absorbed = 2.0 * n_c / max(2.0 * n_c - 6.0, 1.0)
    static = float(np.sqrt(max(ms - leftover, 0.0) * absorbed))
    return CornerErrors(random, static, n_c, n_frames)


def corner_counts(corner_ids: list[NDArray[np.int64]], board: Board) -> F64:
    """How many of the frames saw each of the board's corners."""
    counts = np.zeros(len(board.corner_points()))
    for ids in corner_ids:
        np.add.at(counts, np.asarray(ids, dtype=np.int64), 1.0)
    return counts


def pose_covariance(board_to_color: F64, board: Board, intr: Intrinsics, sigma_px: float,
                    weights: F64 | None = None) -> F64:
    """6x6 covariance of a board pose from corner errors of sigma_px per coordinate (Cramer-Rao),
    in the parameters p = (rotation vector applied in the camera frame, translation). `weights`:
    each corner's weight (frames that saw it, or their share); None: every corner once."""
    jac = pose_jacobian(board_to_color, board.corner_points(), intr)
    try:
        return np.asarray(sigma_px ** 2 * np.linalg.inv(weighted_information(jac, weights)), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf)


def _perturbed(board_to_color: F64, p: F64) -> F64:
    out = board_to_color.copy()
    out[:3, :3] = rodrigues(p[:3]) @ board_to_color[:3, :3]
    out[:3, 3] = board_to_color[:3, 3] + p[3:]
    return out


def _geometry(board_to_depth: F64, board: Board, basis: tuple[F64, F64] | None = None
              ) -> tuple[float, F64, float, tuple[F64, F64]]:
    """(distance, tilt vector in the plane across the ray, offset of the plane along its normal at
    the board centre, the basis of the tilt vector) of a board-to-depth pose."""
    c = board_to_depth[:3, :3] @ board.center + board_to_depth[:3, 3]
    r = c / np.linalg.norm(c)
    n = board_to_depth[:3, 2]
    m = -n if float(n @ c) > 0 else n  # the normal towards the camera
    if basis is None:
        e1 = np.cross(r, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        basis = (e1, np.cross(r, e1))
    tilt = m - float(m @ -r) * -r  # |tilt| = sin(inclination)
    return float(c[2]), np.array([tilt @ basis[0], tilt @ basis[1]]), float(n @ c), basis


def propagate(board_to_color: F64, depth_to_color: F64, board: Board, cov: F64) -> dict[str, Any]:
    """First-order propagation of a colour-pose covariance to distance, tilt (2x2) and plane offset."""
    to_depth = np.linalg.inv(depth_to_color)
    d0, t0, o0, basis = _geometry(to_depth @ board_to_color, board)
    eps = 1e-6
    jac = np.zeros((4, 6))
    for i in range(6):
        p = np.zeros(6)
        p[i] = eps
        d, t, o, _ = _geometry(to_depth @ _perturbed(board_to_color, p), board, basis)
        jac[:, i] = (np.array([d, *t, o]) - np.array([d0, *t0, o0])) / eps
    c = jac @ cov @ jac.T
    return {"distance_var": float(c[0, 0]), "tilt_cov": c[1:3, 1:3], "offset_var": float(c[3, 3]),
            "tilt": t0, "basis": basis}


def pose_spread(boards_to_depth: list[F64], board: Board, basis: tuple[F64, F64]) -> dict[str, Any]:
    """The frames' own scatter of distance, tilt (2x2, in `basis`) and plane offset: the variances
    of one frame's pose. Why: the Cramer-Rao figures above hold the corners' noise only; whatever
    else moves the pose from frame to frame (a corner that comes and goes, a detector switching
    between solutions, vibration) shows here, and the mean of n frames varies by this / n."""
    geo = [_geometry(p, board, basis) for p in boards_to_depth]
    if len(geo) < 2:
        nan = float("nan")
        return {"distance_var": nan, "tilt_cov": np.full((2, 2), nan), "offset_var": nan}
    return {"distance_var": float(np.var([g[0] for g in geo], ddof=1)),
            "tilt_cov": np.atleast_2d(np.cov(np.array([g[1] for g in geo]).T, ddof=1)),
            "offset_var": float(np.var([g[2] for g in geo], ddof=1))}


def folded_angle(tilt: F64, tilt_cov: F64, k: float) -> tuple[float, float]:
    """(estimate, U95) in degrees of the inclination from the tilt vector (|tilt| = sin angle).

    Far from 0 the angle is Gaussian along the tilt's direction: U95 = k sigma_along. Near 0 the
    angle is a magnitude (folded): it reads high (E|t| = 1.25 sigma at a true 0) and k sigma_along
    would exclude a head-on truth. There |R - nu| <= |noise| for every true tilt nu, and the 2-D
    noise stays within 2.448 sigma (the Rayleigh 95 % quantile) with 95 % probability, so
    R +- 2.448 sigma covers the truth at any inclination: the estimate stays the folded value and
    U95 widens to that bound.
    """
    r = float(np.linalg.norm(tilt))
    ang = float(np.arcsin(min(r, 1.0)))
    if not np.all(np.isfinite(tilt_cov)):
        return float(np.degrees(ang)), float("nan")
    lam = max(float(np.max(np.linalg.eigvalsh(tilt_cov))), 0.0)
    sigma = float(np.sqrt(lam))
    if r > FOLD_SIGMAS * sigma:
        g = tilt / r
        s_along = float(np.sqrt(max(float(g @ tilt_cov @ g), 0.0)))
        return float(np.degrees(ang)), float(np.degrees(k * s_along / max(np.cos(ang), 1e-6)))
    return float(np.degrees(ang)), float(np.degrees(RAYLEIGH_95 * (k / 1.96) * sigma))


def coverage_factor(frames: int) -> float:
    return float(stdtrit(max(frames - 1, 1), 0.975))  # t quantile (scipy.stats costs 0.4 s to import)
