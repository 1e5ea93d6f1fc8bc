"""Per-pixel correction: the inclination from the depth image itself (local normals through the
camera model's rays) and the model's bias removed, in numba passes over the image.

Why from the depth itself: a user's sequence has no reference to take normals from. On a plane
n . X = 1 the inverse depth is affine in the rays, 1/z = n . (x, y, 1), so its slope over the rays
gives the normal. Real stereo noise is correlated over the matcher's window, so the slopes span
width/40 pixels of a depth box-averaged about as wide: the work is done on a grid of blocks of a
quarter of that (block means, a box of 5 blocks, slopes over 4), one normal per block, which every
pixel of the block takes. At a crease or an edge the slope is taken on the side that is planar
(the smaller second difference of the inverse depth). On the tests' room
(tests/test_error_model.py) the inclination is within 0.3-0.5 deg (median) of the truth below
70 deg and the bias removed per pixel within 1.2 mm (std) of the true one. On the real D435 set,
with a four-term model whose inclination terms magnify a normal's error, slopes over 12 px of 1920
left its boards' plane residual at 13 mm against 7.8 raw (the stereo noise, correlated, tilted the
normals); over 48 px at 8.1-12.1 mm against 7.7-11.2.
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
# The normals are taken on a grid of blocks of stride / COARSE_STRIDE pixels: slopes over
# COARSE_STRIDE blocks of a depth averaged over COARSE_SMOOTH blocks (about the stride's width)
COARSE_STRIDE = 4
COARSE_SMOOTH = 5
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


def stride_for(width: int) -> int:
    """Tangent stride: 8 px at 1280 wide (the same angle of view at every resolution), at least 3
    (on the tests' 160 x 120 room 3 px gave 1.7 deg RMS against 2.2 deg for 2 px below 60 deg)."""
    return max(3, round(width / 40))


@numba.njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _at(wi: Any, i: int, j: int) -> float:
    """wi[i, j], 0 outside the image; clamped indices and a multiply instead of a branch."""
    h, w = wi.shape
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    return wi[min(max(i, 0), h - 1), min(max(j, 0), w - 1)] * inside


@numba.njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _slope(wi: Any, i: int, j: int, di: int, dj: int, s: int, w0: float, share: float) -> tuple[bool, float]:
    """d(1/z)/d(pixel) along (di, dj) at (i, j): central where the surface is planar across the
    pixel, else on the side that is (the smaller second difference of the inverse depth, which is
    affine in the rays on a plane); False where neither side holds a depth that continues it.
    Written without branches (selects): on noisy depth the choice is a coin toss for the branch
    predictor, and the branchy form cost 8x the central difference."""
    lim = share * w0
    wb = _at(wi, i - di * s, j - dj * s)
    wf = _at(wi, i + di * s, j + dj * s)
    wbb = _at(wi, i - 2 * di * s, j - 2 * dj * s)
    wff = _at(wi, i + 2 * di * s, j + 2 * dj * s)
    okb = (wb > 0.0) & (abs(wb - w0) < lim)
    okf = (wf > 0.0) & (abs(wf - w0) < lim)
    big = 1e30
    ddf = abs(wff - 2.0 * wf + w0) if okf & (wff > 0.0) & (abs(wff - wf) < lim) else big
    ddb = abs(w0 - 2.0 * wb + wbb) if okb & (wbb > 0.0) & (abs(wbb - wb) < lim) else big
    use_c = okb & okf & (abs(wf - 2.0 * w0 + wb) <= 2.0 * min(ddf, ddb))
    use_f = (not use_c) & okf & ((ddf <= ddb) | (not okb))
    g = (wf - wb) / (2.0 * s) if use_c else ((wf - w0) / s if use_f else (w0 - wb) / s)
    return use_c | use_f | okb, g


@numba.njit(cache=True, nogil=True, fastmath=_FAST, inline="always")
def _basis_value(c: Any, z: float, tn: float) -> float:
    return c[0] + c[1] * z + c[2] * z * z + c[3] * z * tn + c[4] * z * z * tn


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _cos_at(wi: Any, x: Any, y: Any, jac: Any, i: int, j: int, s: int) -> float:
    """cos(inclination) at pixel (i, j) from the inverse depth's gradient; NaN where there is none.
    On a plane n . X = 1 with X = z (x, y, 1), 1/z = n . (x, y, 1): the gradient of 1/z over the
    rays gives n, and cos(theta) = 1 / (|n| |X|)."""
    w0 = wi[i, j]
    if w0 <= 0.0:
        return np.nan
    xu, xv, yu, yv = jac[i, j, 0], jac[i, j, 1], jac[i, j, 2], jac[i, j, 3]
    oku, gu = _slope(wi, i, j, 0, 1, s, w0, min(EDGE_SHARE_MAX, EDGE_SLOPE * s * abs(xu)))
    okv, gv = _slope(wi, i, j, 1, 0, s, w0, min(EDGE_SHARE_MAX, EDGE_SLOPE * s * abs(yv)))
    if not (oku and okv):
        return np.nan
    det = xu * yv - xv * yu
    gx = (yv * gu - yu * gv) / det
    gy = (xu * gv - xv * gu) / det
    x0 = x[i, j]
    y0 = y[i, j]
    nzc = w0 - gx * x0 - gy * y0
    nn = math.sqrt(gx * gx + gy * gy + nzc * nzc)
    return min(w0 / (nn * math.sqrt(x0 * x0 + y0 * y0 + 1.0)), 1.0)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def normals_kernel(wi: Any, x: Any, y: Any, jac: Any, s: int, sub: int, out_cos: Any, row0: int,
                   row1: int) -> None:
    """cos(inclination) at the centre pixel of every sub x sub block of rows [row0, row1) of the
    coarse grid. Why blocks: the slopes span `s` >= 4 sub pixels of a box-smoothed depth, so the
    normal hardly changes within a block, and one per block costs a sixteenth to a 64th of one per
    pixel (the kernel took 8x the time of the read + write before)."""
    h, w = wi.shape
    for bi in range(row0, row1):
        i = min(bi * sub + sub // 2, h - 1)
        for bj in range(out_cos.shape[1]):
            j = min(bj * sub + sub // 2, w - 1)
            out_cos[bi, bj] = _cos_at(wi, x, y, jac, i, j, s)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def correct_kernel(depth: Any, coarse: Any, sub: int, units: float, cb: Any, cs: Any, dom: Any,
                   dz_step: float, nc: int, theta_cap: float,
                   iterate: int, out_depth: Any, out_sigma: Any, out_cos: Any, want_sigma: bool,
                   counts: Any, row0: int, row1: int) -> None:
    """Corrected depth (counts of `units`), sigma (m, NaN where unknown), cos(inclination) per pixel
    of rows [row0, row1) (each row's result depends on nothing but the inputs: bands may run in
    any order, on any thread). A pixel takes its block's normal (`coarse`); none where the block
    has none (no depth around it, or an edge on both sides).

    `dom` is the domain raster over (z / dz_step, cos(theta) * nc).
    counts per row: [0] corrected, [1] outside the domain, [2] no normal, [3] beyond 16 bits."""
    w = depth.shape[1]
    nz = dom.shape[0]
    ccap = math.cos(math.radians(theta_cap))
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
            out_cos[i, j] = np.nan
            if raw == 0:
                continue
            c = coarse[i // sub, j // sub]
            if not c >= 0.0:
                c2 += 1
                continue
            out_cos[i, j] = c
            zm = raw * units
            iz = int(zm / dz_step)
            ic = min(int(c * nc), nc - 1)
            if iz >= nz or dom[iz, ic] == 0:
                c1 += 1
                continue
            cc = max(c, ccap)
            tn = math.sqrt(1.0 - cc * cc) / cc
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


@numba.njit(cache=True, nogil=True)
def block_sums(depth: Any, sub: int, units: float, out_sum: Any, out_count: Any) -> None:
    """Sum of the valid depths (m) and their count per sub x sub block."""
    h, w = depth.shape
    for i in range(h):
        bi = i // sub
        for j in range(w):
            d = depth[i, j]
            if d != 0:
                out_sum[bi, j // sub] += d * units
                out_count[bi, j // sub] += 1.0


def ray_jacobian(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """dx/du, dx/dv, dy/du, dy/dv of the rays per pixel (H x W x 4). A pinhole's (rays broadcast
    from a row and a column) are one constant, broadcast: no 30 MB array to stream per frame."""
    if x.strides[0] == 0 and y.strides[1] == 0 and x.shape[1] > 1 and y.shape[0] > 1:
        c = np.array([x[0, 1] - x[0, 0], 0.0, 0.0, y[1, 0] - y[0, 0]])
        return np.broadcast_to(c, (*x.shape, 4))
    xv, xu = np.gradient(np.asarray(x, dtype=np.float64))
    yv, yu = np.gradient(np.asarray(y, dtype=np.float64))
    return np.ascontiguousarray(np.stack([xu, xv, yu, yv], axis=-1))


class Corrector:
    """The model made ready for one stream: coefficient vectors, the domain raster, the rays; the
    kernels run in row bands on `threads` threads (they release the GIL)."""

    def __init__(self, model: ErrorModel, x: NDArray[np.float64], y: NDArray[np.float64], units_m: float,
                 out_units_m: float, threads: int = 2) -> None:
        self.cb = model.bias.full()
        self.cs = model.sigma.full()
        self.dom, self.dz, self.nc = model.domain.cos_raster()
        self.units = float(units_m)
        self.out_units = float(out_units_m)
        self.stride = stride_for(x.shape[1])
        self.sub = max(1, round(self.stride / COARSE_STRIDE))
        h, w = x.shape
        self.coarse_shape = (-(-h // self.sub), -(-w // self.sub))
        self.xc, self.yc = self._blocks(np.asarray(x, np.float64)), self._blocks(np.asarray(y, np.float64))
        self.jac = ray_jacobian(self.xc, self.yc)
        self.threads = max(1, threads)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def _blocks(self, a: NDArray[Any]) -> NDArray[Any]:
        """Means over sub x sub blocks (the image's edge blocks over what they hold)."""
        if self.sub == 1:
            return np.ascontiguousarray(a)
        hc, wc = self.coarse_shape
        return np.ascontiguousarray(cv2.resize(a, (wc, hc), interpolation=cv2.INTER_AREA))

    def coarse_inverse_depth(self, depth: NDArray[np.uint16]) -> NDArray[np.float32]:
        """The inverse of the box-mean depth of the valid pixels, on the block grid: block sums
        (one pass over the image) then a box over COARSE_SMOOTH blocks, about the stride's width."""
        ds = np.zeros(self.coarse_shape, np.float32)
        vs = np.zeros(self.coarse_shape, np.float32)
        block_sums(depth, self.sub, self.units, ds, vs)
        k = (COARSE_SMOOTH, COARSE_SMOOTH)
        ds = cv2.boxFilter(ds, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        vs = cv2.boxFilter(vs, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        out = np.zeros(ds.shape, np.float32)
        np.divide(vs, ds, out=out, where=(vs > 1e-3) & (ds > 0))
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()

    def _bands(self, fn: Any, n: int) -> None:
        if self._pool is None:
            fn(0, n)
            return
        edges = np.linspace(0, n, 2 * self.threads + 1).astype(int)
        list(self._pool.map(fn, edges[:-1], edges[1:]))

    def __call__(self, depth: NDArray[np.uint16], want_sigma: bool
                 ) -> tuple[NDArray[np.uint16], NDArray[np.float32], NDArray[np.float32], NDArray[np.int64]]:
        """(corrected depth, sigma or a 1x1 placeholder, cos(inclination), counts)."""
        h, w = depth.shape
        wi = self.coarse_inverse_depth(depth)
        sub = self.sub
        coarse = np.empty(self.coarse_shape, np.float64)
        self._bands(lambda r0, r1: normals_kernel(wi, self.xc, self.yc, self.jac, COARSE_STRIDE, 1, coarse,
                                                  r0, r1), coarse.shape[0])
        out = np.empty((h, w), np.uint16)
        sig = np.empty((h, w) if want_sigma else (1, 1), np.float32)
        cos = np.empty((h, w), np.float32)
        counts = np.zeros((h, 4), np.int64)
        src = depth
        if self.out_units != self.units:   # a coarser source: correct in the output's units
            src = np.clip(np.rint(depth.astype(np.float64) * (self.units / self.out_units)), 0, 65535
                          ).astype(np.uint16)

        def band(r0: int, r1: int) -> None:
            correct_kernel(src, coarse, sub, self.out_units, self.cb, self.cs, self.dom, self.dz, self.nc,
                           THETA_CAP_DEG, 2, out, sig, cos, want_sigma, counts, r0, r1)

        self._bands(band, h)
        return out, sig, cos, counts.sum(axis=0)

    @staticmethod
    def degrees(cos: NDArray[np.float32]) -> NDArray[np.float32]:
        """Inclination in degrees from the kernel's cos(inclination) image (NaN stays NaN)."""
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).astype(np.float32)
