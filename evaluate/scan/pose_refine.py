"""Per-frame pose corrections estimated jointly with a low-dimensional sensor field (the budget's maths).

Why jointly: a depth error seen against the reference is the sum of the camera's own error, a
field over distance x inclination shared by every frame, and the pose's error, shared by every
pixel of one frame and smooth in time (SLAM drift). Linearised at the given pose, a pixel's error is

    e = b(z, theta) + g . xi_f ,   g = -[p x n_c, n_c] / (n_c . d)

with xi_f = (omega, v) the correction of frame f in its camera frame (T_true = T exp(xi_f)), d the
pixel's ray (z = 1), p = z d the point and n_c the surface normal in the camera frame. Both parts
are linear, so one sparse least-squares problem (Gauss-Newton, re-rendered at the corrected poses)
holds them: a block-banded part for the frames (a second-difference prior on xi in time: drift; a
weak prior of SLAM size on xi itself: the gauge where a frame's view does not fix a direction)
and a few dense columns for the sensor basis. The sensor basis is there only so that the poses do
not absorb the camera's error; the sensor grid itself is measured afresh with the corrected poses.
Uncertainty: the posterior of the whole problem (Schur complement for the sensor terms, banded
Cholesky for the frames), sampled, so every figure derived from it carries the correlation
between the sensor terms and the poses (what the data cannot separate shows as a wide band).
The banded Cholesky is this module's own (numba, one thread): LAPACK's through a threaded BLAS
took 0.9 s instead of 16 ms for 1334 frames on a loaded 2-core box, and its rounding followed the
CPU's BLAS kernels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

F64 = NDArray[np.float64]

SIGMA_ROT_RAD = float(np.radians(0.3))  # the prior's scale of a SLAM pose error (rotation) ...
SIGMA_TRANS_M = 0.015                    # ... and translation: about what ORB-SLAM3 drifts by
PRIOR_SCALE = np.array([SIGMA_ROT_RAD] * 3 + [SIGMA_TRANS_M] * 3)
RIDGE = 1.0          # prior xi ~ N(0, PRIOR_SCALE^2) per frame: the gauge of what a view does not fix
LAMBDAS = (1e0, 1e2, 1e4, 1e6)  # second-difference weights tried by cross-validation
HOLD_OUT_EVERY = 5   # every 5th frame held out (its data dropped, its pose from the prior) in the CV
MAX_THETA_DEG = 75.0  # beyond: 1/cos(theta) makes a pixel's pose derivative explode
GROSS_M = 0.15       # |error| beyond this is not a depth error (an edge, an occluder) in the first pass
TRIM_SIGMAS = 5.0    # robust trimming of whitened residuals (MAD scale)
NOISE_FLOOR_M = 0.001
SUBPIXEL_PX = 0.08   # Intel's expected disparity noise: sigma_z = z^2 0.08 px / (f B)
SENSOR_TERMS = ("offset", "z", "z2", "z_tan", "z_sec", "z2_sec")
SENSOR_MEANING = {
    "offset": "constant depth offset (m)",
    "z": "depth scale (m per m)",
    "z2": "disparity offset (z^2)",
    "z_tan": "inclination: z tan(theta)",
    "z_sec": "inclination: z (1/cos(theta) - 1) (a slant scale)",
    "z2_sec": "inclination: z^2 (1/cos(theta) - 1) (a slant disparity offset)",
}
REDUCED_TERMS = (0, 1, 2, 3)  # the smaller model whose poses measure how much the choice of model moves them
VIF_LIMIT = 10.0  # a sensor term whose variance grows 10x once the poses are free is not separated


def sensor_basis(z: F64, theta_deg: F64, cols: tuple[int, ...] | None = None) -> F64:
    """The sensor field's basis at distance z (m) and inclination theta: (n, len(SENSOR_TERMS)),
    or its columns `cols`."""
    z = np.asarray(z, dtype=np.float64)
    th = np.radians(np.minimum(np.asarray(theta_deg, dtype=np.float64), MAX_THETA_DEG))
    t = np.tan(th)
    sec = 1.0 / np.cos(th) - 1.0
    out = np.stack([np.ones_like(z), z, z * z, z * t, z * sec, z * z * sec], axis=-1)
    return out if cols is None else out[:, list(cols)]


def skew(w: F64) -> F64:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_se3(xi: F64) -> F64:
    """4x4 of a small motion xi = (omega, v) (first-order translation: the corrections are mm)."""
    w = np.asarray(xi[:3], dtype=np.float64)
    th = float(np.linalg.norm(w))
    k = skew(w)
    if th < 1e-12:
        r = np.eye(3) + k
    else:
        r = np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th ** 2 * (k @ k)
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = xi[3:]
    return m


def corrected(poses: F64, xi: F64) -> F64:
    """T_f exp(xi_f) for every frame."""
    return np.stack([p @ exp_se3(x) for p, x in zip(poses, xi, strict=True)])


@dataclass(frozen=True)
class FrameData:
    """The sampled pixels of one frame at its current pose: what the solve needs."""

    e: F64            # measured - reference z-depth (m)
    z: F64            # reference z-depth (m)
    theta: F64        # inclination (deg)
    g: F64            # (n, 6) d e / d xi
    w: F64            # 1 / sigma^2 of the pixel's depth noise
    c: F64            # n_c . d (point-to-plane over depth)
    key: NDArray[np.int64]  # surface patch of the hit (world voxel and normal direction)
    phi: F64          # (n, len(SENSOR_TERMS)) the sensor basis at (z, theta): computed once

    def take(self, keep: NDArray[np.bool_]) -> FrameData:
        return FrameData(self.e[keep], self.z[keep], self.theta[keep], self.g[keep], self.w[keep],
                         self.c[keep], self.key[keep], self.phi[keep])

    def basis(self, cols: tuple[int, ...] | None = None) -> F64:
        return self.phi if cols is None else self.phi[:, list(cols)]

    @property
    def n(self) -> int:
        return int(self.e.size)


PATCH_M = 0.125


PATCH_NORMAL_M = 1.0   # a patch's extent along its normal: a surface and its defect stay in one patch
PATCH_SHIFT_M = 0.0173  # bins off round coordinates (a room's walls often lie on them)


def patch_keys(points: F64, normals: F64) -> NDArray[np.int64]:
    """A surface patch per hit: PATCH_M squares in the plane of its normal's dominant axis,
    PATCH_NORMAL_M along that axis (centred on whole metres), and the normal's sign."""
    ax = np.argmax(np.abs(normals), axis=1)
    v = np.floor((points + PATCH_SHIFT_M) / PATCH_M).astype(np.int64)
    along = np.floor((np.take_along_axis(points, ax[:, None], axis=1)[:, 0] + PATCH_NORMAL_M / 2)
                     / PATCH_NORMAL_M).astype(np.int64)
    np.put_along_axis(v, ax[:, None], along[:, None], axis=1)
    v += 4096
    sign = (np.take_along_axis(normals, ax[:, None], axis=1)[:, 0] > 0).astype(np.int64)
    return np.asarray(((v[:, 0] * 8192 + v[:, 1]) * 8192 + v[:, 2]) * 6 + ax * 2 + sign, dtype=np.int64)


def patch_centres(keys: NDArray[np.int64]) -> tuple[F64, NDArray[np.int64]]:
    """The centres (m) of the patches `patch_keys` named, and their normals' axis (0-2)."""
    k = np.asarray(keys, dtype=np.int64)
    ax = (k % 6) // 2
    v = k // 6
    vz, v = v % 8192, v // 8192
    vy, vx = v % 8192, v // 8192
    idx = np.stack([vx, vy, vz], axis=1) - 4096
    centre = (idx + 0.5) * PATCH_M - PATCH_SHIFT_M
    rows = np.arange(k.size)
    centre[rows, ax] = idx[rows, ax] * PATCH_NORMAL_M
    return np.asarray(centre, dtype=np.float64), ax


@numba.njit(cache=True, nogil=True)
def _frame_kernel(t: Any, nw: Any, d: Any, zm: Any, rot: Any, trans: Any, z_max: float, gross: float,
                  fb: float, e: Any, z: Any, theta: Any, g: Any, w: Any, c: Any,
                  key: Any) -> int:  # pragma: no cover - compiled
    """`frame_data`'s per-pixel arithmetic in one pass (numpy's took 4 ms a frame of 2500 pixels,
    mostly in calls on short arrays); returns how many samples it wrote."""
    k = 0
    cos_max = np.cos(np.radians(MAX_THETA_DEG))
    for i in range(t.shape[0]):
        zi, ti = zm[i], np.float64(t[i])  # float64 arithmetic on the renderer's float32
        n0, n1, n2 = np.float64(nw[i, 0]), np.float64(nw[i, 1]), np.float64(nw[i, 2])
        if not (zi > 0.0 and np.isfinite(ti) and ti < z_max and np.isfinite(n0) and np.isfinite(n1)
                and np.isfinite(n2)):
            continue
        d0, d1, d2 = np.float64(d[i, 0]), np.float64(d[i, 1]), np.float64(d[i, 2])
        # the normal in the camera frame: R^T n
        c0 = n0 * rot[0, 0] + n1 * rot[1, 0] + n2 * rot[2, 0]
        c1 = n0 * rot[0, 1] + n1 * rot[1, 1] + n2 * rot[2, 1]
        c2 = n0 * rot[0, 2] + n1 * rot[1, 2] + n2 * rot[2, 2]
        ci = c0 * d0 + c1 * d1 + c2 * d2
        cos = min(max(abs(ci) / np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 0.0), 1.0)
        ei = zi - ti
        if not (cos > cos_max and abs(ei) < gross and abs(ci) > 1e-6):
            continue
        p0, p1, p2 = ti * d0, ti * d1, ti * d2
        e[k], z[k], c[k] = ei, ti, ci
        theta[k] = np.degrees(np.arccos(cos))
        g[k, 0] = -(p1 * c2 - p2 * c1) / ci
        g[k, 1] = -(p2 * c0 - p0 * c2) / ci
        g[k, 2] = -(p0 * c1 - p1 * c0) / ci
        g[k, 3], g[k, 4], g[k, 5] = -c0 / ci, -c1 / ci, -c2 / ci
        s = ti * ti * SUBPIXEL_PX / fb
        w[k] = 1.0 / (NOISE_FLOOR_M * NOISE_FLOOR_M + s * s)
        # the hit's surface patch (`patch_keys`): world point and normal
        x0 = rot[0, 0] * p0 + rot[0, 1] * p1 + rot[0, 2] * p2 + trans[0]
        x1 = rot[1, 0] * p0 + rot[1, 1] * p1 + rot[1, 2] * p2 + trans[1]
        x2 = rot[2, 0] * p0 + rot[2, 1] * p1 + rot[2, 2] * p2 + trans[2]
        ax, big, nax, xax = 0, abs(n0), n0, x0
        if abs(n1) > big:
            ax, big, nax, xax = 1, abs(n1), n1, x1
        if abs(n2) > big:
            ax, big, nax, xax = 2, abs(n2), n2, x2
        v0 = np.int64(np.floor((x0 + PATCH_SHIFT_M) / PATCH_M))
        v1 = np.int64(np.floor((x1 + PATCH_SHIFT_M) / PATCH_M))
        v2 = np.int64(np.floor((x2 + PATCH_SHIFT_M) / PATCH_M))
        along = np.int64(np.floor((xax + PATCH_NORMAL_M / 2) / PATCH_NORMAL_M))
        if ax == 0:
            v0 = along
        elif ax == 1:
            v1 = along
        else:
            v2 = along
        sign = 1 if nax > 0 else 0
        key[k] = (((v0 + 4096) * 8192 + (v1 + 4096)) * 8192 + (v2 + 4096)) * 6 + ax * 2 + sign
        k += 1
    return k


def frame_data(t_hit: NDArray[Any], normals: NDArray[Any], dirs: NDArray[Any], pose: F64,
               depth: NDArray[Any], units: float, fb: float, z_max: float,
               gross_m: float = GROSS_M) -> FrameData:
    """Samples of a frame from its rendered reference (z-depth t_hit, world normals per pixel):
    pixels with a depth, a reference hit on measured surface within z_max, below MAX_THETA_DEG
    and within gross_m of the reference."""
    zm = np.ascontiguousarray(depth).ravel().astype(np.float64) * units
    t = np.ascontiguousarray(t_hit).ravel()
    nw = np.ascontiguousarray(normals).reshape(-1, 3)
    d = np.ascontiguousarray(dirs).reshape(-1, 3)
    n = t.shape[0]
    e, z, theta, w, c = (np.empty(n) for _ in range(5))
    g = np.empty((n, 6))
    key = np.empty(n, np.int64)
    pose = np.asarray(pose, dtype=np.float64)
    k = _frame_kernel(t, nw, d, zm, np.ascontiguousarray(pose[:3, :3]), pose[:3, 3].copy(), float(z_max),
                      float(gross_m), float(fb), e, z, theta, g, w, c, key)
    return FrameData(e[:k], z[:k], theta[:k], g[:k], w[:k], c[:k], key[:k], sensor_basis(z[:k], theta[:k]))


@dataclass
class Solution:
    """One solve: increments of the corrections, the sensor terms, and what is needed to sample."""

    dxi: F64          # (F, 6)
    a: F64            # (K,)
    s2: float         # reduced chi^2 (residual scale)
    chol: F64         # banded Cholesky factor L of the frames' block (H = L L^T; lower band form)
    y: F64            # H_pp^-1 H_ps
    s_inv: F64        # Schur complement's inverse (unscaled)
    hss_inv: F64      # H_ss^-1 (the sensor terms' covariance with the poses known)
    samples: int
    cols: tuple[int, ...] | None = None  # the sensor terms fitted (None: all)


def _prior(frames: int, lam: float) -> sp.csr_matrix:
    """lam * (second differences)^T (second differences) + RIDGE, whitened by PRIOR_SCALE."""
    inv = sp.diags(np.tile(1.0 / PRIOR_SCALE ** 2, frames))
    if frames >= 3:
        d2 = sp.diags([np.ones(frames - 2), -2 * np.ones(frames - 2), np.ones(frames - 2)], [0, 1, 2],
                      shape=(frames - 2, frames))
        dd = sp.kron((d2.T @ d2).tocsr(), sp.identity(6))
        prior = lam * (inv @ dd) + RIDGE * inv
    else:
        prior = RIDGE * inv
    return sp.csr_matrix(prior)


BAND = 17  # bandwidth of the frames' block: blocks of 6 and the second difference's reach of 2


def _banded(h: sp.csr_matrix) -> F64:
    """Lower band form: ab[i - j, j] = h[i, j] for j <= i <= j + BAND."""
    n = h.shape[0]
    ab = np.zeros((BAND + 1, n))
    for k in range(BAND + 1):
        ab[k, :n - k] = h.diagonal(-k)
    return ab


@numba.njit(cache=True, nogil=True)
def _chol_band(ab: F64) -> F64:  # pragma: no cover - compiled
    """L of H = L L^T, both in lower band form (ab[i - j, j]); H symmetric positive definite."""
    p = ab.shape[0] - 1
    n = ab.shape[1]
    lb = np.zeros_like(ab)
    for j in range(n):
        s = ab[0, j]
        for k in range(max(0, j - p), j):
            s -= lb[j - k, k] * lb[j - k, k]
        if s <= 0.0:
            raise ValueError("the frames' block is not positive definite")
        d = np.sqrt(s)
        lb[0, j] = d
        for i in range(j + 1, min(n, j + p + 1)):
            s = ab[i - j, j]
            for k in range(max(0, i - p), j):
                s -= lb[i - k, k] * lb[j - k, k]
            lb[i - j, j] = s / d
    return lb


@numba.njit(cache=True, nogil=True)
def _forward(lb: F64, b: F64) -> F64:  # pragma: no cover - compiled
    """y with L y = b (b: (n, m))."""
    p = lb.shape[0] - 1
    n, m = b.shape
    y = b.copy()
    for i in range(n):
        for k in range(max(0, i - p), i):
            f = lb[i - k, k]
            for c in range(m):
                y[i, c] -= f * y[k, c]
        for c in range(m):
            y[i, c] /= lb[0, i]
    return y


@numba.njit(cache=True, nogil=True)
def _backward(lb: F64, y: F64) -> F64:  # pragma: no cover - compiled
    """x with L^T x = y (y: (n, m))."""
    p = lb.shape[0] - 1
    n, m = y.shape
    x = y.copy()
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, min(n, i + p + 1)):
            f = lb[k - i, i]
            for c in range(m):
                x[i, c] -= f * x[k, c]
        for c in range(m):
            x[i, c] /= lb[0, i]
    return x


def chol_solve(lb: F64, b: F64) -> F64:
    """H^-1 b from H's band factor (b: (n,) or (n, m))."""
    b2 = np.ascontiguousarray(b, dtype=np.float64)
    out = _backward(lb, _forward(lb, b2.reshape(b2.shape[0], -1)))
    return np.asarray(out.reshape(b2.shape), dtype=np.float64)


def chol_sample(lb: F64, z: F64) -> F64:
    """L^-T z: N(0, H^-1) for z ~ N(0, I)."""
    z2 = np.ascontiguousarray(z, dtype=np.float64)
    return np.asarray(_backward(lb, z2.reshape(-1, 1)).ravel(), dtype=np.float64)


def solve(data: list[FrameData | None], xi_prev: F64, lam: float,
          cols: tuple[int, ...] | None = None) -> Solution:
    """Joint Gauss-Newton step: frames without data (None: held out or empty) follow the prior;
    `cols`: the sensor terms fitted (all by default)."""
    frames = len(data)
    k = len(SENSOR_TERMS) if cols is None else len(cols)
    hpp_blocks = np.zeros((frames, 6, 6))
    hps = np.zeros((frames * 6, k))
    hss = np.zeros((k, k))
    gp = np.zeros(frames * 6)
    gs = np.zeros(k)
    n = 0
    for f, fd in enumerate(data):
        if fd is None or fd.n == 0:
            continue
        phi = fd.basis(cols)
        gw = fd.g * fd.w[:, None]
        hpp_blocks[f] = gw.T @ fd.g
        hps[6 * f:6 * f + 6] = gw.T @ phi
        hss += (phi * fd.w[:, None]).T @ phi
        gp[6 * f:6 * f + 6] = gw.T @ fd.e
        gs += (phi * fd.w[:, None]).T @ fd.e
        n += fd.n
    prior = _prior(frames, lam)
    gp -= prior @ xi_prev.ravel()
    hpp = (sp.block_diag(list(hpp_blocks), format="csr") + prior).tocsr()
    chol = _chol_band(_banded(hpp))
    y = chol_solve(chol, hps)
    schur = hss - hps.T @ y
    s_inv = np.linalg.inv(schur)
    a = s_inv @ (gs - y.T @ gp)
    dxi = chol_solve(chol, gp - hps @ a)
    chi2 = 0.0
    for f, fd in enumerate(data):
        if fd is None or fd.n == 0:
            continue
        r = fd.e - fd.basis(cols) @ a - fd.g @ dxi[6 * f:6 * f + 6]
        chi2 += float(np.sum(fd.w * r * r))
    s2 = chi2 / max(n - 6 * frames - k, 1)
    try:
        hss_inv = np.linalg.inv(hss)
    except np.linalg.LinAlgError:
        hss_inv = np.full((k, k), np.nan)
    return Solution(dxi.reshape(frames, 6), a, s2, chol, y, np.asarray(s_inv, dtype=np.float64),
                    np.asarray(hss_inv, dtype=np.float64), n, cols)


def residuals(fd: FrameData, a: F64, dxi: F64, cols: tuple[int, ...] | None = None) -> F64:
    return np.asarray(fd.e - fd.basis(cols) @ a - fd.g @ dxi, dtype=np.float64)


def trim(data: list[FrameData | None], sol: Solution) -> list[FrameData | None]:
    """Drop samples whose whitened residual exceeds TRIM_SIGMAS robust sigmas (edges, occluders)."""
    whitened = [None if fd is None or fd.n == 0 else residuals(fd, sol.a, sol.dxi[f]) * np.sqrt(fd.w)
                for f, fd in enumerate(data)]
    live = [rw for rw in whitened if rw is not None]
    if not live:
        return data
    allw = np.concatenate(live)
    scale = 1.4826 * float(np.median(np.abs(allw - np.median(allw)))) or 1.0
    return [fd if fd is None or rw is None else fd.take(np.abs(rw) <= TRIM_SIGMAS * scale)
            for fd, rw in zip(data, whitened, strict=True)]


def cross_validate(data: list[FrameData | None], xi_prev: F64,
                   lambdas: tuple[float, ...] = LAMBDAS) -> tuple[float, list[dict[str, float]]]:
    """The second-difference weight whose poses best predict held-out frames (every
    HOLD_OUT_EVERY-th frame's data dropped; its pose comes from its neighbours by the prior)."""
    held = [f for f in range(len(data)) if f % HOLD_OUT_EVERY == HOLD_OUT_EVERY // 2 and data[f] is not None]
    table: list[dict[str, float]] = []
    if len(data) < 2 * HOLD_OUT_EVERY or not held:
        return lambdas[len(lambdas) // 2], table
    fit_data = [None if f in held else fd for f, fd in enumerate(data)]
    best = (np.inf, lambdas[0])
    for lam in lambdas:
        sol = solve(fit_data, xi_prev, lam)
        num = den = 0.0
        for f in held:
            fd = data[f]
            assert fd is not None
            r = residuals(fd, sol.a, sol.dxi[f])
            num += float(np.sum(fd.w * np.minimum(r * r, 25 * sol.s2 / fd.w)))  # an outlier counts as 5 sigma
            den += float(fd.w.size)
        score = num / max(den, 1.0)
        table.append({"lambda": lam, "held_out_chi2_per_sample": score, "held_out_frames": float(len(held))})
        if score < best[0]:
            best = (score, lam)
    return best[1], table


def draws(sol: Solution, xi_prev: F64, count: int = 40,
          seed: int = 0) -> tuple[F64, F64]:
    """Posterior draws (xi total (D, F, 6), sensor terms (D, K)) of the linear problem: the sensor
    terms from their marginal (the Schur complement: their confusion with the poses included), the
    poses given them, the frames' covariance through the banded Cholesky factor."""
    rng = np.random.default_rng(seed)
    k = sol.a.size
    cov_a = sol.s2 * sol.s_inv
    la = np.linalg.cholesky(0.5 * (cov_a + cov_a.T) + 1e-30 * np.eye(k))
    frames = sol.dxi.shape[0]
    xs = np.empty((count, frames, 6))
    as_ = np.empty((count, k))
    s = np.sqrt(sol.s2)
    for i in range(count):
        da = la @ rng.standard_normal(k)
        eta = chol_sample(sol.chol, rng.standard_normal(frames * 6))
        dx = -sol.y @ da + s * eta  # the frames move with the sensor terms (their correlation)
        as_[i] = sol.a + da
        xs[i] = xi_prev + sol.dxi + dx.reshape(frames, 6)
    return xs, as_


@dataclass
class Patches:
    """Reference surface patches whose error is the same seen from every frame: a mesh defect."""

    keys: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    offset_m: F64 = field(default_factory=lambda: np.zeros(0))   # along the normal (point-to-plane)
    u95_m: F64 = field(default_factory=lambda: np.zeros(0))
    frames: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    z_span_m: F64 = field(default_factory=lambda: np.zeros(0))
    defect: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))

    def lookup(self, keys: NDArray[np.int64]) -> F64:
        """Point-to-plane offset of the defect patches at `keys` (0 elsewhere)."""
        out = np.zeros(keys.shape)
        if not self.keys.size:
            return out
        idx = np.searchsorted(self.keys, keys)
        idx = np.clip(idx, 0, self.keys.size - 1)
        hit = (self.keys[idx] == keys) & self.defect[idx]
        out[hit] = self.offset_m[idx[hit]]
        return out


DEFECT_MIN_M = 0.003   # a patch offset below this is not called a defect
DEFECT_FRAMES = 3      # seen by at least this many frames
DEFECT_Z_SPAN_M = 0.2  # from distances at least this far apart: a sensor error would change with them
DEFECT_SIGMAS = 5.0    # and off the patches' median by this many robust spreads
DEFECT_U95S = 2.0      # and by twice its U95 (4 sigma: hundreds of patches are tested)


def find_patches(data: list[FrameData | None], sol: Solution) -> Patches:
    """Per surface patch the mean point-to-plane residual and its frames-as-clusters U95; a defect
    when it is larger than DEFECT_MIN_M and twice its U95, seen by DEFECT_FRAMES frames from distances
    DEFECT_Z_SPAN_M apart (so that it is the surface, not the camera at one distance). Summed per
    frame first (a few hundred patches each), then over the frames: no sort of every sample."""
    live = [(f, fd) for f, fd in enumerate(data) if fd is not None and fd.n]
    if not live:
        return Patches()
    res = [residuals(fd, sol.a, sol.dxi[f]) for f, fd in live]
    # the camera's own error beyond the smooth model is a function of distance x inclination: taken
    # out by each 0.25 m x 5 deg cell's mean residual, so that what stays is the surface's
    cells = [(fd.z / 0.25).astype(np.int64) * 100 + (fd.theta / 5.0).astype(np.int64) for _, fd in live]
    call = np.concatenate(cells)
    wd = np.concatenate([fd.w for _, fd in live])
    rr = np.concatenate(res)
    with np.errstate(invalid="ignore", divide="ignore"):
        cell_mean = np.bincount(call, wd * rr) / np.bincount(call, wd)
    pk, pf, pw, pq, pz0, pz1 = [], [], [], [], [], []
    for (f, fd), r, cell in zip(live, res, cells, strict=True):
        qq = (r - cell_mean[cell]) * fd.c
        ww = fd.w / (fd.c * fd.c)
        uk, inv = np.unique(fd.key, return_inverse=True)
        zmin = np.full(uk.size, np.inf)
        zmax = np.full(uk.size, -np.inf)
        np.minimum.at(zmin, inv, fd.z)
        np.maximum.at(zmax, inv, fd.z)
        pk.append(uk)
        pf.append(np.full(uk.size, f))
        pw.append(np.bincount(inv, ww, minlength=uk.size))
        pq.append(np.bincount(inv, ww * qq, minlength=uk.size))
        pz0.append(zmin)
        pz1.append(zmax)
    keys = np.concatenate(pk)
    fw, fq = np.concatenate(pw), np.concatenate(pq)
    uk, inv = np.unique(keys, return_inverse=True)
    sw = np.bincount(inv, fw, minlength=uk.size)
    mean = np.bincount(inv, fq, minlength=uk.size) / sw
    # frames as clusters: the per (patch, frame) means about the patch's
    nf = np.bincount(inv, minlength=uk.size)
    dev = fw * (fq / fw - mean[inv])
    var = np.bincount(inv, dev * dev, minlength=uk.size) / (sw * sw) * nf / np.maximum(nf - 1, 1)
    u95 = 1.96 * np.sqrt(var)
    zmin = np.full(uk.size, np.inf)
    zmax = np.full(uk.size, -np.inf)
    np.minimum.at(zmin, inv, np.concatenate(pz0))
    np.maximum.at(zmax, inv, np.concatenate(pz1))
    span = zmax - zmin
    seen = (nf >= DEFECT_FRAMES) & (span >= DEFECT_Z_SPAN_M)
    # a defect is local: an outlier among the patches (a shared offset of all of them is the
    # sensor's or the poses', never the mesh's)
    typical = float(np.median(mean[seen])) if seen.any() else 0.0
    spread = 1.4826 * float(np.median(np.abs(mean[seen] - typical))) if seen.any() else 0.0
    off = np.abs(mean - typical)
    defect = seen & (off > np.maximum(DEFECT_MIN_M, DEFECT_U95S * u95)) & (off > DEFECT_SIGMAS * spread)
    return Patches(uk, mean, u95, nf, span, defect)


def without_patches(data: list[FrameData | None], patches: Patches) -> list[FrameData | None]:
    """The samples less those on defect patches: a mesh defect must not move the poses (it would
    pull the frames that see it and leave its trace on the neighbouring patches)."""
    if not patches.defect.any():
        return data
    bad = patches.keys[patches.defect]
    return [fd if fd is None or fd.n == 0 else fd.take(~np.isin(fd.key, bad)) for fd in data]


def _skews(v: F64) -> F64:
    """skew(v_f) for every row of v: (F, 3, 3)."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def split_registration(poses: F64, xi: F64) -> tuple[F64, dict[str, Any]]:
    """The global part of the corrections: one small similarity of the reference frame (rotation
    r, translation t, scale k about the walk's centroid) that best moves the given cameras onto the
    corrected ones (rotations and centres, each weighted by PRIOR_SCALE); its per-frame xi and the
    parameters. The rest is the poses' own (per-frame) error. Gauge: the registration is this
    least-squares similarity, so the per-frame part has no global rotation, translation or scale."""
    rots = poses[:, :3, :3]
    d = poses[:, :3, 3] - poses[:, :3, 3].mean(axis=0)
    c0 = poses[:, :3, 3].mean(axis=0)
    frames = poses.shape[0]
    # per frame: rotation R omega = r_g; centre R v = r_g x (c - c0) + t + k (c - c0)
    a = np.zeros((frames, 6, 7))
    a[:, 0:3, 0:3] = np.eye(3)
    a[:, 3:6, 0:3] = -_skews(d)
    a[:, 3:6, 3:6] = np.eye(3)
    a[:, 3:6, 6] = d
    rhs = np.concatenate([np.einsum("fij,fj->fi", rots, xi[:, :3]),
                          np.einsum("fij,fj->fi", rots, xi[:, 3:])], axis=1)
    # weighted least squares by its 7 x 7 normal equations (lstsq of the 6F x 7 system went
    # through a threaded BLAS: 55 ms a call on a loaded box, 40 draws)
    w2 = (1.0 / PRIOR_SCALE) ** 2
    aw = a * w2[None, :, None]
    sol = np.linalg.solve(np.einsum("fki,fkj->ij", aw, a), np.einsum("fki,fk->i", aw, rhs))
    rg, tg, kg = sol[:3], sol[3:6], float(sol[6])
    xreg = np.empty_like(xi)
    xreg[:, :3] = np.einsum("fji,j->fi", rots, rg)
    xreg[:, 3:] = np.einsum("fji,fj->fi", rots, np.cross(rg, d) + tg + kg * d)
    return xreg, {"rotation_rad": rg.tolist(), "translation_m": tg.tolist(), "scale": 1.0 + kg,
                  "about_m": c0.tolist()}
