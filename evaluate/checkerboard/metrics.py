"""Plane statistics from moment matrices: noise (fit residual) and accuracy (reference-plane distance).

One frame's board points are reduced to a 4x4 moment matrix A = sum [1, p][1, p]^T (points
relative to an origin near the board, float64). The least-squares plane, its RMS residual and the
mean/RMS signed distance to any other plane all follow from A, so a frame is read once and the
reference plane (the standpoint's averaged pose, known only at the end) is applied afterwards.
The plane fit is the eigen-decomposition of the 3x3 covariance: the SVD normal at a third of the cost.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def moment_matrix(x: NDArray[np.floating], y: NDArray[np.floating],
                  z: NDArray[np.floating]) -> FloatArray:
    """4x4 moments sum [1, p][1, p]^T of points p = (x, y, z) (1-D arrays, already centred)."""
    m = np.empty((x.size, 4), dtype=np.float64)
    m[:, 0] = 1.0
    m[:, 1] = x
    m[:, 2] = y
    m[:, 3] = z
    return np.asarray(m.T @ m)


def fit_plane_moments(a: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares plane of the points behind `a`: (centroid, unit normal away from the camera, RMS).

    RMS of the orthogonal residuals = sqrt of the smallest covariance eigenvalue. The normal is
    turned to point away from the camera origin when the origin of `a` is the camera; callers with
    a shifted origin orient it themselves.
    """
    n = a[0, 0]
    if n < 3:
        return np.full(3, np.nan), np.full(3, np.nan), float("nan")
    mean = a[0, 1:] / n
    cov = a[1:, 1:] / n - np.outer(mean, mean)
    vals, vecs = np.linalg.eigh(cov)
    normal = vecs[:, 0]
    return mean, normal, float(np.sqrt(max(vals[0], 0.0)))


def plane_distance_stats(a: FloatArray, normal: FloatArray, offset: float) -> tuple[float, float]:
    """Mean and RMS of the signed distances n.p - offset of the points behind `a` (n unit)."""
    n = a[0, 0]
    if n < 1:
        return float("nan"), float("nan")
    w = np.concatenate([[-offset], normal])
    mean = float(w @ a[:, 0]) / n
    ms = float(w @ a @ w) / n
    return mean, float(np.sqrt(max(ms, 0.0)))


def svd_plane_rms(points: NDArray[np.floating]) -> float:
    """RMS orthogonal residual of an SVD plane fit (the paper's method; used to cross-check)."""
    p = np.asarray(points, dtype=np.float64)
    q = p - p.mean(axis=0)
    _, s, _ = np.linalg.svd(q, full_matrices=False)
    return float(s[-1] / np.sqrt(len(p)))


def shift_moments(a: FloatArray, delta: FloatArray) -> FloatArray:
    """Moments of the same points relative to an origin moved by -delta: p' = p + delta.

    Frames keep moments about their own board centre; shifting them to one common origin lets a
    standpoint fit one plane to the points of all its frames without re-reading a frame.
    """
    m = np.eye(4)
    m[1:, 0] = delta
    return np.asarray(m @ a @ m.T)
