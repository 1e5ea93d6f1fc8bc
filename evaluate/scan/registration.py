"""Registration of the trajectory frame to the reference, chosen by the user (`--register`):

- `none` (default): the trajectory as given (or the `--similarity` given), checked against the
  reference: a cloud of depth pixels in a trusted band (paper: 0.5-2.0 m) must lie on the mesh;
- `rigid`: ICP and a point-to-plane refinement on the mesh, rotation and translation only;
- `similarity`: the same with a scale (the paper's registration, s = 0.98288);
- `pass-points`: Umeyama with scale from surveyed pass points.

Why `none` by default: the study measures depth error, and a scale fitted on the depth pixels
swallows exactly the depth-scale error it exists to measure (a scale of 0.98288 absorbs a
+1.74 % depth error: 52 mm at 3 m). A scale, wherever it comes from, is therefore reported as the
depth-scale error it absorbs, with its 95 % band: from the fit's own residuals, blocks of
consecutive frames as clusters (a frame's noise is correlated over its window and its pose, so
frames, not points, vary independently), see `cluster_covariance`. The refinement picks its pixels
by the reference's depth and matches each along its ray, so that neither depends on the pixel's
own noise (`reference_band`, `refine_on_mesh`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import stdtrit

from depthstation.core.camera_model import ray_planes
from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.frames import FrameSource
from depthstation.core.geometry import rodrigues, rotation_angle_deg
from depthstation.core.lazy_open3d import open3d
from depthstation.core.text_files import read_text
from depthstation.evaluate.scan.trajectory import (
    LocalFrames,
    Trajectory,
    compose_similarity,
    decompose_similarity,
)

F64 = NDArray[np.float64]


REGISTER_MODES = ("none", "rigid", "similarity", "pass-points")
# Blocks of consecutive frames taken as the band's clusters (fewer with fewer frames; a fit from one
# frame has no band): a block holds what its frames share (a SLAM trajectory's drift over a few
# frames); t with Bell and McCaffrey's degrees of freedom (at most blocks - 1) keeps few blocks
# honest (benchmarks/bench_registration_coverage.py)
BAND_BLOCKS = 10


@dataclass
class Registration:
    """p_reference = s R p_trajectory + t, how it was found, and how well it fits.

    `matrix` maps the local frames (`local`: the shifts subtracted from far-away coordinates) the
    study works in; `to_dict` reports it between the frames as given.
    """

    matrix: F64
    method: str
    mean_c2c_m: float | None = None
    mean_c2m_m: float | None = None
    icp: dict[str, Any] = field(default_factory=dict)
    mode: str = "none"
    median_c2m_m: float | None = None
    scale_band95: tuple[float, float] | None = None  # of an estimated scale (None: given or 1)
    local: LocalFrames | None = None
    # the fit's covariance from its residuals, blocks of frames as clusters: every band comes from it
    step_covariance: StepCovariance | None = None

    @property
    def scale(self) -> float:
        return decompose_similarity(self.matrix)[0]

    @property
    def absorbed_depth_scale_error(self) -> float:
        """The relative depth-scale error the scale hides: depth (and a trajectory built on it)
        too long by (1 + e) is mapped onto the reference by s = 1 / (1 + e)."""
        return 1.0 / self.scale - 1.0

    def absorbed(self) -> dict[str, Any] | None:
        """What the registration's scale absorbs (None when it applies no scale)."""
        if abs(self.scale - 1.0) < 1e-12:
            return None
        band = None if self.scale_band95 is None else [1.0 / s - 1.0 for s in self.scale_band95[::-1]]
        return {"scale": self.scale, "depth_scale_error": self.absorbed_depth_scale_error,
                "depth_scale_error_band95": band,
                "meaning": "the registration's scale maps a trajectory (and the depth it was built on) too "
                           "long by this fraction onto the reference; with exact poses it would be depth "
                           "error moved into the poses, and the grid's errors would not be the camera's"}

    def caption(self) -> str:
        """One line for figure captions and the console."""
        a = self.absorbed()
        text = f"registration {self.mode}"
        if a is not None:
            band = a["depth_scale_error_band95"]
            text += (f", scale {self.scale:.5f} absorbs a depth-scale error of "
                     f"{100 * a['depth_scale_error']:+.3f}%"
                     + (f" (95%: {100 * band[0]:+.3f} to {100 * band[1]:+.3f}%)" if band else " (given)"))
        if self.median_c2m_m is not None:
            text += f"; median cloud-to-mesh {1000 * self.median_c2m_m:.1f} mm"
        return text

    @property
    def given_matrix(self) -> F64:
        """The similarity between the trajectory and reference frames as given (shifts undone)."""
        return self.local.to_given(self.matrix) if self.local is not None else self.matrix

    def bands(self) -> dict[str, Any] | None:
        """U95 of the fitted rotation (deg, about each axis of the reference frame) and translation
        (m, each axis), frames as given, and the scale's 95 % band, from the fit's cluster-robust
        covariance (`cluster_covariance`) and t with each quantity's degrees of freedom
        (`StepCovariance.dof`). None when no covariance was found (given, pass points, or fewer
        than 2 frames)."""
        sc = self.step_covariance
        if sc is None:
            return None
        jac = sc.jacobian(self.matrix, self.local)
        sd = np.sqrt(np.maximum(np.diag(jac @ sc.cov @ jac.T), 0.0))
        dof = np.array([sc.dof(row) for row in jac])
        k = np.asarray(stdtrit(dof, 0.975), dtype=np.float64)
        s = self.scale
        out: dict[str, Any] = {
            "method": f"cluster-robust (CR2) covariance of the fit, {sc.blocks} blocks of consecutive frames "
                      "as clusters, t with Bell and McCaffrey's degrees of freedom",
            "blocks": sc.blocks,
            "rotation_u95_deg": np.degrees(k[1:4] * sd[1:4]).tolist(),
            "translation_u95_m": (k[4:7] * sd[4:7]).tolist(),
            "dof": {"scale": dof[0], "rotation": dof[1:4].tolist(), "translation": dof[4:7].tolist()}}
        if sc.with_scale:
            out["scale_band95"] = [s - k[0] * sd[0], s + k[0] * sd[0]]
        return out

    def to_dict(self) -> dict[str, Any]:
        m = self.given_matrix
        s, r, t = decompose_similarity(m)
        out = {"mode": self.mode, "method": self.method, "scale": s, "rotation": r.tolist(),
               "translation_m": t.tolist(), "matrix": m.tolist(), "mean_c2c_m": self.mean_c2c_m,
               "mean_c2m_m": self.mean_c2m_m, "median_c2m_m": self.median_c2m_m,
               "absorbed": self.absorbed(), "band95": self.bands(), "icp": self.icp}
        if self.local is not None:
            out["local_shift"] = self.local.to_dict()
            out["local_matrix"] = self.matrix.tolist()
        return out


def read_similarity(path: Path) -> F64:
    """A 4x4 matrix as text (whitespace or commas); 3x4 accepted; positive scale required."""
    path = Path(path)
    try:
        text = read_text(path, "similarity matrix")
        m = np.loadtxt(io.StringIO(text), delimiter="," if "," in text else None, ndmin=2)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"not a 4x4 matrix ({exc})") from exc
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4) or not np.allclose(m[3], [0, 0, 0, 1]):
        raise InputError(path, f"expected a 4x4 similarity [sR t; 0 0 0 1], got shape {m.shape}")
    if not np.isfinite(m).all():  # every pose would be NaN: no frame could be evaluated, for no named reason
        row, col = (int(x) for x in np.argwhere(~np.isfinite(m))[0])
        raise InputError(path, f"row {row + 1}, column {col + 1} is {m[row, col]}: the matrix must be finite")
    try:
        s, r, _ = decompose_similarity(m)
    except ValueError as exc:
        raise InputError(path, str(exc)) from exc
    if not np.allclose(m[:3, :3], s * r, atol=1e-6 * s):
        raise InputError(path, "upper-left 3x3 is not a scaled rotation")
    return m


def read_pass_points(path: Path) -> tuple[F64, F64]:
    """CSV rows `x y z x_ref y_ref z_ref` (trajectory frame, reference frame); header optional."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "pass-point file not found")
    src, dst = [], []
    with io.StringIO(read_text(path, "pass-point CSV"), newline="") as fh:
        for lineno, row in enumerate(csv.reader(fh), 1):
            vals = [c.strip() for c in row if c.strip()]
            if not vals or vals[0].startswith("#"):
                continue
            try:
                nums = [float(v) for v in vals]
            except ValueError:
                if lineno == 1:
                    continue  # header
                raise InputError(path, f"line {lineno}: not numbers: {row}") from None
            if len(nums) == 7:  # leading point id
                nums = nums[1:]
            if len(nums) != 6:
                raise InputError(path, f"line {lineno}: expected 6 coordinates, got {len(nums)}")
            src.append(nums[:3])
            dst.append(nums[3:])
    if len(src) < 3:
        raise InputError(path, f"need at least 3 pass points, got {len(src)}")
    return np.asarray(src), np.asarray(dst)


def umeyama(src: F64, dst: F64, with_scale: bool = True) -> F64:
    """Least-squares similarity dst ~ s R src + t (Umeyama 1991) as a 4x4 matrix."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / src.shape[0]
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    r = u @ sign @ vt
    var_s = (a**2).sum() / src.shape[0]
    if var_s <= 0:
        raise EvaluationError("pass points are all the same point")
    s = float(np.trace(np.diag(d) @ sign) / var_s) if with_scale else 1.0
    return compose_similarity(s, r, mu_d - s * r @ mu_s)


class NoStart(EvaluationError):
    """The trajectory lies too far from the reference for the registration's refinement to start:
    the input's frame, not a failure of the station (exit 2, with what gives a start)."""


class NoPosedFrame(EvaluationError):
    """No frame of the sequence has a pose within the tolerance (`nearest_s`: the smallest gap
    between a frame and a pose): the trajectory's fault, said by the caller naming its file."""

    def __init__(self, tolerance_s: float, nearest_s: float) -> None:
        super().__init__(f"no frame has a pose within {tolerance_s:g} s (the nearest pose is "
                         f"{1000 * nearest_s:.1f} ms from its frame; --pose-tolerance-s)")
        self.nearest_s = nearest_s


@dataclass
class BandFrame:
    """One registered frame's depth pixels: posed into the trajectory frame, with the camera's
    centre there and each pixel's measured depth (what the reference-depth selection needs)."""

    points: F64
    centre: F64
    z: F64

    def within(self, band_m: tuple[float, float]) -> F64:
        """The points whose measured depth lies in the band."""
        return self.points[(self.z >= band_m[0]) & (self.z <= band_m[1])]


# The measured depths collected beyond the band on either side, so that the pixels whose reference
# depth lies in the band are all there whatever their noise (at 2 m the D455's noise is 0.5-1.3 %
# of the depth at 640-256 px wide)
BAND_MARGIN = 0.25
# Pixels the mesh refinement fits at most (every k-th of each frame beyond): each step casts a ray
# through every one
MAX_FIT_POINTS = 200_000
# A refinement step below this (rad, m, relative scale) is the float32 surface query's own noise
# (5e-8 at a few metres): the fit has converged
RESOLVED_STEP = 2e-7


def band_frames(source: FrameSource, trajectory: Trajectory, *,
                band_m: tuple[float, float] = (0.5, 2.0), tolerance_s: float = 0.01, every: int = 10,
                stride: int = 4, max_frames: int | None = None) -> list[BandFrame]:
    """Per frame, its depth pixels within the band widened by `BAND_MARGIN`, back-projected and
    posed into the trajectory frame.

    Every `every`-th frame and every `stride`-th pixel: registration needs coverage, not density.
    """
    info = source.info
    intr = info.depth_intrinsics
    xs, ys = ray_planes(intr)   # through the lens, when the stream has one
    x = np.ascontiguousarray(xs[::stride, ::stride]).ravel()
    y = np.ascontiguousarray(ys[::stride, ::stride]).ravel()
    lo, hi = band_m[0] / (1.0 + BAND_MARGIN), band_m[1] * (1.0 + BAND_MARGIN)
    parts = []
    posed = 0
    nearest = np.inf
    for pos, fs in enumerate(source.frames()):  # by position: device frame numbers have gaps
        if pos % every or fs.depth is None:
            continue
        pose = trajectory.match(fs.timestamp_ns * 1e-9, tolerance_s)
        if pose is None:
            if len(trajectory):
                nearest = min(nearest, trajectory.gap_s(fs.timestamp_ns * 1e-9))
            continue
        posed += 1
        z = fs.depth[::stride, ::stride].astype(np.float64).ravel() * info.depth_units_m
        ok = (z >= lo) & (z <= hi)
        p = np.stack([x[ok] * z[ok], y[ok] * z[ok], z[ok]], axis=-1)
        parts.append(BandFrame(p @ pose[:3, :3].T + pose[:3, 3], np.array(pose[:3, 3], dtype=np.float64),
                               z[ok]))
        if max_frames is not None and len(parts) >= max_frames:
            break
    if posed == 0 and np.isfinite(nearest) and every > 1:  # the frames between the sampled ones
        for pos, fs in enumerate(source.frames()):
            if pos % every and trajectory.match(fs.timestamp_ns * 1e-9, tolerance_s) is not None:
                return []  # poses, but none on a sampled frame: nothing to fit, the study goes on
            if pos % every:
                nearest = min(nearest, trajectory.gap_s(fs.timestamp_ns * 1e-9))
    if posed == 0 and np.isfinite(nearest):
        raise NoPosedFrame(tolerance_s, float(nearest))
    return [f for f in parts if len(f.z)]


def thin_frames(frames: list[BandFrame], max_points: int) -> list[BandFrame]:
    """Every k-th pixel of each frame, k the least that keeps the total within `max_points`."""
    total = sum(len(f.z) for f in frames)
    k = -(-total // max_points)
    if k <= 1:
        return frames
    return [BandFrame(f.points[::k], f.centre, f.z[::k]) for f in frames]


def depth_band_frames(source: FrameSource, trajectory: Trajectory, *,
                      band_m: tuple[float, float] = (0.5, 2.0), tolerance_s: float = 0.01, every: int = 10,
                      stride: int = 4, max_frames: int | None = None) -> list[F64]:
    """Per frame, its depth pixels whose measured depth lies within the band, posed into the
    trajectory frame (`band_frames`, cut to the band)."""
    frames = band_frames(source, trajectory, band_m=band_m, tolerance_s=tolerance_s, every=every,
                         stride=stride, max_frames=max_frames)
    return [p for p in (f.within(band_m) for f in frames) if len(p)]


def reference_band(frames: list[BandFrame], scene: Any, m: F64,
                   band_m: tuple[float, float]) -> list[BandFrame]:
    """Per frame, its pixels whose *reference* depth lies in the band, the reference cast along
    each pixel's ray with the trajectory moved by `m` (frames left with no pixel dropped).

    Why not the measured depth: a band cut on the noisy depth keeps, at its far edge, the pixels
    whose noise made them short and drops those it made long, so the floor seen at 2 m came out
    too high (+1.4 mm along the vertical on the simulated D455 at 256x144); the reference's depth
    does not depend on the pixel's noise.
    """
    out = []
    s = decompose_similarity(m)[0]
    for f in frames:
        c = m[:3, :3] @ f.centre + m[:3, 3]
        hit, _, rng = _cast(scene, np.broadcast_to(c, f.points.shape), f.points @ m[:3, :3].T + m[:3, 3])
        z_ref = hit * f.z / rng  # the depth the camera would measure there, in its own units
        keep = np.isfinite(z_ref) & (z_ref >= band_m[0] * s) & (z_ref <= band_m[1] * s)
        if keep.any():
            out.append(BandFrame(f.points[keep], f.centre, f.z[keep]))
    return out


def _cast(scene: Any, c: F64, p: F64) -> tuple[F64, F64, F64]:
    """Along the rays from the camera centres `c` through the points `p` (reference frame): the
    distance to the reference surface (inf where none), its unit normal, and the points' range."""
    o3d = open3d()
    v = p - c
    rng = np.linalg.norm(v, axis=1)
    rays = np.concatenate([c, v / np.maximum(rng, 1e-12)[:, None]], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    n = ans["primitive_normals"].numpy().astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return ans["t_hit"].numpy().astype(np.float64), n, rng


def voxel_cloud(parts: list[F64], voxel_m: float = 0.01) -> F64:
    o3d = open3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(parts)))
    if voxel_m > 0:
        pc = pc.voxel_down_sample(voxel_m)
    return np.asarray(pc.points)


def depth_band_cloud(source: FrameSource, trajectory: Trajectory, *, band_m: tuple[float, float] = (0.5, 2.0),
                     tolerance_s: float = 0.01, every: int = 10, stride: int = 4,
                     max_frames: int | None = None, voxel_m: float = 0.01) -> F64:
    """The band's depth pixels of all frames in one cloud, thinned to `voxel_m`."""
    return voxel_cloud(depth_band_frames(source, trajectory, band_m=band_m, tolerance_s=tolerance_s,
                                         every=every, stride=stride, max_frames=max_frames), voxel_m)


def icp_with_scale(points: F64, target: Any, init: F64, *,
                   distances_m: tuple[float, ...] = (0.2, 0.08, 0.03, 0.015),
                   max_iterations: int = 60, with_scale: bool = True) -> tuple[F64, dict[str, Any]]:
    """Point-to-point ICP estimating a similarity (or, without scale, a rigid motion), coarse to
    fine correspondence distances."""
    o3d = open3d()

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    m = np.asarray(init, dtype=np.float64)
    res = None
    for dist in distances_m:
        res = reg.registration_icp(
            src, target, dist, m, reg.TransformationEstimationPointToPoint(with_scaling=with_scale),
            reg.ICPConvergenceCriteria(relative_fitness=1e-10, relative_rmse=1e-10,
                                       max_iteration=max_iterations))
        m = np.asarray(res.transformation).copy()
    assert res is not None
    s0, r0, t0 = decompose_similarity(init)
    s1, r1, t1 = decompose_similarity(m)
    return m, {"fitness": float(res.fitness), "inlier_rmse_m": float(res.inlier_rmse),
               "final_distance_m": distances_m[-1], "points": len(points),
               "scale_change": s1 / s0, "rotation_change_deg": rotation_angle_deg(r0, r1),
               "translation_change_m": float(np.linalg.norm(t1 - t0))}


def refine_on_mesh(points: F64, mesh: Any, init: F64, *, centres: F64 | None = None,
                   max_distance_m: float = 0.05, iterations: int = 50, tol: float = 1e-8,
                   with_scale: bool = True, scene: Any | None = None) -> tuple[F64, dict[str, Any]]:
    """Point-to-plane ICP against the exact surface (Gauss-Newton on a similarity, or without
    scale on a rigid motion), each step halved until the sum of squared surface distances (each
    capped at `max_distance_m`) falls.

    Why against the mesh: point-to-point ICP against sampled reference points converges to where
    the samples happen to lie (cm spacing). The residual is the distance along the surface's
    normal; the Jacobian is taken on the surface, not at the noisy measured point, so depth noise
    does not shrink the scale (errors in variables: ~0.1 % with Umeyama at D455 noise levels).
    With `centres` (each point's camera centre, trajectory frame) a point is matched where its
    pixel's ray meets the surface: a point that depends on the pose only. The closest surface
    point (without centres) moves with the point's own noise (along the floor, round the table),
    and the fit came out +0.13 % in scale on the simulated D455 at 256x144 (white noise only;
    noise-free depth: -0.006 +- 0.013 %). Why the halving: where few surfaces hold a motion (a
    round table's facets and a floor for a turn about the vertical), the full step jumped back and
    forth (0.3 mm, 0.003 deg) and the fit ended wherever its last step left it. `scene`: the
    mesh's raycasting scene when the caller refits many times. Matched along the rays, a step
    that does not shrink to half the last one is halved from then on: a pixel whose ray switches
    between two surfaces (a table's edge and the floor beyond) held half the simulated walks in a
    two-step cycle (0.5 mm, 0.03 deg), and the fit ended at whichever end the 50th step reached.
    """
    if scene is None:
        scene = mesh_scene(mesh)
    pts = np.asarray(points, dtype=np.float64)
    cen = None if centres is None else np.asarray(centres, dtype=np.float64)
    m = np.asarray(init, dtype=np.float64).copy()
    q, n, d, ok, cost = _surface_fit(scene, pts, cen, m, max_distance_m)
    used = 0
    it = 0
    damping, last = 1.0, np.inf
    for it in range(iterations):
        used = int(ok.sum())
        if used < 10:
            raise NoStart(f"fewer than 10 of its depth points lie within {max_distance_m:g} m of the "
                          "reference surface, so the fit has nothing to start from")
        qc = q[ok] - q[ok].mean(0)  # centred: better conditioned scale/translation
        cols = [np.cross(qc, n[ok]), n[ok]] + ([(n[ok] * qc).sum(1)] if with_scale else [])
        a = np.column_stack(cols)
        # normal equations: a has 6-7 well scaled columns (centred), and numpy's lstsq on a tall
        # matrix cost 20-40 ms a step on a busy machine (threads), the 7 x 7 one 0.2 ms
        x = np.linalg.lstsq(a.T @ a, -(a.T @ d[ok]), rcond=None)[0]  # a plane alone: minimum norm
        size = float(np.abs(x).max())
        if cen is not None and it >= 2 and size > 0.5 * last:
            damping /= 2.0  # not shrinking: a pixel's ray switching surfaces holds it in a cycle
        last = size
        x = damping * x
        c = q[ok].mean(0)
        for _ in range(8 if cen is None else 1):
            omega, tau, eps = x[:3], x[3:6], float(x[6]) if with_scale else 0.0
            step = np.eye(4)
            step[:3, :3] = (1.0 + eps) * rodrigues(omega)
            step[:3, 3] = c - step[:3, :3] @ c + tau
            trial = _surface_fit(scene, pts, cen, step @ m, max_distance_m)
            if cen is not None or trial[4] <= cost:
                break
            x = x / 2.0
        else:
            break  # no step lowers the sum: converged as far as the float32 surface query resolves
        m = step @ m
        q, n, d, ok, cost = trial
        if np.abs(x).max() < max(tol, RESOLVED_STEP):
            break
    return m, {"mesh_refine_iterations": it + 1, "mesh_refine_points": used,
               "mesh_refine_match": "closest surface point" if cen is None else "along the pixel's ray"}


def _surface_fit(scene: Any, pts: F64, centres: F64 | None, m: F64,
                 max_distance_m: float) -> tuple[F64, F64, F64, NDArray[np.bool_], float]:
    """The moved points' surface matches (closest, or along their rays from `centres`), unit
    normals there, the signed distances along them, the points within `max_distance_m`, and the
    sum of squared distances each capped there (a ray that misses counts as capped)."""
    p = pts @ m[:3, :3].T + m[:3, 3]
    if centres is None:
        o3d = open3d()
        ans = scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        q = ans["points"].numpy().astype(np.float64)
        n = ans["primitive_normals"].numpy().astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        d = ((p - q) * n).sum(1)
        dist2 = ((p - q) ** 2).sum(1)
    else:
        c = centres @ m[:3, :3].T + m[:3, 3]
        hit, n, rng = _cast(scene, c, p)
        q = c + (p - c) * (hit / np.maximum(rng, 1e-12))[:, None]
        with np.errstate(invalid="ignore"):
            d = np.where(np.isfinite(hit), ((p - q) * n).sum(1), np.inf)
        q = np.where(np.isfinite(q), q, p)
        dist2 = d * d
    ok = dist2 < max_distance_m**2
    return q, n, d, ok, float(np.minimum(dist2, max_distance_m**2).sum())


def mesh_scene(mesh: Any) -> Any:
    """Open3D's raycasting scene of a legacy triangle mesh (closest points, distances)."""
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def fit_distances(points: F64, matrix: F64, target: Any,
                  mesh: Any | None) -> tuple[float, float | None, float | None]:
    """Mean distance of the registered cloud to the reference points (C2C, as CloudCompare) and,
    with a mesh, to the surface (C2M, free of the sampling spacing of the points)."""
    o3d = open3d()

    p = np.asarray(points) @ matrix[:3, :3].T + matrix[:3, 3]
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    c2c = float(np.mean(np.asarray(src.compute_point_cloud_distance(target))))
    c2m = c2m_median = None
    if mesh is not None:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        dist = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
        c2m, c2m_median = float(np.mean(dist)), float(np.median(dist))
    return c2c, c2m, c2m_median


def initial_similarity(similarity: F64 | None,
                       pass_points: tuple[F64, F64] | None) -> tuple[F64, str]:
    """The starting similarity (trajectory -> reference) and its name: given, pass points, identity."""
    if similarity is not None:
        return np.asarray(similarity, dtype=np.float64), "given"
    if pass_points is not None:
        return umeyama(*pass_points), "pass_points"
    return np.eye(4), "identity"


def register(source: FrameSource, trajectory: Trajectory, mesh: Any, target: Any, *, mode: str = "none",
             similarity: F64 | None = None, pass_points: tuple[F64, F64] | None = None,
             band_m: tuple[float, float] = (0.5, 2.0), tolerance_s: float = 0.01,
             every: int = 10, local: LocalFrames | None = None) -> Registration:
    """The registration `mode` asks for (see the module's docstring), from the initial transform
    (given similarity, pass points or identity), with its fit and what its scale absorbs.

    `local`: the trajectory and mesh are in local frames (far-away coordinates shifted); the
    similarity and pass points are in the frames as given and are moved along.
    """
    if mode not in REGISTER_MODES:
        raise InputError(None, f"--register must be one of {', '.join(REGISTER_MODES)}, not '{mode}'")
    if mode == "pass-points" and pass_points is None:
        raise InputError(None, "--register pass-points needs --pass-points FILE")
    init, method = initial_similarity(similarity, pass_points)
    scale_band = (_jackknife_band(*pass_points) if mode == "pass-points" and pass_points is not None
                  and similarity is None else None)
    if local is not None:
        init = local.to_local(init)
    frames = band_frames(source, trajectory, band_m=band_m, tolerance_s=tolerance_s, every=every)
    parts = [p for p in (f.within(band_m) for f in frames) if len(p)]
    info: dict[str, Any] = {"band_m": list(band_m), "frames": len(parts)}
    m = init
    if not parts:  # no posed depth in the band: nothing to fit, nor to measure the fit by
        if mode in ("rigid", "similarity"):
            raise EvaluationError(f"--register {mode}: no posed frame has depth in {band_m[0]:g}-"
                                  f"{band_m[1]:g} m to fit (--icp-band-m)")
        info["note"] = f"no posed depth in {band_m[0]:g}-{band_m[1]:g} m: cloud-to-mesh not measured"
        return Registration(m, method, None, None, info, mode, None, scale_band95=scale_band, local=local)
    points = voxel_cloud(parts)
    step_cov = None
    if mode in ("rigid", "similarity"):
        scaled = mode == "similarity"
        m, icp_info = icp_with_scale(points, target, init, with_scale=scaled)
        info.update(icp_info)
        method += "+icp"
        if mesh is not None:
            scene = mesh_scene(mesh)
            fit_frames = thin_frames(frames, MAX_FIT_POINTS)
            for _ in range(2):  # the band by the reference depth, cast from the ICP fit, then the refined
                chosen = reference_band(fit_frames, scene, m, band_m)
                if not chosen:
                    raise NoStart(f"no depth pixel's ray meets the reference within {band_m[0]:g}-"
                                  f"{band_m[1]:g} m, so the fit has nothing to start from")
                pts, cen = _fit_points(chosen)
                m, refine_info = refine_on_mesh(pts, mesh, m, centres=cen, with_scale=scaled, scene=scene)
            info.update(refine_info)
            info["refine_band"] = "reference depth along each pixel's ray"
            info["refine_frames"] = len(chosen)
            method += "+mesh"
            step_cov = cluster_covariance(chosen, scene, m, scaled)
    c2c, c2m, c2m_median = fit_distances(points, m, target, mesh)
    reg = Registration(m, method, c2c, c2m, info, mode, c2m_median, scale_band95=scale_band, local=local,
                       step_covariance=step_cov)
    bands = reg.bands()
    if bands is not None and "scale_band95" in bands:
        reg.scale_band95 = (float(bands["scale_band95"][0]), float(bands["scale_band95"][1]))
    return reg


def _fit_points(parts: Sequence[BandFrame | F64]) -> tuple[F64, F64 | None]:
    """What the refinement fits: frames' pixels with their camera centres (matched along their
    rays), or bare point sets (voxel-thinned, matched to the closest surface point)."""
    if parts and isinstance(parts[0], BandFrame):
        frames = [f for f in parts if isinstance(f, BandFrame)]
        return (np.concatenate([f.points for f in frames]),
                np.concatenate([np.broadcast_to(f.centre, f.points.shape) for f in frames]))
    return voxel_cloud([p for p in parts if isinstance(p, np.ndarray)]), None


@dataclass
class StepCovariance:
    """Covariance of a refinement step about the converged fit: rotation vector (rad), translation
    (m) and, with scale, the relative scale change, the step taken about `centre` (local frame), as
    `refine_on_mesh` parametrises it; `blocks` clusters gave it."""

    cov: F64
    centre: F64
    blocks: int
    with_scale: bool
    bread: F64 | None = None  # (A'A)^-1 of the step's Jacobian A
    # per block: T = W' S V' (A_b = U S V', W the eigenvectors of its leverage) and 1 / sqrt(1 - eigenvalues)
    leverage: list[tuple[F64, F64]] = field(default_factory=list)

    def dof(self, c: F64) -> float:
        """Bell and McCaffrey's degrees of freedom of the variance of c' step (Satterthwaite, under
        independent equal errors): blocks - 1 when the blocks' leverages are alike, fewer when a few
        blocks alone hold c (a side of the room seen by one block of frames)."""
        if self.bread is None or not self.leverage:
            return float(self.blocks - 1)
        norms, vs = [], []
        for t, gain in self.leverage:
            f = gain * (t @ (self.bread @ c))
            norms.append(float(f @ f))
            vs.append(t.T @ f)
        v = np.array(vs)
        gtg = np.diag(norms) - v @ self.bread @ v.T
        tr = float(np.trace(gtg))
        ff = float(np.sum(gtg * gtg))
        return float(np.clip(tr * tr / ff, 1.0, self.blocks - 1)) if ff > 0 else float(self.blocks - 1)

    def jacobian(self, m: F64, local: LocalFrames | None) -> F64:
        """d(scale, rotation vector about the reference axes, translation as given) / d(step)."""
        _, r0, _ = decompose_similarity(m)

        def reading(x: F64) -> F64:
            step = np.eye(4)
            step[:3, :3] = (1.0 + (x[6] if self.with_scale else 0.0)) * rodrigues(x[:3])
            step[:3, 3] = self.centre - step[:3, :3] @ self.centre + x[3:6]
            mm = step @ m
            g = local.to_given(mm) if local is not None else mm
            s, r, t = decompose_similarity(g)
            return np.concatenate([[s], _rotvec(r @ r0.T), t])

        k = self.cov.shape[0]
        h = 1e-6
        cols = []
        for j in range(k):
            e = np.zeros(7)
            e[j] = h
            cols.append((reading(e) - reading(-e)) / (2 * h))
        return np.column_stack(cols)


def cluster_covariance(frames: list[BandFrame], scene: Any, m: F64, with_scale: bool, *,
                       max_distance_m: float = 0.05, blocks: int = BAND_BLOCKS) -> StepCovariance | None:
    """The fit's covariance from its own residuals, blocks of consecutive frames as clusters
    (cluster-robust sandwich with Bell and McCaffrey's CR2 leverage correction).

    Why: a frame's pixels share its errors (the matching window's noise, its pose), so pixels are
    not independent but blocks of frames are; the sandwich takes the residuals' correlation
    within a block as it is. CR2 divides out each block's leverage: without it a block that alone
    holds a direction (one side of the table) shows a too small residual there. None with fewer
    than 2 blocks."""
    g = min(len(frames), blocks)
    if g < 2:
        return None
    pts, cen = _fit_points(frames)
    assert cen is not None
    group = np.concatenate([np.full(len(frames[i].z), b) for b, idx in
                            enumerate(np.array_split(np.arange(len(frames)), g)) for i in idx])
    q, n, d, ok, _ = _surface_fit(scene, pts, cen, m, max_distance_m)
    centre = q[ok].mean(0)
    qc = q - centre
    a = np.column_stack([np.cross(qc, n), n] + ([(n * qc).sum(1)] if with_scale else []))
    bread = np.linalg.pinv(a[ok].T @ a[ok])
    meat = np.zeros_like(bread)
    leverage: list[tuple[F64, F64]] = []
    for b in range(g):
        rows = ok & (group == b)
        if not rows.any():
            continue
        ab, db = a[rows], d[rows]
        u, sv, vt = np.linalg.svd(ab, full_matrices=False)
        kk = (sv[:, None] * vt) @ bread @ (vt.T * sv)
        lam, w = np.linalg.eigh((kk + kk.T) / 2)
        uw = u @ w
        gain = 1.0 / np.sqrt(1.0 - np.clip(lam, 0.0, 0.99))
        dt = db + uw @ ((gain - 1.0) * (uw.T @ db))
        score = ab.T @ dt
        meat += np.outer(score, score)
        leverage.append((w.T @ (sv[:, None] * vt), gain))
    return StepCovariance(bread @ meat @ bread, centre, g, with_scale, bread, leverage)


def _rotvec(r: F64) -> F64:
    """Rotation vector (rad) of a rotation matrix near the identity."""
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    sin = float(np.linalg.norm(w))
    if sin < 1e-15:
        return np.zeros(3)
    angle = float(np.arctan2(sin, (np.trace(r) - 1.0) / 2.0))
    return np.asarray(w / sin * angle, dtype=np.float64)


def _jackknife_band(src: F64, dst: F64) -> tuple[float, float] | None:
    """95 % band of the Umeyama scale from pass points (leave-one-out jackknife)."""
    n = len(src)
    if n < 4:
        return None
    s = decompose_similarity(umeyama(src, dst))[0]
    loo = np.array([decompose_similarity(umeyama(np.delete(src, i, 0), np.delete(dst, i, 0)))[0]
                    for i in range(n)])
    se = float(np.sqrt((n - 1) / n * np.sum((loo - loo.mean()) ** 2)))
    half = float(stdtrit(n - 1, 0.975)) * se
    return s - half, s + half
