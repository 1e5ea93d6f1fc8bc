"""Registration of the trajectory frame to the reference, chosen by the user (`--register`):

- `none` (default): the trajectory as given (or the `--similarity` given), checked against the
  reference: a cloud of depth pixels in a trusted band (paper: 0.5-2.0 m) must lie on the mesh;
- `rigid`: ICP and a point-to-plane refinement on the mesh, rotation and translation only;
- `similarity`: the same with a scale (the paper's registration, s = 0.98288);
- `pass-points`: Umeyama with scale from surveyed pass points.

Why `none` by default: the study measures depth error, and a scale fitted on the depth pixels
swallows exactly the depth-scale error it exists to measure (a scale of 0.98288 absorbs a
+1.74 % depth error: 52 mm at 3 m). A scale, wherever it comes from, is therefore reported as the
depth-scale error it absorbs, with its 95 % band from a block jackknife over the frames (each block
of consecutive frames left out in turn and the fit redone): frames, not points, are what vary
independently (a frame's noise is correlated over its window and its pose), so a band from point
subsets was too narrow (+0.061 to +0.099 % round a truth of 0).
"""

from __future__ import annotations

import csv
import io
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
# Blocks of consecutive frames the band's jackknife leaves out in turn (fewer with fewer frames; a
# fit from one frame has no band). More blocks cost more refits; ten gave coverage within the
# benchmark's resolution (benchmarks/bench_registration_coverage.py).
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
    # the fits with each block of frames left out (local frames), from which every band comes
    replicates: list[F64] | None = None

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
        (m, each axis), frames as given, and the scale's 95 % band: block jackknife over the frames
        (`jackknife_u95`). None when no fit was redone without a block (given, pass points, or
        too few frames)."""
        if not self.replicates:
            return None
        given = [self.local.to_given(r) if self.local is not None else r for r in self.replicates]
        _, r0, _ = decompose_similarity(self.given_matrix)
        parts = [decompose_similarity(g) for g in given]
        rot = np.array([np.degrees(_rotvec(r @ r0.T)) for _, r, _ in parts])
        out: dict[str, Any] = {
            "method": f"block jackknife over the frames ({len(given)} blocks of consecutive frames)",
            "blocks": len(given),
            "rotation_u95_deg": jackknife_u95(rot).tolist(),
            "translation_u95_m": jackknife_u95(np.array([t for _, _, t in parts])).tolist()}
        if self.scale_band95 is not None:
            out["scale_band95"] = list(self.scale_band95)
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


def depth_band_frames(source: FrameSource, trajectory: Trajectory, *,
                      band_m: tuple[float, float] = (0.5, 2.0), tolerance_s: float = 0.01, every: int = 10,
                      stride: int = 4,
                      max_frames: int | None = None) -> list[F64]:
    """Per frame, its depth pixels within the band, back-projected and posed into the trajectory frame.

    Every `every`-th frame and every `stride`-th pixel: registration needs coverage, not density.
    """
    info = source.info
    intr = info.depth_intrinsics
    xs, ys = ray_planes(intr)   # through the lens, when the stream has one
    x = np.ascontiguousarray(xs[::stride, ::stride]).ravel()
    y = np.ascontiguousarray(ys[::stride, ::stride]).ravel()
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
        ok = (z >= band_m[0]) & (z <= band_m[1])
        p = np.stack([x[ok] * z[ok], y[ok] * z[ok], z[ok]], axis=-1)
        parts.append(p @ pose[:3, :3].T + pose[:3, 3])
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
    return [p for p in parts if len(p)]


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


def refine_on_mesh(points: F64, mesh: Any, init: F64, *, max_distance_m: float = 0.05,
                   iterations: int = 50, tol: float = 1e-8, with_scale: bool = True,
                   scene: Any | None = None) -> tuple[F64, dict[str, Any]]:
    """Point-to-plane ICP against the exact surface (Gauss-Newton on a similarity, or without
    scale on a rigid motion).

    Why: point-to-point ICP against sampled reference points converges to where the samples
    happen to lie (cm spacing). Against the mesh, residuals are the distances along the hit
    triangle's normal; the Jacobian is taken at the closest surface point, not at the noisy
    measured point, so depth noise does not shrink the scale (errors-in-variables attenuation,
    which Umeyama on noisy points shows as ~0.1 % at D455 noise levels). `scene`: the mesh's
    raycasting scene when the caller refits many times.
    """
    o3d = open3d()
    if scene is None:
        scene = mesh_scene(mesh)
    pts = np.asarray(points, dtype=np.float64)
    m = np.asarray(init, dtype=np.float64).copy()
    used = 0
    it = 0
    for it in range(iterations):  # noqa: B007 - reported below
        p = pts @ m[:3, :3].T + m[:3, 3]
        ans = scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        q = ans["points"].numpy().astype(np.float64)
        n = ans["primitive_normals"].numpy().astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        d = ((p - q) * n).sum(1)
        ok = np.linalg.norm(p - q, axis=1) < max_distance_m
        used = int(ok.sum())
        if used < 10:
            raise NoStart(f"fewer than 10 of its depth points lie within {max_distance_m:g} m of the "
                          "reference surface, so the fit has nothing to start from")
        qc = q[ok] - q[ok].mean(0)  # centred: better conditioned scale/translation
        cols = [np.cross(qc, n[ok]), n[ok]] + ([(n[ok] * qc).sum(1)] if with_scale else [])
        a = np.column_stack(cols)
        x, *_ = np.linalg.lstsq(a, -d[ok], rcond=None)
        omega, tau, eps = x[:3], x[3:6], float(x[6]) if with_scale else 0.0
        step = np.eye(4)
        step[:3, :3] = (1.0 + eps) * rodrigues(omega)
        c = q[ok].mean(0)
        step[:3, 3] = c - step[:3, :3] @ c + tau
        m = step @ m
        if max(np.abs(omega).max(), abs(eps), np.abs(tau).max()) < tol:
            break
    return m, {"mesh_refine_iterations": it + 1, "mesh_refine_points": used}


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
    parts = depth_band_frames(source, trajectory, band_m=band_m, tolerance_s=tolerance_s, every=every)
    info: dict[str, Any] = {"band_m": list(band_m), "frames": len(parts)}
    m = init
    if not parts:  # no posed depth in the band: nothing to fit, nor to measure the fit by
        if mode in ("rigid", "similarity"):
            raise EvaluationError(f"--register {mode}: no posed frame has depth in {band_m[0]:g}-"
                                  f"{band_m[1]:g} m to fit (--icp-band-m)")
        info["note"] = f"no posed depth in {band_m[0]:g}-{band_m[1]:g} m: cloud-to-mesh not measured"
        return Registration(m, method, None, None, info, mode, None, scale_band95=scale_band, local=local)
    points = voxel_cloud(parts)
    replicates = None
    if mode in ("rigid", "similarity"):
        scaled = mode == "similarity"
        m, icp_info = icp_with_scale(points, target, init, with_scale=scaled)
        info.update(icp_info)
        method += "+icp"
        if mesh is not None:
            scene = mesh_scene(mesh)
            m, refine_info = refine_on_mesh(points, mesh, m, with_scale=scaled, scene=scene)
            info.update(refine_info)
            method += "+mesh"
            replicates = block_replicates(parts, mesh, m, scaled, scene)
            if scaled and replicates is not None:
                s = float(decompose_similarity(m)[0])
                half = float(jackknife_u95(np.array([decompose_similarity(r)[0] for r in replicates])))
                scale_band = (s - half, s + half)
    c2c, c2m, c2m_median = fit_distances(points, m, target, mesh)
    return Registration(m, method, c2c, c2m, info, mode, c2m_median, scale_band95=scale_band, local=local,
                        replicates=replicates)


def block_replicates(parts: list[F64], mesh: Any, m: F64, with_scale: bool, scene: Any,
                     blocks: int = BAND_BLOCKS) -> list[F64] | None:
    """The mesh refinement redone with each block of consecutive frames left out (min(frames,
    `blocks`) blocks), started from the full fit `m`; None with fewer than 2 frames or when a
    refit has nothing to start from (then no band is claimed)."""
    g = min(len(parts), blocks)
    if g < 2:
        return None
    out = []
    for block in np.array_split(np.arange(len(parts)), g):
        left = set(block.tolist())
        rest = [p for j, p in enumerate(parts) if j not in left]
        try:
            mj, _ = refine_on_mesh(voxel_cloud(rest), mesh, m, with_scale=with_scale, scene=scene)
        except EvaluationError:
            return None
        out.append(mj)
    return out


def jackknife_u95(values: F64) -> F64:
    """Half width of the 95 % interval from delete-one-block jackknife replicates (rows): the
    jackknife standard error sqrt((g - 1) / g sum (v - mean)^2) times t(0.975, g - 1)."""
    v = np.asarray(values, dtype=np.float64)
    g = v.shape[0]
    se = np.sqrt((g - 1) / g * np.sum((v - v.mean(axis=0)) ** 2, axis=0))
    return np.asarray(float(stdtrit(g - 1, 0.975)) * se, dtype=np.float64)


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
