"""Per-pixel correction: the inclination from the depth image itself (local normals through the
camera model's rays) and the model's bias removed, in one numba pass over the image.

Why from the depth itself: a user's sequence has no reference to take normals from. The normal is
the cross product of two tangents, each a difference of back-projected points `STRIDE` pixels apart
on a box-smoothed depth (the smoothing and the stride keep the depth noise out of the angle: at
2 m a 2 mm noise over 8 px tilts a raw normal by ~3 deg). At a crease or an edge the tangent is
taken on the side whose depth continues the pixel's (the smaller step), so a wall's pixels next
to a corner still see the wall.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from depthstation.evaluate.errormodel.schema import THETA_CAP_DEG, ErrorModel

# A jump larger than this share of the depth between two tangent points is an edge, not a slope.
EDGE_SHARE = 0.1
SMOOTH_PX = 5          # box filter of the depth before the tangents (odd)
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


def stride_for(width: int) -> int:
    """Tangent stride: 8 px at 1280 wide, at least 2 (the same angle of view at every resolution)."""
    return max(2, round(width / 160))


def smoothed_depth(depth: NDArray[np.uint16], units_m: float) -> NDArray[np.float32]:
    """Box mean of the valid depths around each pixel (metres, 0 where none is valid)."""
    d = depth.astype(np.float32) * np.float32(units_m)
    valid = (depth > 0).astype(np.float32)
    k = (SMOOTH_PX, SMOOTH_PX)
    s = cv2.boxFilter(d, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = cv2.boxFilter(valid, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    out = np.zeros_like(d)
    np.divide(s, n, out=out, where=n > 0.5)
    return out


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _tangent(zs: Any, x: Any, y: Any, i: int, j: int, di: int, dj: int, s: int, z0: float,
             p0x: float, p0y: float, out: Any) -> bool:
    """Tangent along (di, dj) at pixel (i, j): central, or one-sided where the other side jumps."""
    h, w = zs.shape
    ib, jb, i_f, jf = i - di * s, j - dj * s, i + di * s, j + dj * s
    okb = 0 <= ib < h and 0 <= jb < w and zs[ib, jb] > 0
    okf = 0 <= i_f < h and 0 <= jf < w and zs[i_f, jf] > 0
    lim = EDGE_SHARE * z0
    dzb = abs(zs[ib, jb] - z0) if okb else 1e30
    dzf = abs(zs[i_f, jf] - z0) if okf else 1e30
    okb = okb and dzb < lim
    okf = okf and dzf < lim
    if okb and okf and abs((zs[i_f, jf] - z0) - (z0 - zs[ib, jb])) < 0.25 * max(dzb, dzf) + 1e-4 * z0:
        za, zb = zs[i_f, jf], zs[ib, jb]
        out[0] = x[i_f, jf] * za - x[ib, jb] * zb
        out[1] = y[i_f, jf] * za - y[ib, jb] * zb
        out[2] = za - zb
        return True
    if okf and (not okb or dzf <= dzb):
        za = zs[i_f, jf]
        out[0] = x[i_f, jf] * za - p0x
        out[1] = y[i_f, jf] * za - p0y
        out[2] = za - z0
        return True
    if okb:
        zb = zs[ib, jb]
        out[0] = p0x - x[ib, jb] * zb
        out[1] = p0y - y[ib, jb] * zb
        out[2] = z0 - zb
        return True
    return False


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _basis_value(c: Any, z: float, tn: float) -> float:
    return c[0] + c[1] * z + c[2] * z * z + c[3] * z * tn + c[4] * z * z * tn


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=_FAST)
def correct_kernel(depth: Any, zs: Any, x: Any, y: Any, units: float, s: int, cb: Any, cs: Any,
                   dom: Any, dz_step: float, dt_step: float, theta_cap: float, iterate: int,
                   out_depth: Any, out_sigma: Any, out_theta: Any, want_sigma: bool, counts: Any) -> None:
    """Corrected depth (counts of `units`), sigma (m, NaN where unknown), inclination (deg) per pixel.

    counts per row: [0] corrected, [1] outside the domain, [2] no normal, [3] beyond 16 bits."""
    h, w = depth.shape
    nz, nt = dom.shape
    tcap = math.tan(math.radians(theta_cap))
    for i in numba.prange(h):
        t = np.empty(3)
        u = np.empty(3)
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
            z0 = zs[i, j]
            if z0 <= 0.0:
                z0 = raw * units
            p0x = x[i, j] * z0
            p0y = y[i, j] * z0
            if not (_tangent(zs, x, y, i, j, 0, 1, s, z0, p0x, p0y, t)
                    and _tangent(zs, x, y, i, j, 1, 0, s, z0, p0x, p0y, u)):
                c2 += 1
                continue
            nx = t[1] * u[2] - t[2] * u[1]
            ny = t[2] * u[0] - t[0] * u[2]
            nzv = t[0] * u[1] - t[1] * u[0]
            nn = math.sqrt(nx * nx + ny * ny + nzv * nzv)
            rr = math.sqrt(p0x * p0x + p0y * p0y + z0 * z0)
            if nn <= 0.0 or rr <= 0.0:
                c2 += 1
                continue
            cosv = abs(nx * p0x + ny * p0y + nzv * z0) / (nn * rr)
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
            q = round(zc / units)
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


class Corrector:
    """The model made ready for one stream: coefficient vectors, the domain raster, the rays."""

    def __init__(self, model: ErrorModel, x: NDArray[np.float64], y: NDArray[np.float64], units_m: float,
                 out_units_m: float) -> None:
        self.cb = model.bias.full()
        self.cs = model.sigma.full()
        self.dom, self.dz, self.dt = model.domain.raster()
        self.x, self.y = x, y
        self.units = float(units_m)
        self.out_units = float(out_units_m)
        self.stride = stride_for(x.shape[1])

    def __call__(self, depth: NDArray[np.uint16], want_sigma: bool
                 ) -> tuple[NDArray[np.uint16], NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        h, w = depth.shape
        zs = smoothed_depth(depth, self.units)
        out = np.empty((h, w), np.uint16)
        sig = np.empty((h, w) if want_sigma else (1, 1), np.float32)
        theta = np.empty((h, w), np.float32)
        counts = np.zeros((h, 4), np.int64)
        src = depth
        if self.out_units != self.units:   # a coarser source: correct in the output's units
            src = np.clip(np.rint(depth.astype(np.float64) * (self.units / self.out_units)), 0, 65535
                          ).astype(np.uint16)
        correct_kernel(src, zs, self.x, self.y, self.out_units, self.stride, self.cb, self.cs, self.dom,
                       self.dz, self.dt, THETA_CAP_DEG, 2, out, sig, theta, want_sigma, counts)
        return out, sig, theta, counts.sum(axis=0)
