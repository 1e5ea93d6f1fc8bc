"""Sub-pixel board corners by fitting a blurred X-junction model to the pixels (Gauss-Newton).

Why not `cornerSubPix` alone: its gradient-orthogonality estimate is biased by the corner's
sub-pixel phase (~0.045 px RMS, up to 0.09 px on small or foreshortened squares, measured on
exactly rendered corners). The bias is the same in every frame of a still standpoint, so it does
not average out, and it tilts the PnP pose of 12 px squares by 1-2 degrees. A model fit has no
such preferred phase: the image is turned back into linear light (sRGB decoding; pixel values
integrate light, so an edge pixel is an area mix only in linear light), blurred by a known
Gaussian (which makes the pixel box and any optical blur look Gaussian), and fitted per corner by

    I(p) = m + h * erf(n1.(p - c) / (sqrt(2) s)) * erf(n2.(p - c) / (sqrt(2) s))

with the corner c, the two edge directions (n1, n2 their normals), the grey levels m, h and the
blur s free. The residual bias is ~0.01 px (docs/checkerboard-study.md, `benchmarks/
bench_checkerboard.py --corners`).
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

SRGB_TO_LINEAR = ((np.arange(256, dtype=np.float64) / 255.0) ** 2.2).astype(np.float32)
_SQRT_PI = float(np.sqrt(np.pi))


def edge_directions(image_points: F64, object_points: F64) -> tuple[F64, F64, float] | None:
    """Image directions of the board's x and y edges at every corner (unit vectors, N x 2 each) and
    the smallest square side in pixels, from the homography board plane -> image."""
    if len(image_points) < 4:
        return None
    hmat, _ = cv2.findHomography(object_points[:, :2].astype(np.float64),
                                 image_points.astype(np.float64), 0)
    if hmat is None or not np.all(np.isfinite(hmat)):
        return None
    xy1 = np.column_stack([object_points[:, :2], np.ones(len(object_points))])
    p = xy1 @ hmat.T
    w = p[:, 2:3]
    # d(u, v)/dX and d(u, v)/dY of the projective map (metres -> pixels)
    dx = (hmat[:2, 0][None, :] * w - p[:, :2] * hmat[2, 0]) / w**2
    dy = (hmat[:2, 1][None, :] * w - p[:, :2] * hmat[2, 1]) / w**2
    nx = np.linalg.norm(dx, axis=1)
    ny = np.linalg.norm(dy, axis=1)
    if np.any(nx == 0) or np.any(ny == 0):
        return None
    s = float(np.diff(np.sort(np.unique(object_points[:, 0])))[:1].sum() or 0.0)
    side = float(min(nx.min(), ny.min()) * s) if s > 0 else float("nan")
    return dx / nx[:, None], dy / ny[:, None], side


def window_radius(square_px: float) -> int:
    """Fit window half size: ~0.3 square so that the blurred window stays clear of the next edges."""
    if not np.isfinite(square_px):
        return 3
    return int(np.clip(np.floor(0.3 * square_px), 2, 8))


def _blur_matrix(radius: int, pad: int, sigma: float) -> NDArray[np.float32]:
    """(2r+1) x (2r+2pad+1) matrix applying a 1-D Gaussian ('valid' part) to a patch row."""
    k = np.exp(-0.5 * (np.arange(-pad, pad + 1) / sigma) ** 2)
    k /= k.sum()
    n = 2 * radius + 1
    m = np.zeros((n, n + 2 * pad), dtype=np.float32)
    for i in range(n):
        m[i, i:i + 2 * pad + 1] = k
    return m


def refine_xjunctions(gray: NDArray[np.uint8], points: F64, object_points: F64, *,
                      blur_px: float = 1.0, iters: int = 10, linear: bool = True,
                      radius: int | None = None) -> tuple[F64, NDArray[np.bool_]]:
    """Corners refined by the X-junction model fit; (N x 2 points, N accepted flags).

    `points` need to be within ~1 px (cornerSubPix's output or the last frame's corners). A corner
    whose fit fails (diverges, moves > 1 px, implausible blur or contrast) keeps its input position
    and is flagged False.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    ok = np.zeros(n, dtype=bool)
    dirs = edge_directions(pts, np.asarray(object_points, dtype=np.float64))
    if dirs is None:
        return pts.copy(), ok
    ex, ey, side = dirs
    r = radius if radius is not None else window_radius(side)
    pad = int(np.ceil(3.0 * blur_px))
    size = 2 * (r + pad) + 1
    base = np.rint(pts).astype(np.int64)
    off = np.arange(size) - (r + pad)
    h, w = gray.shape
    rows = np.clip(base[:, 1, None] + off[None, :], 0, h - 1)
    cols = np.clip(base[:, 0, None] + off[None, :], 0, w - 1)
    patch = gray[rows[:, :, None], cols[:, None, :]]
    img = SRGB_TO_LINEAR[patch] if linear else patch.astype(np.float32)
    if blur_px > 0:
        km = _blur_matrix(r, pad, blur_px)
        img = km @ img @ km.T
    else:
        img = img[:, pad:pad + 2 * r + 1, pad:pad + 2 * r + 1]
    v = img.reshape(n, -1).astype(np.float64)
    grid = np.arange(-r, r + 1, dtype=np.float64)
    gx = (base[:, 0, None, None] + grid[None, None, :]).repeat(2 * r + 1, axis=1).reshape(n, -1)
    gy = (base[:, 1, None, None] + grid[None, :, None]).repeat(2 * r + 1, axis=2).reshape(n, -1)
    # parameters: cx, cy, a1, a2 (edge angles), m, h, s
    par = np.empty((n, 7))
    par[:, :2] = pts
    par[:, 2] = np.arctan2(ex[:, 1], ex[:, 0])
    par[:, 3] = np.arctan2(ey[:, 1], ey[:, 0])
    par[:, 6] = np.hypot(blur_px, 0.5)
    _, jac = _model(par, gx, gy)
    e = jac[..., 5]  # erf product at the start: solve the grey levels linearly
    a = np.stack([np.ones_like(e), e], axis=-1)
    ata = np.einsum("nki,nkj->nij", a, a) + 1e-9 * np.eye(2)
    par[:, 4:6] = np.linalg.solve(ata, np.einsum("nki,nk->ni", a, v)[..., None])[..., 0]
    eye = np.eye(7)
    for _ in range(iters):
        f, jac = _model(par, gx, gy)
        res = v - f
        jt = jac.transpose(0, 2, 1)
        jtj = jt @ jac
        jtj = jtj + 1e-6 * eye * np.maximum(np.diagonal(jtj, axis1=1, axis2=2), 1e-12)[:, :, None]
        jtr = (jt @ res[..., None])[..., 0]
        try:
            step = np.linalg.solve(jtj, jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return pts.copy(), ok
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        par += step
        par[:, 6] = np.clip(np.abs(par[:, 6]), 0.3, 5.0)
        if float(np.max(np.abs(step[:, :2]))) < 1e-5:
            break
    f, _ = _model(par, gx, gy)
    rms = np.sqrt(np.mean((v - f) ** 2, axis=1))
    moved = np.hypot(*(par[:, :2] - pts).T)
    ok = (np.all(np.isfinite(par), axis=1) & (moved < 1.0) & (par[:, 6] < 4.0)
          & (np.abs(par[:, 5]) > 0.02) & (rms < 0.25 * np.abs(par[:, 5])))
    out = np.where(ok[:, None], par[:, :2], pts)
    return out, ok


def _model(par: F64, gx: F64, gy: F64) -> tuple[F64, F64]:
    """X-junction values and Jacobian (N x K x 7) at pixel centres gx, gy (N x K)."""
    f = np.empty(gx.shape)
    jac = np.empty((*gx.shape, 7))
    _model_kernel(np.ascontiguousarray(par), np.ascontiguousarray(gx), np.ascontiguousarray(gy), f, jac)
    return f, jac


@numba.njit(cache=True, nogil=True)
def _model_kernel(par: F64, gx: F64, gy: F64, f: F64, jac: F64) -> None:  # pragma: no cover
    """One pass per pixel (the model was a third of a frame's time as a dozen numpy temporaries)."""
    for i in range(gx.shape[0]):
        cx, cy, a1, a2, m, h, s = par[i, 0], par[i, 1], par[i, 2], par[i, 3], par[i, 4], par[i, 5], par[i, 6]
        n1x, n1y = -math.sin(a1), math.cos(a1)
        n2x, n2y = -math.sin(a2), math.cos(a2)
        c1, s1 = math.cos(a1), math.sin(a1)
        c2, s2 = math.cos(a2), math.sin(a2)
        k = 1.0 / (math.sqrt(2.0) * s)
        for j in range(gx.shape[1]):
            dx = gx[i, j] - cx
            dy = gy[i, j] - cy
            d1 = n1x * dx + n1y * dy
            d2 = n2x * dx + n2y * dy
            e1 = math.erf(d1 * k)
            e2 = math.erf(d2 * k)
            g1 = 2.0 / _SQRT_PI * math.exp(-((d1 * k) ** 2)) * k
            g2 = 2.0 / _SQRT_PI * math.exp(-((d2 * k) ** 2)) * k
            jac[i, j, 0] = -h * (g1 * n1x * e2 + e1 * g2 * n2x)
            jac[i, j, 1] = -h * (g1 * n1y * e2 + e1 * g2 * n2y)
            jac[i, j, 2] = h * g1 * (-c1 * dx - s1 * dy) * e2
            jac[i, j, 3] = h * e1 * g2 * (-c2 * dx - s2 * dy)
            jac[i, j, 4] = 1.0
            jac[i, j, 5] = e1 * e2
            jac[i, j, 6] = -h / s * (g1 * d1 * e2 + e1 * g2 * d2)
            f[i, j] = m + h * e1 * e2
