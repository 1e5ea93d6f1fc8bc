"""Per-pixel correction: the inclination from the depth image itself (local normals through the
camera model's rays) and the model's bias removed, in one numba pass over the image.

Why from the depth itself: a user's sequence has no reference to take normals from. The normal is
the cross product of two tangents, each a difference of back-projected points a stride apart
(`stride_for`) on a 3 x 3 box-smoothed depth (the smoothing and the stride keep the depth noise out
of the angle). At a crease or an edge the tangent is taken on the side that is planar (the
second difference of the inverse depth, which is affine in the rays on a plane), so a wall's
pixels next to a corner still see the wall. On the tests' room (tests/test_error_model.py) this
took the bias error per pixel from 2.8 mm std (5 x 5 smoothing, the smaller depth step choosing
the side) to 1.2 mm.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.evaluate.errormodel.schema import THETA_CAP_DEG, ErrorModel

# A depth step between two slope points steeper than a surface at 80 deg to the ray is an edge, not
# a slope (the step's share of the depth: EDGE_SLOPE x the lateral spacing over z, at most 0.5).
EDGE_SLOPE = math.tan(math.radians(80.0))
EDGE_SHARE_MAX = 0.5
SMOOTH_MIN_PX = 3      # box filter of the depth before the slopes: the stride's width, at least this (odd)
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


def stride_for(width: int) -> int:
    """Tangent stride: 8 px at 1280 wide (the same angle of view at every resolution), at least 3
    (on the tests' 160 x 120 room 3 px gave 1.7 deg RMS against 2.2 deg for 2 px below 60 deg)."""
    return max(3, round(width / 40))


def smooth_for(stride: int) -> int:
    """Box filter width: the stride's (odd), so the slopes see the noise averaged over what they span."""
    return max(SMOOTH_MIN_PX, 2 * (stride // 2) + 1)


def smoothed_depth(depth: NDArray[np.uint16], units_m: float,
                   size: int = SMOOTH_MIN_PX) -> NDArray[np.float32]:
    """Box mean of the valid depths around each pixel (metres, 0 where none is valid)."""
    d = depth.astype(np.float32) * np.float32(units_m)
    valid = (depth > 0).astype(np.float32)
    k = (size, size)
    s = cv2.boxFilter(d, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = cv2.boxFilter(valid, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    out = np.zeros_like(d)
    np.divide(s, n, out=out, where=n > 0.5)
    return out


@numba.njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _slope(wi: Any, i: int, j: int, di: int, dj: int, s: int, w0: float, share: float) -> tuple[bool, float]:
    """d(1/z)/d(pixel) along (di, dj) at (i, j): central where the surface is planar across the
    pixel, else on the side that is (the smaller second difference of the inverse depth, which is
    affine in the rays on a plane); False where neither side holds a depth that continues it."""
    h, w = wi.shape
    lim = share * w0
    ib, jb, i_f, jf = i - di * s, j - dj * s, i + di * s, j + dj * s
    ibb, jbb, iff, jff = i - 2 * di * s, j - 2 * dj * s, i + 2 * di * s, j + 2 * dj * s
    wb = wi[ib, jb] if 0 <= ib < h and 0 <= jb < w else 0.0
    wf = wi[i_f, jf] if 0 <= i_f < h and 0 <= jf < w else 0.0
    okb = wb > 0.0 and abs(wb - w0) < lim
    okf = wf > 0.0 and abs(wf - w0) < lim
    big = 1e30
    ddf = big
    ddb = big
    if okf and 0 <= iff < h and 0 <= jff < w:
        wff = wi[iff, jff]
        if wff > 0.0 and abs(wff - wf) < lim:
            ddf = abs(wff - 2.0 * wf + w0)
    if okb and 0 <= ibb < h and 0 <= jbb < w:
        wbb = wi[ibb, jbb]
        if wbb > 0.0 and abs(wbb - wb) < lim:
            ddb = abs(w0 - 2.0 * wb + wbb)
    if okb and okf and abs(wf - 2.0 * w0 + wb) <= 2.0 * min(ddf, ddb):
        return True, (wf - wb) / (2.0 * s)
    if okf and (ddf <= ddb or not okb):
        return True, (wf - w0) / s
    if okb:
        return True, (w0 - wb) / s
    return False, 0.0


@numba.njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _basis_value(c: Any, z: float, tn: float) -> float:
    return c[0] + c[1] * z + c[2] * z * z + c[3] * z * tn + c[4] * z * z * tn


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def correct_kernel(depth: Any, wi: Any, x: Any, y: Any, jac: Any, units: float, s: int, cb: Any, cs: Any,
                   dom: Any, dz_step: float, dt_step: float, theta_cap: float, iterate: int,
                   out_depth: Any, out_sigma: Any, out_theta: Any, want_sigma: bool, counts: Any,
                   row0: int, row1: int) -> None:
    """Corrected depth (counts of `units`), sigma (m, NaN where unknown), inclination (deg) per pixel
    of rows [row0, row1) (each row's result depends on nothing but the inputs: bands may run in
    any order, on any thread).

    `wi` is the smoothed inverse depth (1/m, 0 where none); `jac` the rays' derivatives per pixel
    (dx/du, dx/dv, dy/du, dy/dv). On a plane n . X = 1 with X = z (x, y, 1), 1/z = n . (x, y, 1):
    the gradient of 1/z over the rays gives n, and cos(theta) = 1 / (|n| |X|).

    counts per row: [0] corrected, [1] outside the domain, [2] no normal, [3] beyond 16 bits."""
    w = depth.shape[1]
    nz, nt = dom.shape
    tcap = math.tan(math.radians(theta_cap))
    for i in range(row0, row1):
        c0 = 0
        c1 = 0
        c2 = 0
        c3 = 0
        for j in range(w):
            raw = depth[i, j]
            out_depth[i, j] = raw
            if want_sigma:
                out_sigma[i, j] = np.nan
            out_theta[i, j] = np.nan
            if raw == 0:
                continue
            w0 = wi[i, j]
            if w0 <= 0.0:
                w0 = 1.0 / (raw * units)
            xu, xv, yu, yv = jac[i, j, 0], jac[i, j, 1], jac[i, j, 2], jac[i, j, 3]
            oku, gu = _slope(wi, i, j, 0, 1, s, w0, min(EDGE_SHARE_MAX, EDGE_SLOPE * s * abs(xu)))
            okv, gv = _slope(wi, i, j, 1, 0, s, w0, min(EDGE_SHARE_MAX, EDGE_SLOPE * s * abs(yv)))
            if not (oku and okv):
                c2 += 1
                continue
            det = xu * yv - xv * yu
            gx = (yv * gu - yu * gv) / det
            gy = (xu * gv - xv * gu) / det
            x0 = x[i, j]
            y0 = y[i, j]
            nzc = w0 - gx * x0 - gy * y0
            nn = math.sqrt(gx * gx + gy * gy + nzc * nzc)
            cosv = w0 / (nn * math.sqrt(x0 * x0 + y0 * y0 + 1.0))
            cosv = min(cosv, 1.0)
            theta = math.degrees(math.acos(cosv))
            out_theta[i, j] = theta
            zm = raw * units
            iz = int(zm / dz_step)
            it = int(theta / dt_step)
            if iz >= nz or it >= nt or dom[iz, it] == 0:
                c1 += 1
                continue
            tn = math.tan(math.radians(theta)) if theta < theta_cap else tcap
            zc = zm
            for _ in range(iterate):   # z_ref = z_m - b(z_ref): a fixed point, two steps suffice
                zc = zm - _basis_value(cb, zc, tn)
            q = math.floor(zc / units + 0.5)
            if q < 1.0 or q > 65535.0:
                c3 += 1
                out_depth[i, j] = 0
                continue
            out_depth[i, j] = np.uint16(q)
            if want_sigma:
                out_sigma[i, j] = max(_basis_value(cs, zc, tn), 0.0)
            c0 += 1
        counts[i, 0] = c0
        counts[i, 1] = c1
        counts[i, 2] = c2
        counts[i, 3] = c3


def ray_jacobian(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """dx/du, dx/dv, dy/du, dy/dv of the rays per pixel (H x W x 4; a pinhole's are constant)."""
    xv, xu = np.gradient(np.asarray(x, dtype=np.float64))
    yv, yu = np.gradient(np.asarray(y, dtype=np.float64))
    return np.ascontiguousarray(np.stack([xu, xv, yu, yv], axis=-1))


def inverse_depth(zs: NDArray[np.float32]) -> NDArray[np.float32]:
    """1 / z of the smoothed depth, 0 where none."""
    out = np.zeros_like(zs)
    np.divide(np.float32(1.0), zs, out=out, where=zs > 0)
    return out


class Corrector:
    """The model made ready for one stream: coefficient vectors, the domain raster, the rays; the
    kernel runs in row bands on `threads` threads (it releases the GIL)."""

    def __init__(self, model: ErrorModel, x: NDArray[np.float64], y: NDArray[np.float64], units_m: float,
                 out_units_m: float, threads: int = 2) -> None:
        self.cb = model.bias.full()
        self.cs = model.sigma.full()
        self.dom, self.dz, self.dt = model.domain.raster()
        self.x, self.y = x, y
        self.jac = ray_jacobian(x, y)
        self.units = float(units_m)
        self.out_units = float(out_units_m)
        self.stride = stride_for(x.shape[1])
        self.threads = max(1, threads)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def __call__(self, depth: NDArray[np.uint16], want_sigma: bool
                 ) -> tuple[NDArray[np.uint16], NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        h, w = depth.shape
        wi = inverse_depth(smoothed_depth(depth, self.units, smooth_for(self.stride)))
        out = np.empty((h, w), np.uint16)
        sig = np.empty((h, w) if want_sigma else (1, 1), np.float32)
        theta = np.empty((h, w), np.float32)
        counts = np.zeros((h, 4), np.int64)
        src = depth
        if self.out_units != self.units:   # a coarser source: correct in the output's units
            src = np.clip(np.rint(depth.astype(np.float64) * (self.units / self.out_units)), 0, 65535
                          ).astype(np.uint16)
        def band(r0: int, r1: int) -> None:
            correct_kernel(src, wi, self.x, self.y, self.jac, self.out_units, self.stride, self.cb, self.cs,
                           self.dom, self.dz, self.dt, THETA_CAP_DEG, 2, out, sig, theta, want_sigma, counts,
                           r0, r1)

        if self._pool is None:
            band(0, h)
        else:
            edges = np.linspace(0, h, 2 * self.threads + 1).astype(int)
            list(self._pool.map(band, edges[:-1], edges[1:]))
        return out, sig, theta, counts.sum(axis=0)
