"""Rigid-body maths shared by every stage: rotations, pose averaging, planes, inclination."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def rodrigues(rvec: NDArray[Any]) -> FloatArray:
    """Axis-angle vector (radians) to a rotation matrix."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


def rotation_to_axis_angle(r: NDArray[Any]) -> FloatArray:
    """Rotation matrix to axis-angle vector (radians)."""
    r = np.asarray(r, dtype=np.float64)
    cos = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    theta = float(np.arccos(cos))
    if theta < 1e-12:
        return np.zeros(3)
    if np.pi - theta < 1e-6:
        # near 180 degrees: axis from the symmetric part
        m = (r + np.eye(3)) / 2
        axis = np.sqrt(np.clip(np.diag(m), 0, None))
        i = int(np.argmax(axis))
        axis = m[:, i] / np.sqrt(m[i, i])
        return axis * theta
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * np.sin(theta))
    return w * theta


def rotation_angle_deg(r_a: NDArray[Any], r_b: NDArray[Any]) -> float:
    """Angle of the relative rotation between two rotation matrices, in degrees: atan2 of its sine
    (from the skew part) and cosine (from the trace). Why not arccos of the trace alone: near 0 it
    resolves only ~1e-6 deg (sqrt of the float64 epsilon), so equal rotations read 1.2e-6 deg on
    one CPU and 0 on another."""
    rel = np.asarray(r_a, dtype=np.float64).T @ np.asarray(r_b, dtype=np.float64)
    skew = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    return float(np.degrees(np.arctan2(0.5 * np.linalg.norm(skew), 0.5 * (np.trace(rel) - 1.0))))


def project_to_so3(m: NDArray[Any]) -> FloatArray:
    """Nearest rotation (Frobenius) to a 3x3 matrix."""
    u, _, vt = np.linalg.svd(np.asarray(m, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def average_rotations(rotations: Sequence[NDArray[Any]] | NDArray[Any], iterations: int = 20) -> FloatArray:
    """Karcher (geodesic L2) mean of rotations, started from the chordal mean.

    Averaging matrices element-wise leaves SO(3); this stays on it and is what the
    per-standpoint reference pose needs.
    """
    rs = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    mean = project_to_so3(rs.sum(axis=0))
    for _ in range(iterations):
        deltas = np.array([rotation_to_axis_angle(mean.T @ r) for r in rs])
        step = deltas.mean(axis=0)
        mean = mean @ rodrigues(step)
        if np.linalg.norm(step) < 1e-12:
            break
    return mean


def average_poses(poses: Sequence[NDArray[Any]] | NDArray[Any]) -> FloatArray:
    """Mean of 4x4 rigid poses: rotation by Karcher mean, translation arithmetic."""
    ps = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    out = np.eye(4)
    out[:3, :3] = average_rotations(ps[:, :3, :3])
    out[:3, 3] = ps[:, :3, 3].mean(axis=0)
    return out


def quaternion_to_matrix(q: NDArray[Any]) -> FloatArray:
    """Quaternion (x, y, z, w), the TUM and ROS order, to a rotation matrix."""
    x, y, z, w = (float(c) for c in np.asarray(q, dtype=np.float64) / np.linalg.norm(q))
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r: NDArray[Any]) -> FloatArray:
    """Rotation matrix to quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    return q if q[3] >= 0 else -q


def fit_plane(points: NDArray[Any]) -> tuple[FloatArray, FloatArray]:
    """Least-squares plane through Nx3 points: (centroid, unit normal).

    Uses the eigen-decomposition of the 3x3 covariance, which gives the same normal as the SVD
    of the centred points (the paper's method) at a third of the cost. The normal points
    towards the camera origin side (negative z for a surface in front of the camera).
    """
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    q = p - c
    cov = q.T @ q
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, 0]
    if float(np.dot(n, c)) > 0:
        n = -n
    return c, n


def inclination_deg(ray: NDArray[Any], normal: NDArray[Any]) -> FloatArray:
    """Angle between viewing rays and surface normals folded into [0, 90] degrees (DESIGN §2)."""
    r = np.asarray(ray, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    cos = np.abs(np.sum(r * n, axis=-1)) / (np.linalg.norm(r, axis=-1) * np.linalg.norm(n, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def look_at(eye: NDArray[Any], target: NDArray[Any],
            up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> FloatArray:
    """Camera-to-world pose (4x4) of an OpenCV camera (x right, y down, z forward) looking at target."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up_v = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up_v)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose
