"""Reference depth of a pinhole view by rasterising the mesh: per pixel centre the z-depth, the hit
triangle and its normal, bit for bit what Open3D's ray casting returns for the same rays.

Why: a depth frame is a pinhole view, so its rays share one origin and pass through a regular grid
of pixel centres. Projecting each triangle onto that grid finds the few pixels it can cover
(a z-buffer keeps the nearest), instead of a general ray caster walking a BVH for every one of
307 k independent rays. Clusters of 1024 spatially sorted triangles are culled against the view
frustum first, so a frame touches only the part of the mesh in view.

Exactness: every candidate (pixel, triangle) pair is decided with the arithmetic of Embree's
robust triangle test as Open3D's `RaycastingScene` runs it (the ray origin moved to zero, Pluecker
edge tests on float32 coordinates with a one-ulp tolerance, the stable triangle normal, the hit
distance as approximate reciprocal + one Newton step times the plane offset, fused multiply-adds
where Embree's AVX2 kernel has them), so depth, triangle and normal are the same float32 values.
Which arithmetic the installed Open3D uses is measured once per process (`arithmetic()`): a small
scene is cast with Open3D and the variant that reproduces it bit for bit is kept. The projected
bounding box of a triangle is widened by a bound on Embree's rounding (tens of ulps of the angle,
more where the camera sits near the triangle's plane), so no pixel that Embree would hit is left
untested. Culling back faces would be faster, but ray casting hits back faces (open meshes, holes),
so they are rasterised too. Ties (a ray exactly on an edge shared by two triangles at the same
depth) go to the lower triangle id; Embree's choice there depends on its tree and may differ.

Lens distortion: the projection of a triangle onto the pixel grid is exact only for a pinhole;
with distortion the rays are not a grid and callers fall back to ray casting (`Intrinsics.has_distortion`).
"""

from __future__ import annotations

import copy
import platform
import threading
from functools import cache
from typing import Any

import numba
import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.cpython.unsafe.numbers import trailing_zeros as _trailing_zeros
from numba.extending import intrinsic
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.lazy_open3d import open3d

# measured with benchmarks/bench_raster_constants.py: 64 took 1.3x the CPU per frame, 512 1.03x
CLUSTER_SIZE = 1024
TIE_ROOM = 4096  # equal-depth hits a frame may note before it is rendered again with more room
SMALL_BOX = 16  # triangles whose box holds at most this many pixel centres skip the edge walk
# a kept cluster's triangles are culled again in blocks of this many (measured: without blocks
# 1.16x the CPU per frame; blocks of 32-256 within 1 % of each other;
# benchmarks/bench_raster_constants.py)
BLOCK_SIZE = 128
if CLUSTER_SIZE % BLOCK_SIZE or CLUSTER_SIZE // BLOCK_SIZE > 32:  # the blocks kept are bits of an int64
    raise ValueError("BLOCK_SIZE must divide CLUSTER_SIZE into at most 32 blocks")
if not 1 <= SMALL_BOX <= 62:  # pragma: no cover - a small box's pixel centres are bits of an int64
    raise ImportError(f"SMALL_BOX {SMALL_BOX} must be 1-62 (`_small_mask`)")
_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")

# arithmetic variants (which Embree kernel Open3D runs on this CPU)
FMA_RCP = 0      # AVX2 kernel: fused multiply-adds, rcpps + Newton step with FMA
PLAIN_RCP = 1    # SSE / AVX kernel: separate multiply and add, rcpps + Newton step
FMA_DIV = 2      # exact division (no x86 rcp), fused multiply-adds (e.g. aarch64 builds)
PLAIN_DIV = 3
ARITHMETIC_NAMES = {FMA_RCP: "fma+rcp", PLAIN_RCP: "plain+rcp", FMA_DIV: "fma+div", PLAIN_DIV: "plain+div"}


def _fma32_impl(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """a * b + c with one rounding (llvm.fma.f32), as Embree's madd/msub on FMA hardware."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        f32 = ir.FloatType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f32], fnty=ir.FunctionType(f32, [f32, f32, f32]))
        return builder.call(fn, args)

    return sig, codegen


_fma32: Any = intrinsic(_fma32_impl)


if _X86:
    def _rcp_approx_impl(typingctx: Any, a: Any) -> Any:
        """The x86 approximate reciprocal (rcpss) of this CPU, the seed of Embree's rcp()."""
        sig = types.float32(types.float32)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            vt = ir.VectorType(ir.FloatType(), 4)
            fn = builder.module.declare_intrinsic("llvm.x86.sse.rcp.ss", fnty=ir.FunctionType(vt, [vt]))
            zero = ir.Constant(ir.IntType(32), 0)
            v = builder.insert_element(ir.Constant(vt, ir.Undefined), args[0], zero)
            return builder.extract_element(builder.call(fn, [v]), zero)

        return sig, codegen

    _rcp_approx: Any = intrinsic(_rcp_approx_impl)
else:  # pragma: no cover - no approximate reciprocal: the division variants are used
    @numba.njit(inline="always")
    def _rcp_approx(a: Any) -> Any:
        return np.float32(1.0) / a


# the rasteriser allocates nothing (no reference counting in its loops), and divides without
# Python's zero checks
_KERNEL_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "_nrt": False, "error_model": "numpy"}
_ONE = np.float32(1.0)
_cttz: Any = _trailing_zeros  # the lowest set bit's index (llvm.cttz)
_ULP = np.float32(np.finfo(np.float32).eps)


@numba.njit(inline="always")
def _madd(a: Any, b: Any, c: Any, fma: bool) -> Any:
    if fma:
        return _fma32(a, b, c)
    return a * b + c


@numba.njit(inline="always")
def _msub(a: Any, b: Any, c: Any, fma: bool) -> Any:
    if fma:
        return _fma32(a, b, -c)
    return a * b - c


@numba.njit(inline="always")
def _dot(ax: Any, ay: Any, az: Any, bx: Any, by: Any, bz: Any, fma: bool) -> Any:
    return _madd(ax, bx, _madd(ay, by, az * bz, fma), fma)


@numba.njit(inline="always")
def _cross(ax: Any, ay: Any, az: Any, bx: Any, by: Any, bz: Any, fma: bool) -> Any:
    return (_msub(ay, bz, az * by, fma), _msub(az, bx, ax * bz, fma), _msub(ax, by, ay * bx, fma))


@numba.njit(inline="always")
def _reciprocal(a: Any, mode: int) -> Any:
    if mode == FMA_RCP:
        r = _rcp_approx(a)
        return _fma32(r, _fma32(-a, r, _ONE), r)
    if mode == PLAIN_RCP:
        r = _rcp_approx(a)
        return r + r * (_ONE - a * r)
    return _ONE / a


@numba.njit(inline="always")
def _plane(e0x: Any, e0y: Any, e0z: Any, e1x: Any, e1y: Any, e1z: Any, e2x: Any, e2y: Any, e2z: Any,
           p0x: Any, p0y: Any, p0z: Any, fma: bool) -> Any:
    """Stable triangle normal (of the two cross products, per component the one with the smaller
    rounding error) and twice the plane offset of the origin-shifted triangle."""
    ab_x, ab_y, ab_z = e0z * e1y, e0x * e1z, e0y * e1x
    bc_x, bc_y, bc_z = e1z * e2y, e1x * e2z, e1y * e2x
    nx = _msub(e0y, e1z, ab_x, fma) if abs(ab_x) < abs(bc_x) else _msub(e1y, e2z, bc_x, fma)
    ny = _msub(e0z, e1x, ab_y, fma) if abs(ab_y) < abs(bc_y) else _msub(e1z, e2x, bc_y, fma)
    nz = _msub(e0x, e1y, ab_z, fma) if abs(ab_z) < abs(bc_z) else _msub(e1x, e2y, bc_z, fma)
    t2 = _dot(p0x, p0y, p0z, nx, ny, nz, fma)
    return nx, ny, nz, t2 + t2


@numba.njit(inline="always")
def _setup_p(p0x: Any, p0y: Any, p0z: Any, p1x: Any, p1y: Any, p1z: Any, p2x: Any, p2y: Any, p2z: Any,
             fma: bool) -> Any:
    """Per triangle and ray origin, from its vertices with the origin moved to zero (float32): the
    three edge-plane normals (Pluecker), the stable geometric normal and twice the plane offset."""
    e0x, e0y, e0z = p2x - p0x, p2y - p0y, p2z - p0z
    e1x, e1y, e1z = p0x - p1x, p0y - p1y, p0z - p1z
    e2x, e2y, e2z = p1x - p2x, p1y - p2y, p1z - p2z
    ux, uy, uz = _cross(e0x, e0y, e0z, p2x + p0x, p2y + p0y, p2z + p0z, fma)
    wx, wy, wz = _cross(e1x, e1y, e1z, p0x + p1x, p0y + p1y, p0z + p1z, fma)
    qx, qy, qz = _cross(e2x, e2y, e2z, p1x + p2x, p1y + p2y, p1z + p2z, fma)
    nx, ny, nz, t2 = _plane(e0x, e0y, e0z, e1x, e1y, e1z, e2x, e2y, e2z, p0x, p0y, p0z, fma)
    return ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2


@numba.njit(inline="always")
def _setup(vx: Any, ia: int, ib: int, ic: int, ox: Any, oy: Any, oz: Any, fma: bool) -> Any:
    """`_setup_p` of the triangle (vx[ia], vx[ib], vx[ic]) seen from (ox, oy, oz), all float32."""
    return _setup_p(vx[ia, 0] - ox, vx[ia, 1] - oy, vx[ia, 2] - oz, vx[ib, 0] - ox, vx[ib, 1] - oy,
                    vx[ib, 2] - oz, vx[ic, 0] - ox, vx[ic, 1] - oy, vx[ic, 2] - oz, fma)


@numba.njit(inline="always")
def _setup_at(tv: Any, bv: int, q: int, ox: Any, oy: Any, oz: Any, fma: bool) -> Any:
    """`_setup_p` of triangle q of the cluster whose vertex block starts at tv[bv] (`_prepare`)."""
    c = CLUSTER_SIZE
    return _setup_p(tv[bv + q] - ox, tv[bv + c + q] - oy, tv[bv + 2 * c + q] - oz,
                    tv[bv + 3 * c + q] - ox, tv[bv + 4 * c + q] - oy, tv[bv + 5 * c + q] - oz,
                    tv[bv + 6 * c + q] - ox, tv[bv + 7 * c + q] - oy, tv[bv + 8 * c + q] - oz, fma)


@numba.njit(inline="always")
def _test(ux: Any, uy: Any, uz: Any, wx: Any, wy: Any, wz: Any, qx: Any, qy: Any, qz: Any,
          nx: Any, ny: Any, nz: Any, t2: Any, dx: Any, dy: Any, dz: Any, tfar: Any, mode: int,
          fma: bool) -> tuple[bool, Any]:
    """The edge tests (one-ulp tolerance, either orientation) and the hit distance: (hit, t).
    Computed without branches (every value, then one mask): a pixel test is a coin flip near
    edges, and mispredicted branches cost more than the arithmetic."""
    u = _dot(ux, uy, uz, dx, dy, dz, fma)
    v = _dot(wx, wy, wz, dx, dy, dz, fma)
    w = _dot(qx, qy, qz, dx, dy, dz, fma)
    eps = _ULP * abs(u + v + w)
    inside = (min(u, min(v, w)) >= -eps) | (max(u, max(v, w)) <= eps)
    den = _dot(nx, ny, nz, dx, dy, dz, fma)
    den = den + den
    t = _reciprocal(den, mode) * t2
    return inside & (den != 0) & (t >= 0) & (t <= tfar), t


@numba.njit(inline="always")
def _unit_normal(nx: Any, ny: Any, nz: Any, out: Any, k: int) -> None:
    """Open3D's normalisation of Embree's geometric normal (float32, one division, three products)."""
    inv = _ONE / np.sqrt(nx * nx + ny * ny + nz * nz)
    out[k, 0] = nx * inv
    out[k, 1] = ny * inv
    out[k, 2] = nz * inv


@numba.njit(inline="always")
def world_direction(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float, r20: float,
               r21: float, r22: float, x: Any, y: Any, z: Any) -> Any:
    """World direction of a camera-frame ray, float64 products and sums rounded once to float32."""
    return (np.float32(r00 * x + r01 * y + r02 * z), np.float32(r10 * x + r11 * y + r12 * z),
            np.float32(r20 * x + r21 * y + r22 * z))


@numba.njit(inline="always")
def _dir_sum(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float, r02: float, r12: float,
             r22: float) -> Any:
    """`world_direction` from a column's products (a) and a row's (b): same operations, same order."""
    return np.float32(a0 + b0 + r02), np.float32(a1 + b1 + r12), np.float32(a2 + b2 + r22)


@numba.njit(inline="always")
def _col(dtab: Any, u: Any) -> tuple[float, float, float]:
    """Column u's products of the ray directions (`_render`'s dtab rows 0-2); u taken as unsigned,
    so no negative-index wraparound is computed per pixel."""
    u = np.uint64(u)
    return dtab[0, u], dtab[1, u], dtab[2, u]


@numba.njit(inline="always")
def _row(dtab: Any, v: Any) -> tuple[float, float, float]:
    """Row v's products of the ray directions (`_render`'s dtab rows 3-5), v unsigned."""
    v = np.uint64(v)
    return dtab[3, v], dtab[4, v], dtab[5, v]


@numba.njit(cache=True, nogil=True)
def fill_rays(rays: Any, origin: Any, rot: Any, dirs: Any) -> None:
    """rays[i] = (origin, rot @ dirs[i]) as float32: the rays both reference-depth renderers use
    (Open3D's caster takes this array; the rasteriser computes the same directions per pixel)."""
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    for i in range(dirs.shape[0]):
        dx, dy, dz = world_direction(r00, r01, r02, r10, r11, r12, r20, r21, r22,
                                dirs[i, 0], dirs[i, 1], dirs[i, 2])
        rays[i, 0] = origin[0]
        rays[i, 1] = origin[1]
        rays[i, 2] = origin[2]
        rays[i, 3] = dx
        rays[i, 4] = dy
        rays[i, 5] = dz


@numba.njit(cache=True, nogil=True)
def _probe(vx: Any, tri: Any, rays: Any, ids: Any, mode: int, t_out: Any, n_out: Any) -> None:
    """t and unit normal of ray i against triangle ids[i] (NaN where it misses), one variant."""
    fma = mode in (FMA_RCP, FMA_DIV)
    for i in range(rays.shape[0]):
        t_out[i] = np.nan
        k = ids[i]
        if k < 0:
            continue
        ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2 = _setup(
            vx, tri[k, 0], tri[k, 1], tri[k, 2], rays[i, 0], rays[i, 1], rays[i, 2], fma)
        hit, t = _test(ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2, rays[i, 3], rays[i, 4], rays[i, 5],
                       np.float32(np.inf), mode, fma)
        if hit:
            t_out[i] = t
            _unit_normal(nx, ny, nz, n_out, i)


@numba.njit(inline="always")
def _extent(pu: Any, pv: Any, n: int) -> tuple[float, float, float, float]:
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    for k in range(n):
        umin = min(umin, pu[k])
        umax = max(umax, pu[k])
        vmin = min(vmin, pv[k])
        vmax = max(vmax, pv[k])
    return umin, umax, vmin, vmax


@numba.njit(inline="always")
def clip_polygon(pu: Any, pv: Any, n: int, axis: int, bound: float, keep_above: bool, cu: Any,
                 cv: Any) -> int:
    """Sutherland-Hodgman: clip the convex polygon (pu, pv)[:n] in place to the half-plane
    coordinate >= bound (keep_above) or <= bound along axis 0 (u) or 1 (v); the new vertices on
    the boundary get exactly `bound`. pu, pv and the scratch cu, cv hold at least n + 1 values
    (a convex polygon gains at most one vertex). Returns the new count."""
    m = 0
    for k in range(n):
        l = k + 1 if k + 1 < n else 0
        a = pu[k] if axis == 0 else pv[k]
        b = pu[l] if axis == 0 else pv[l]
        ina = a >= bound if keep_above else a <= bound
        inb = b >= bound if keep_above else b <= bound
        if ina:
            cu[m] = pu[k]
            cv[m] = pv[k]
            m += 1
        if ina != inb:
            f = (bound - a) / (b - a)
            cu[m] = pu[k] + f * (pu[l] - pu[k])
            cv[m] = pv[k] + f * (pv[l] - pv[k])
            if axis == 0:
                cu[m] = bound
            else:
                cv[m] = bound
            m += 1
    for k in range(m):
        pu[k] = cu[k]
        pv[k] = cv[k]
    return m


@numba.njit(inline="always")
def _note_tie(ties: Any, tie_t: Any, i: int, t: Any) -> None:
    """Record that a hit at pixel i equalled its nearest depth so far (ties[0] counts them, also
    beyond the capacity, so that the caller can render again with room for all). A rare branch,
    instead of a flag per pixel read and written by every test."""
    n = ties[0] + 1
    ties[0] = n
    if n < ties.shape[0]:
        ties[n] = i
        tie_t[n] = t


@numba.njit(inline="always")
def _keep(i: Any, ux: Any, uy: Any, uz: Any, wx: Any, wy: Any, wz: Any, qx: Any, qy: Any, qz: Any, nx: Any,
          ny: Any, nz: Any, t2: Any, dx: Any, dy: Any, dz: Any, ident: int, zbuf: Any, tid: Any, ties: Any,
          tie_t: Any, mode: int, fma: bool) -> bool:
    """Pixel i's reference test against the set-up triangle `ident`; the nearer hit (the lower id
    at equal depth) is kept, an equal depth noted (`_note_tie`). Returns whether this one won."""
    i = np.uint64(i)  # never negative: no wraparound per access
    z = zbuf[i]
    k = tid[i]
    hit, t = _test(ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2, dx, dy, dz, z, mode, fma)
    better = hit & ((t < z) | (ident < k))
    zbuf[i] = t if better else z
    tid[i] = ident if better else k
    if hit & (t == z):
        _note_tie(ties, tie_t, i, t)
    return better


@numba.njit(inline="always")
def _raster_polygon(pu: Any, pv: Any, npoly: int, m: float, full: bool, width: int, height: int,
                    tv: Any, bv: int, q: int, ox32: Any, oy32: Any, oz32: Any, ident: int,
                    dtab: Any, r02: float, r12: float, r22: float, mode: int, fma: bool, zbuf: Any,
                    tid: Any, ties: Any, tie_t: Any, nrm: Any, sc: Any) -> tuple[int, int]:
    """Test every pixel centre within m of the projected polygon (pu, pv)[:npoly] (all pixels
    when `full`) against the triangle in the reference arithmetic; keep the nearest hit.
    Returns (1 if the triangle was set up, pixel tests)."""
    cu, cv, ea, eb, ec, inv_a = sc[0], sc[1], sc[2], sc[3], sc[4], sc[5]
    umin, umax, vmin, vmax = _extent(pu, pv, npoly)
    if full:
        u0, u1, v0, v1 = 0, width - 1, 0, height - 1
        npoly = 0
    else:
        # a polygon reaching out of the image is clipped to it (widened by m): its box then
        # holds only lines that can meet pixels
        if umin < -m or umax > width - 1.0 + m or vmin < -m or vmax > height - 1.0 + m:
            npoly = clip_polygon(pu, pv, npoly, 0, -m, True, cu, cv)
            npoly = clip_polygon(pu, pv, npoly, 0, width - 1.0 + m, False, cu, cv)
            npoly = clip_polygon(pu, pv, npoly, 1, -m, True, cu, cv)
            npoly = clip_polygon(pu, pv, npoly, 1, height - 1.0 + m, False, cu, cv)
            if npoly == 0:
                return 0, 0
            umin, umax, vmin, vmax = _extent(pu, pv, npoly)
        u0 = max(0, int(np.ceil(umin - m)))
        u1 = min(width - 1, int(np.floor(umax + m)))
        v0 = max(0, int(np.ceil(vmin - m)))
        v1 = min(height - 1, int(np.floor(vmax + m)))
        if u0 > u1 or v0 > v1:
            return 0, 0
    # the polygon's edges pushed out by m (|dx| + |dy| >= the edge length), as half-planes
    # a u + b v + c >= 0; a nearly degenerate projection (seen edge-on) keeps only its box
    area2 = 0.0
    scale2 = 0.0
    for k in range(npoly):
        l = k + 1 if k + 1 < npoly else 0
        area2 += pu[k] * pv[l] - pu[l] * pv[k]
        scale2 += abs(pu[k] * pv[l]) + abs(pu[l] * pv[k])
    nedge = 0
    if abs(area2) > 1e-9 * scale2:
        sigma = 1.0 if area2 > 0 else -1.0
        for k in range(npoly):
            l = k + 1 if k + 1 < npoly else 0
            dx = pu[l] - pu[k]
            dy = pv[l] - pv[k]
            if dx == 0.0 and dy == 0.0:
                continue
            ea[nedge] = -sigma * dy
            eb[nedge] = sigma * dx
            ec[nedge] = sigma * (dy * pu[k] - dx * pv[k]) + m * (abs(dx) + abs(dy))
            nedge += 1
    # walk the lines of the shorter side of the box (rows, or columns for tall triangles)
    by_rows = (v1 - v0) <= (u1 - u0)
    if by_rows:
        l0, l1, c0, c1 = v0, v1, u0, u1
    else:
        l0, l1, c0, c1 = u0, u1, v0, v1
        for k in range(nedge):
            ea[k], eb[k] = eb[k], ea[k]
    for k in range(nedge):
        inv_a[k] = 1.0 / ea[k] if ea[k] != 0.0 else 0.0
    # every line's span first, edge by edge: loops over contiguous lines that LLVM vectorises (a
    # long thin triangle has many lines and pixel centres on few of them)
    span_lo, span_hi = dtab[6], dtab[7]
    nl = l1 - l0 + 1
    for p in range(nl):
        span_lo[p] = float(c0)
        span_hi[p] = float(c1)
    for k in range(nedge):
        a, b, c, r = ea[k], eb[k], ec[k], inv_a[k]
        if a > 0.0:
            for p in range(nl):
                span_lo[p] = max(span_lo[p], -(b * (l0 + p) + c) * r)
        elif a < 0.0:
            for p in range(nl):
                span_hi[p] = min(span_hi[p], -(b * (l0 + p) + c) * r)
        else:
            for p in range(nl):
                span_hi[p] = -1.0 if b * (l0 + p) + c < 0.0 else span_hi[p]
    # the lines with a pixel centre, in order, listed without a branch per line: whether a line of
    # a thin triangle holds one is a coin flip, and a mispredicted branch costs more than the list
    for p in range(nl):
        span_lo[p] = np.ceil(span_lo[p])
        span_hi[p] = np.floor(span_hi[p])
    lines = dtab[8]
    nh = 0
    for p in range(nl):
        lines[nh] = p
        nh += span_lo[p] <= span_hi[p]
    if nh == 0:
        return 0, 0
    # the reference arithmetic (float32), once per triangle and frame
    ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2 = _setup_at(tv, bv, q, ox32, oy32, oz32, fma)
    won = False
    tests = 0
    for h in range(nh):
        p = int(lines[h])
        ra = int(span_lo[p])
        rb = int(span_hi[p])
        line = l0 + p
        tests += rb - ra + 1
        if by_rows:  # the line's products once, the pixels' from their columns
            b0, b1, b2 = _row(dtab, line)
            for cc in range(ra, rb + 1):
                a0, a1, a2 = _col(dtab, cc)
                dx, dy, dz = _dir_sum(a0, a1, a2, b0, b1, b2, r02, r12, r22)
                won |= _keep(line * width + cc, ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2, dx, dy,
                             dz, ident, zbuf, tid, ties, tie_t, mode, fma)
        else:
            a0, a1, a2 = _col(dtab, line)
            for cc in range(ra, rb + 1):
                b0, b1, b2 = _row(dtab, cc)
                dx, dy, dz = _dir_sum(a0, a1, a2, b0, b1, b2, r02, r12, r22)
                won |= _keep(cc * width + line, ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2, dx, dy,
                             dz, ident, zbuf, tid, ties, tie_t, mode, fma)
    if won and nrm.shape[0] != 0:
        _unit_normal(nx, ny, nz, nrm, ident)
    return 1, tests


# cluster slots: rows of the per-cluster arrays (`_prepare`) and of the per-cluster scratch (`_bounds`)
_F_U, _F_V, _F_M, _F_DIST = 9, 12, 15, 16  # fa: x, y, z of vertex k at rows 3k..3k+2; u, v of the
_F_ROWS = 17                                # three vertices; the rounding bound; the vertex distance
_I_BOX = 1  # ia: the status at row 0, then u0, u1, v0, v1, then the slots that need more than `_bounds`
_I_LIST = 5
_I_ROWS = 6
SKIP, SMALL, TRIANGLE, GENERAL = 0, 1, 2, 3  # what a triangle needs (`_bounds`)


# slot s of a small box w pixels wide (row-major) is column u0 + _SLOT_DU[w, s], row v0 + _SLOT_DV[w, s]
_SLOT_DU = np.array([[s % max(w, 1) for s in range(SMALL_BOX)] for w in range(SMALL_BOX + 1)], np.int64)
_SLOT_DV = np.array([[s // max(w, 1) for s in range(SMALL_BOX)] for w in range(SMALL_BOX + 1)], np.int64)


@numba.njit(inline="always")
def _edge(uk: float, vk: float, ul: float, vl: float, sigma: float, m: float) -> tuple[float, float, float]:
    """The projected edge k -> l as a half-plane a u + b v + c >= 0 towards the inside, pushed out by
    m (|dx| + |dy| >= the edge length): `_raster_polygon`'s half-planes."""
    dx = ul - uk
    dy = vl - vk
    return -sigma * dy, sigma * dx, sigma * (dy * uk - dx * vk) + m * (abs(dx) + abs(dy))


@numba.njit(inline="always")
def _row3(fa: Any, row: int, q: int) -> tuple[float, float, float]:
    """Rows row..row+2 of slot q in a cluster's scratch (`_bounds`)."""
    c = CLUSTER_SIZE
    return fa[row * c + q], fa[(row + 1) * c + q], fa[(row + 2) * c + q]


@numba.njit(inline="always")
def _vertex(fa: Any, k: int, q: int) -> tuple[float, float, float]:
    """Camera-frame vertex k (0-2) of slot q in a cluster's scratch (`_bounds`)."""
    return _row3(fa, 3 * k, q)


@numba.njit(inline="always")
def _project(tv: Any, bv: int, q: int, k: int, ox: float, oy: float, oz: float, r00: float, r01: float,
             r02: float, r10: float, r11: float, r12: float, r20: float, r21: float, r22: float, fx: float,
             fy: float, ppx: float, ppy: float) -> tuple[float, float, float, float, float, float]:
    """Vertex k of slot q of a cluster's vertex block: camera frame (x, y, z), an upper bound of
    its distance (|dx| + |dy| + |dz|) and its projection (u, v)."""
    c = CLUSTER_SIZE
    dx = float(tv[bv + 3 * k * c + q]) - ox
    dy = float(tv[bv + (3 * k + 1) * c + q]) - oy
    dz = float(tv[bv + (3 * k + 2) * c + q]) - oz
    x = r00 * dx + r10 * dy + r20 * dz
    y = r01 * dx + r11 * dy + r21 * dz
    z = r02 * dx + r12 * dy + r22 * dz
    w = 1.0 / z
    return x, y, z, abs(dx) + abs(dy) + abs(dz), fx * x * w + ppx, fy * y * w + ppy


@numba.njit(inline="always")
def _outside(planes_w: Any, lo: Any, hi: Any, ox: float, oy: float, oz: float) -> bool:
    """Whether the box lo..hi lies wholly outside one of the frustum's planes (inward normals
    through the camera centre at ox, oy, oz; 2 px of slack are in the planes)."""
    for p in range(5):
        nwx, nwy, nwz = planes_w[p, 0], planes_w[p, 1], planes_w[p, 2]
        mx = hi[0] if nwx > 0 else lo[0]
        my = hi[1] if nwy > 0 else lo[1]
        mz = hi[2] if nwz > 0 else lo[2]
        if nwx * (mx - ox) + nwy * (my - oy) + nwz * (mz - oz) < -1e-9:
            return True
    return False


@numba.njit(**_KERNEL_OPTIONS)
def _bounds(tv: Any, tn: Any, cl: int, q0: int, q1: int, ox: float, oy: float, oz: float, r00: float,
            r01: float, r02: float, r10: float, r11: float, r12: float, r20: float, r21: float, r22: float,
            fx: float, fy: float, ppx: float, ppy: float, margin_k: float, margin_px: float, wm1: float,
            hm1: float, fa: Any, ia: Any) -> None:
    """For the triangles in slots q0..q1-1 of cluster cl, without branches (LLVM vectorises it):
    their vertices projected, the rounding bound m and the largest vertex distance, and what each
    needs: SKIP (behind the camera, or a box without pixel centres), SMALL (a box of at most
    SMALL_BOX pixel centres, u0 u1 v0 v1), TRIANGLE (in front, a larger box: the edge walk) or
    GENERAL (near its own plane or reaching behind the camera: the rasteriser's general path).

    Why: per triangle this was ~70 cycles of scalar code, a quarter of a frame. It does only what
    every triangle needs: most triangles of a fine mesh have a box without a pixel centre and are
    done here; which of a small box's centres lie near the triangle is asked for the others only
    (`_small_mask`). The cluster's vertices (tv) and normals (tn) and the scratch (fa, ia) are rows
    of CLUSTER_SIZE at constant offsets, so LLVM can check them for overlap as four ranges and
    vectorise."""
    c = CLUSTER_SIZE
    # views from slot q0 on: their indices start at 0 (LLVM then knows them non-negative, with no
    # wraparound test per access, and vectorises); slot q0 + q is the views' q
    tv = tv[cl * (9 * c) + q0:]
    tn = tn[cl * (3 * c) + q0:]
    fa = fa[q0:]
    ia = ia[q0:]
    bv = 0
    for q in range(q1 - q0):
        _, _, za, la, ua, va = _project(tv, bv, q, 0, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21,
                                        r22, fx, fy, ppx, ppy)
        _, _, zb, lb, ub, vb = _project(tv, bv, q, 1, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21,
                                        r22, fx, fy, ppx, ppy)
        _, _, zc, lc, uc, vc = _project(tv, bv, q, 2, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21,
                                        r22, fx, fy, ppx, ppy)
        # rounding bound: Embree's accepted rays lie within m pixels of the exact triangle. h, the
        # camera's distance from the triangle's plane, from the float32 unit normal: each component
        # within 2^-24 of the exact one, so h within 6e-8 of vertex a's |dx| + |dy| + |dz| (la);
        # taken that much smaller (a larger m). h <= 0: m = inf, the general path bounds it
        dxa = ox - float(tv[bv + q])
        dya = oy - float(tv[bv + c + q])
        dza = oz - float(tv[bv + 2 * c + q])
        h = abs(float(tn[q]) * dxa + float(tn[c + q]) * dya + float(tn[2 * c + q]) * dza)
        h = max(h - 1e-7 * la, 0.0)
        dist = max(la, max(lb, lc))
        m = margin_px + margin_k * (dist / h + 1.0)
        zclip = 1e-9 * dist
        front = (za >= zclip) & (zb >= zclip) & (zc >= zclip)
        behind = (za <= 0.0) & (zb <= 0.0) & (zc <= 0.0)
        simple = front & (m <= 0.02)  # else near the plane: m from the edges (general path)
        mb = m if simple else 0.0
        umin = min(ua, min(ub, uc))
        umax = max(ua, max(ub, uc))
        vmin = min(va, min(vb, vc))
        vmax = max(va, max(vb, vc))
        # the box in floats first (clamped: a vertex just in front of the camera projects far out)
        u0 = max(0.0, np.ceil(max(umin, -1e15) - mb))
        u1 = min(wm1, np.floor(min(umax, 1e15) + mb))
        v0 = max(0.0, np.ceil(max(vmin, -1e15) - mb))
        v1 = min(hm1, np.floor(min(vmax, 1e15) + mb))
        empty = (u0 > u1) | (v0 > v1)
        small = (u1 - u0 + 1.0) * (v1 - v0 + 1.0) <= SMALL_BOX
        st = GENERAL
        st = TRIANGLE if simple else st
        st = SMALL if simple & small else st
        st = SKIP if behind | (simple & empty) else st
        ia[q] = st
        ia[_I_BOX * c + q] = int(u0)
        ia[(_I_BOX + 1) * c + q] = int(u1)
        ia[(_I_BOX + 2) * c + q] = int(v0)
        ia[(_I_BOX + 3) * c + q] = int(v1)
        fa[_F_U * c + q] = ua
        fa[(_F_U + 1) * c + q] = ub
        fa[(_F_U + 2) * c + q] = uc
        fa[_F_V * c + q] = va
        fa[(_F_V + 1) * c + q] = vb
        fa[(_F_V + 2) * c + q] = vc
        fa[_F_M * c + q] = m
        fa[_F_DIST * c + q] = dist


@numba.njit(inline="always")
def _small_mask(ua: float, ub: float, uc: float, va: float, vb: float, vc: float, m: float, u0: int, u1: int,
                v0: int, v1: int) -> int:
    """Which pixel centres of a small box (row-major bits, at most SMALL_BOX) lie within the
    projected triangle pushed out by m (the edge walk's half-planes; a projection seen edge-on, or
    with a vertex projected far out, keeps its whole box). Why: about half of a small box's
    centres lie outside, and their reference tests cost ~45 cycles each; asked only for triangles
    whose box holds a centre (`_bounds`)."""
    w = u1 - u0 + 1
    n = w * (v1 - v0 + 1)
    area2 = ((ua * vb - ub * va) + (ub * vc - uc * vb)) + (uc * va - ua * vc)
    scale2 = (((abs(ua * vb) + abs(ub * va)) + (abs(ub * vc) + abs(uc * vb)))
              + (abs(uc * va) + abs(ua * vc)))
    far = max(max(abs(ua), abs(ub)), max(max(abs(uc), abs(va)), max(abs(vb), abs(vc)))) > 1e7
    if far or not (abs(area2) > 1e-9 * scale2):
        return (1 << n) - 1
    sigma = 1.0 if area2 > 0 else -1.0
    a0, b0, c0 = _edge(ua, va, ub, vb, sigma, m)
    a1, b1, c1 = _edge(ub, vb, uc, vc, sigma, m)
    a2, b2, c2 = _edge(uc, vc, ua, va, sigma, m)
    mask = 0
    s = 0
    for v in range(v0, v1 + 1):
        fv = float(v)
        e0 = b0 * fv + c0
        e1 = b1 * fv + c1
        e2 = b2 * fv + c2
        for u in range(u0, u1 + 1):
            fu = float(u)
            d = min(a0 * fu + e0, min(a1 * fu + e1, a2 * fu + e2))
            mask |= int(d >= 0.0) << s
            s += 1
    return mask


@cache
def _render_kernel(mode: int) -> Any:
    """The rasteriser compiled for one arithmetic (a constant, so its branches fold away)."""
    fma = mode in (FMA_RCP, FMA_DIV)

    @numba.njit(**_KERNEL_OPTIONS)
    def _render(tv: Any, tn: Any, cl_start: Any, cl_lo: Any, cl_hi: Any, bl_lo: Any, bl_hi: Any, xs: Any,
                ys: Any, origin: Any, rot: Any, fx: float, fy: float, ppx: float, ppy: float, margin_k: float,
                margin_px: float, zbuf: Any, tid: Any, ties: Any, tie_t: Any, nrm: Any, work: Any, fa: Any,
                ia: Any, dtab: Any, stats: Any) -> None:
        """Rasterise the clustered mesh into zbuf (float32 t, inf = miss) and tid (the triangle's
        rank, its place in the clusters' order; -1 = miss).

        tv, tn: per cluster, its triangles' float32 vertices and unit normals (for the rounding
        bound), in rows of CLUSTER_SIZE slots (`_prepare`); cl_lo, cl_hi:
        the clusters' boxes, bl_lo, bl_hi: their blocks' (BLOCK_SIZE triangles); fa, ia: a
        cluster's scratch (`_bounds`). The rays of pixel (u, v) start at origin (rounded to
        float32) with direction rot @ (xs[u], ys[v], 1)
        (`fill_rays`), xs and ys the pinhole's pixel-centre coordinates (fx, fy, ppx, ppy); rot:
        camera to world. nrm[rank]: the unit normal of every triangle that won a pixel (none
        written when nrm is empty);
        ties[1:ties[0] + 1], tie_t: the pixels where a hit equalled the nearest depth so far, and
        that depth (a tie if it is still the nearest at the end).
        stats += (clusters kept, triangles set up, pixel tests, -, triangles bounded: those of the
        kept clusters' blocks in the frustum, `_bounds`).
        """
        c = CLUSTER_SIZE
        width = xs.shape[0]
        height = ys.shape[0]
        n_pix = width * height
        for i in range(n_pix):
            zbuf[i] = np.inf
            tid[i] = -1
        ties[0] = 0
        ox32, oy32, oz32 = np.float32(origin[0]), np.float32(origin[1]), np.float32(origin[2])
        ox, oy, oz = float(ox32), float(oy32), float(oz32)
        r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
        r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
        r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
        # frustum planes through the camera centre (inward normals, camera frame), 2 px of slack
        slack = 2.0 / min(fx, fy)
        xlo = (0.0 - ppx) / fx - slack
        xhi = (width - 1.0 - ppx) / fx + slack
        ylo = (0.0 - ppy) / fy - slack
        yhi = (height - 1.0 - ppy) / fy + slack
        planes_c = work[0, :15].reshape(5, 3)
        planes_c[0, 0], planes_c[0, 1], planes_c[0, 2] = 1.0, 0.0, -xlo
        planes_c[1, 0], planes_c[1, 1], planes_c[1, 2] = -1.0, 0.0, xhi
        planes_c[2, 0], planes_c[2, 1], planes_c[2, 2] = 0.0, 1.0, -ylo
        planes_c[3, 0], planes_c[3, 1], planes_c[3, 2] = 0.0, -1.0, yhi
        planes_c[4, 0], planes_c[4, 1], planes_c[4, 2] = 0.0, 0.0, 1.0
        planes_w = work[1, :15].reshape(5, 3)
        for p in range(5):
            a, b, cc = planes_c[p, 0], planes_c[p, 1], planes_c[p, 2]
            planes_w[p, 0] = r00 * a + r01 * b + r02 * cc
            planes_w[p, 1] = r10 * a + r11 * b + r12 * cc
            planes_w[p, 2] = r20 * a + r21 * b + r22 * cc
        # per-column and per-row products of the ray directions (see _dir_sum)
        for u in range(width):
            dtab[0, u] = r00 * xs[u]
            dtab[1, u] = r10 * xs[u]
            dtab[2, u] = r20 * xs[u]
        for v in range(height):
            dtab[3, v] = r01 * ys[v]
            dtab[4, v] = r11 * ys[v]
            dtab[5, v] = r21 * ys[v]
        pu, pv = work[8], work[9]
        sc = work[10:16]
        wm1 = width - 1.0
        hm1 = height - 1.0
        kept = 0
        setups = 0
        tests = 0
        bounded = 0
        nb = c // BLOCK_SIZE
        for cl in range(cl_start.shape[0] - 1):
            if _outside(planes_w, cl_lo[cl], cl_hi[cl], ox, oy, oz):
                continue
            kept += 1
            s0 = cl_start[cl]
            bv = cl * (9 * c)
            nt = cl_start[cl + 1] - s0
            # the cluster's blocks in the frustum, as runs of consecutive blocks: a quarter of a
            # kept cluster's triangles lie outside the view, and each would cost the bounds loop
            keep = 0
            for j in range(nb):
                if j * BLOCK_SIZE < nt and not _outside(planes_w, bl_lo[cl, j], bl_hi[cl, j], ox, oy, oz):
                    keep |= 1 << j
            while keep != 0:
                j0 = _cttz(keep)
                j1 = _cttz(~(keep >> j0)) + j0  # the run's end
                keep &= ~((1 << j1) - 1)
                q0 = j0 * BLOCK_SIZE
                q1 = min(nt, j1 * BLOCK_SIZE)
                bounded += q1 - q0
                _bounds(tv, tn, cl, q0, q1, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21, r22, fx,
                        fy, ppx, ppy, margin_k, margin_px, wm1, hm1, fa, ia)
                # the slots that need more, listed without a branch per slot: most triangles of a
                # fine mesh are skipped, whether one is a coin flip, and mispredictions cost more
                todo = ia[_I_LIST * c:(_I_LIST + 1) * c]
                nt_ = 0
                for q in range(q0, q1):
                    todo[nt_] = q
                    nt_ += ia[q] != SKIP
                for h_ in range(nt_):
                    q = todo[h_]
                    st = ia[q]
                    b = _I_BOX * c + q
                    u0, u1, v0, v1 = ia[b], ia[b + c], ia[b + 2 * c], ia[b + 3 * c]
                    m = fa[_F_M * c + q]
                    full = False
                    small = st == SMALL
                    npoly = 3
                    clipped = False
                    if st == GENERAL:
                        for k in range(3):  # the camera-frame vertices, for this rare path only
                            x_, y_, z_, _l, _u, _v = _project(tv, bv, q, k, ox, oy, oz, r00, r01, r02, r10,
                                                              r11, r12, r20, r21, r22, fx, fy, ppx, ppy)
                            fa[3 * k * c + q] = x_
                            fa[(3 * k + 1) * c + q] = y_
                            fa[(3 * k + 2) * c + q] = z_
                        dist = fa[_F_DIST * c + q]
                        if not m <= 0.02:  # near the plane: bound by the distances to its edge lines
                            dmin = np.inf
                            for k in range(3):
                                k2 = k + 1 if k < 2 else 0
                                ax_, ay_, az_ = _vertex(fa, k, q)
                                bx_, by_, bz_ = _vertex(fa, k2, q)
                                cx_ = ay_ * bz_ - az_ * by_
                                cy_ = az_ * bx_ - ax_ * bz_
                                cz_ = ax_ * by_ - ay_ * bx_
                                ex, ey, ez = bx_ - ax_, by_ - ay_, bz_ - az_
                                el = np.sqrt(ex * ex + ey * ey + ez * ez)
                                if el > 0.0:
                                    dmin = min(dmin, np.sqrt(cx_ * cx_ + cy_ * cy_ + cz_ * cz_) / el)
                            full = dmin * 1e5 <= dist
                            m = margin_px + margin_k * (dist / dmin + 1.0) if not full else 0.0
                        zclip = 1e-9 * dist
                        za, zb, zc = fa[2 * c + q], fa[5 * c + q], fa[8 * c + q]
                        if za >= zclip and zb >= zclip and zc >= zclip:
                            if not full:
                                ua, ub, uc = _row3(fa, _F_U, q)
                                va, vb, vc = _row3(fa, _F_V, q)
                                umin = min(ua, min(ub, uc))
                                umax = max(ua, max(ub, uc))
                                vmin = min(va, min(vb, vc))
                                vmax = max(va, max(vb, vc))
                                u0 = max(0, int(np.ceil(max(umin, -1e15) - m)))
                                u1 = min(width - 1, int(np.floor(min(umax, 1e15) + m)))
                                v0 = max(0, int(np.ceil(max(vmin, -1e15) - m)))
                                v1 = min(height - 1, int(np.floor(min(vmax, 1e15) + m)))
                                if u0 > u1 or v0 > v1:
                                    continue
                                small = (u1 - u0 + 1) * (v1 - v0 + 1) <= SMALL_BOX
                        else:  # clip against z = zclip, project what is in front
                            clipped = True
                            npoly = 0
                            for k in range(3):
                                k2 = k + 1 if k < 2 else 0
                                px, py, pz = _vertex(fa, k, q)
                                qx_, qy_, qz_ = _vertex(fa, k2, q)
                                if pz >= zclip:
                                    pu[npoly] = fx * px / pz + ppx
                                    pv[npoly] = fy * py / pz + ppy
                                    npoly += 1
                                if (pz - zclip) * (qz_ - zclip) < 0.0:
                                    f = (zclip - pz) / (qz_ - pz)
                                    pu[npoly] = fx * (px + f * (qx_ - px)) / zclip + ppx
                                    pv[npoly] = fy * (py + f * (qy_ - py)) / zclip + ppy
                                    npoly += 1
                    ident = s0 + q  # the rank: neighbours in space are neighbours in nrm and tid
                    if small:  # test the few pixel centres directly: those `_bounds` found near the triangle
                        # (a general triangle's small box: all of them), in row-major order
                        w = u1 - u0 + 1
                        if st == SMALL:
                            ua, ub, uc = _row3(fa, _F_U, q)
                            va, vb, vc = _row3(fa, _F_V, q)
                            mask = _small_mask(ua, ub, uc, va, vb, vc, m, u0, u1, v0, v1)
                        else:
                            mask = (1 << (w * (v1 - v0 + 1))) - 1
                        if mask == 0:
                            continue
                        ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2 = _setup_at(tv, bv, q, ox32, oy32,
                                                                                       oz32, fma)
                        setups += 1
                        won = False
                        while mask != 0:
                            s = _cttz(mask)
                            mask &= mask - 1
                            u = u0 + _SLOT_DU[w, s]
                            v = v0 + _SLOT_DV[w, s]
                            b0, b1, b2 = _row(dtab, v)
                            a0, a1, a2 = _col(dtab, u)
                            dx, dy, dz = _dir_sum(a0, a1, a2, b0, b1, b2, r02, r12, r22)
                            won |= _keep(v * width + u, ux, uy, uz, wx, wy, wz, qx, qy, qz, nx, ny, nz, t2,
                                         dx, dy, dz, ident, zbuf, tid, ties, tie_t, mode, fma)
                            tests += 1
                        if won and nrm.shape[0] != 0:
                            _unit_normal(nx, ny, nz, nrm, ident)
                        continue
                    if not clipped:
                        pu[0], pu[1], pu[2] = _row3(fa, _F_U, q)
                        pv[0], pv[1], pv[2] = _row3(fa, _F_V, q)
                    up, n = _raster_polygon(pu, pv, npoly, m, full, width, height, tv, bv, q, ox32, oy32,
                                            oz32, ident, dtab, r02, r12, r22, mode, fma, zbuf, tid, ties,
                                            tie_t, nrm, sc)
                    setups += up
                    tests += n
        stats[0] += kept
        stats[1] += setups
        stats[2] += tests
        stats[4] += bounded

    return _render


@numba.njit(cache=True, nogil=True)
def _ranks_to_ids(tid: Any, perm: Any) -> None:
    """The rasteriser's ranks (-1 = miss) to the caller's triangle ids, in place."""
    for i in range(tid.shape[0]):
        k = tid[i]
        if k >= 0:
            tid[i] = perm[k]


@numba.njit(cache=True, nogil=True)
def _gather_normals(tid: Any, nrm: Any, out: Any) -> None:
    for i in range(tid.shape[0]):
        k = tid[i]
        if k < 0:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0
        else:
            out[i, 0] = nrm[k, 0]
            out[i, 1] = nrm[k, 1]
            out[i, 2] = nrm[k, 2]


@numba.njit(cache=True, nogil=True)
def _morton_codes(vx: Any, tri: Any) -> Any:
    """3-D Morton (Z-order) code of each triangle's centroid, 10 bits per axis."""
    m = tri.shape[0]
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    cen = np.empty((m, 3))
    for s in range(m):
        for ax in range(3):
            c = (float(vx[tri[s, 0], ax]) + float(vx[tri[s, 1], ax]) + float(vx[tri[s, 2], ax])) / 3.0
            cen[s, ax] = c
            lo[ax] = min(lo[ax], c)
            hi[ax] = max(hi[ax], c)
    span = max(max(hi[0] - lo[0], hi[1] - lo[1]), max(hi[2] - lo[2], 1e-12))
    code = np.zeros(m, np.int64)
    for s in range(m):
        c = 0
        for ax in range(3):
            q = min(max(int((cen[s, ax] - lo[ax]) / span * 1023.0), 0), 1023)
            for bit in range(10):
                c |= ((q >> bit) & 1) << (3 * bit + ax)
        code[s] = c
    return code


@numba.njit(cache=True, nogil=True)
def _prepare(vx: Any, tri: Any) -> Any:
    """Clusters of CLUSTER_SIZE triangles (in the order given): each cluster's bounding box, those
    of its blocks of BLOCK_SIZE triangles (culled within a kept cluster; an empty block's box stays
    inf..-inf) and, in rows of CLUSTER_SIZE slots, its triangles' vertices (tv: 9 rows, float32)
    and their unit normals (tn: 3 rows, float32, for the rounding bound; `_bounds` allows for their
    rounding)."""
    c = CLUSTER_SIZE
    m = tri.shape[0]
    nc = (m + c - 1) // c
    cl_start = np.empty(nc + 1, np.int64)
    cl_lo = np.full((nc, 3), np.inf)
    cl_hi = np.full((nc, 3), -np.inf)
    nb = c // BLOCK_SIZE
    bl_lo = np.full((nc, nb, 3), np.inf)
    bl_hi = np.full((nc, nb, 3), -np.inf)
    tv = np.zeros(nc * 9 * c, np.float32)
    tn = np.zeros(nc * 3 * c, np.float32)
    for cl in range(nc):
        cl_start[cl] = cl * c
        for s in range(cl * c, min(m, (cl + 1) * c)):
            q = s - cl * c
            for k in range(3):
                v = tri[s, k]
                for ax in range(3):
                    tv[cl * 9 * c + (3 * k + ax) * c + q] = vx[v, ax]
                    cl_lo[cl, ax] = min(cl_lo[cl, ax], float(vx[v, ax]))
                    cl_hi[cl, ax] = max(cl_hi[cl, ax], float(vx[v, ax]))
                    j = q // BLOCK_SIZE
                    bl_lo[cl, j, ax] = min(bl_lo[cl, j, ax], float(vx[v, ax]))
                    bl_hi[cl, j, ax] = max(bl_hi[cl, j, ax], float(vx[v, ax]))
            a, b, d = tri[s, 0], tri[s, 1], tri[s, 2]
            e1x, e1y, e1z = float(vx[b, 0]) - vx[a, 0], float(vx[b, 1]) - vx[a, 1], float(vx[b, 2]) - vx[a, 2]
            e2x, e2y, e2z = float(vx[d, 0]) - vx[a, 0], float(vx[d, 1]) - vx[a, 1], float(vx[d, 2]) - vx[a, 2]
            nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
            nn = np.sqrt(nx * nx + ny * ny + nz * nz)
            if nn > 0.0:
                ux, uy, uz = nx / nn, ny / nn, nz / nn
                base = cl * 3 * c + q
                tn[base], tn[base + c], tn[base + 2 * c] = ux, uy, uz
    cl_start[nc] = m
    return cl_start, cl_lo, cl_hi, bl_lo, bl_hi, tv, tn


class MeshRaster:
    """A triangle mesh prepared for rasterised reference depth (float32 vertices as Embree holds
    them, triangles sorted into clusters with bounding boxes).

    `stats` adds up, over the frames rendered: clusters kept by the frustum test, triangles set
    up, pixel tests, tie pixels ray cast, triangles bounded (those of the kept clusters' blocks in
    the frustum).
    """

    def __init__(self, vertices: NDArray[Any], triangles: NDArray[Any], margin_scale: float = 1.0) -> None:
        vx = np.ascontiguousarray(vertices, dtype=np.float32)
        tri = np.ascontiguousarray(triangles, dtype=np.int32).reshape(-1, 3)
        self.n_triangles = m = len(tri)
        if m and (tri.min() < 0 or tri.max() >= len(vx)):
            raise ValueError("triangle vertex index out of range")
        order = np.argsort(_morton_codes(vx, tri), kind="stable") if m else np.zeros(0, np.int64)
        self.perm = np.ascontiguousarray(order.astype(np.int32))  # rank -> the caller's id
        self.rank = np.empty(m, np.int32)  # the caller's id -> rank
        self.rank[self.perm] = np.arange(m, dtype=np.int32)
        self.cl_start, self.cl_lo, self.cl_hi, self.bl_lo, self.bl_hi, self.tv, self.tn = _prepare(
            vx, np.ascontiguousarray(tri[order]))
        self.margin_scale = float(margin_scale)
        self._ties = _TieCaster(vx, tri)
        self._buffers()

    def _buffers(self) -> None:
        """The per-instance scratch (one instance per thread; the mesh arrays are shared)."""
        self.stats = np.zeros(5, np.int64)
        self._ties_at = np.zeros(1 + TIE_ROOM, np.int64)
        self._ties_t = np.zeros(1 + TIE_ROOM, np.float32)
        # the per-rank normals (12 B per triangle), allocated when a render asks for them
        self._nrm = np.zeros((0, 3), np.float32)
        self._work = np.zeros((16, 16))
        self._fa = np.zeros(_F_ROWS * CLUSTER_SIZE)  # a cluster's scratch (`_bounds`)
        self._ia = np.zeros(_I_ROWS * CLUSTER_SIZE, np.int64)
        self._tab = np.zeros((9, 0))

    def sibling(self) -> MeshRaster:
        """The same prepared mesh (shared, read only) with its own buffers: for another thread."""
        other = copy.copy(self)
        other._buffers()
        return other

    @classmethod
    def from_open3d(cls, mesh: Any, **kw: Any) -> MeshRaster:
        """From a legacy or tensor Open3D TriangleMesh."""
        if hasattr(mesh, "vertex"):  # tensor mesh
            return cls(mesh.vertex.positions.numpy(), mesh.triangle.indices.numpy(), **kw)
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.triangles), **kw)

    def render(self, intr: Intrinsics, cam_to_world: NDArray[Any], t_hit: NDArray[np.float32],
               ids: NDArray[np.int32], normals: NDArray[np.float32] | None = None, *,
               ranks: bool = False, table: bool = True) -> None:
        """Fill t_hit (inf = miss), ids (triangle id in the mesh given, -1 = miss) and, if given,
        normals (unit, float32, 0 on a miss) of the view `cam_to_world` (4x4) for the rays that
        `fill_rays(rays, pose[:3, 3], pose[:3, :3], pixel_rays(intr))` builds: what Open3D's
        `cast_rays` returns for them. Needs a pinhole (no lens distortion).

        `ranks`: ids as the triangles' ranks (`perm[rank]` is the mesh's id), the index of
        `normal_table()`. Why: triangles near in space are near in rank, so a frame's lookups in a
        per-triangle table stay in cache (the mesh's own order may scatter them over 13 MB).

        `table=False` (without `normals`): `normal_table()` is not kept, for a caller with normals of
        its own (the study's float64 planes): no normal computed per winning triangle, and no 12 B
        per triangle held."""
        xs, ys = pinhole_axes(intr)
        want = table or normals is not None
        if want and self._nrm.shape[0] != max(self.n_triangles, 1):
            self._nrm = np.zeros((max(self.n_triangles, 1), 3), np.float32)
        nrm = self._nrm if want else self._nrm[:0]
        f = max(intr.fx, intr.fy)
        x_edge = max(abs(intr.ppx), abs(intr.width - 1 - intr.ppx)) / intr.fx
        y_edge = max(abs(intr.ppy), abs(intr.height - 1 - intr.ppy)) / intr.fy
        stretch = 1.0 + x_edge * x_edge + y_edge * y_edge
        margin_k = 16.0 * float(_ULP) * f * stretch * self.margin_scale
        margin_px = 1e-3 * self.margin_scale
        pose = np.asarray(cam_to_world, dtype=np.float64)
        t_flat, ids_flat = t_hit.reshape(-1), ids.reshape(-1)
        while True:
            counts = np.zeros(5, np.int64)
            _render_kernel(arithmetic())(
                self.tv, self.tn, self.cl_start, self.cl_lo, self.cl_hi, self.bl_lo, self.bl_hi, xs, ys,
                np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]),
                float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy), margin_k, margin_px,
                t_flat, ids_flat, self._ties_at, self._ties_t, nrm, self._work, self._fa, self._ia,
                self._dtab(intr), counts)
            noted = int(self._ties_at[0])
            if noted < self._ties_at.shape[0]:
                break
            # more equal depths than room (e.g. a mesh with duplicated faces): again, with room
            self._ties_at = np.zeros(2 * noted + 1, np.int64)
            self._ties_t = np.zeros(2 * noted + 1, np.float32)
        self.stats += counts
        if normals is not None:
            _gather_normals(ids_flat, self._nrm, normals.reshape(-1, 3))
        at = self._ties_at[1:noted + 1]
        ties = np.unique(at[t_flat[at] == self._ties_t[1:noted + 1]])
        if ties.size:
            self._resolve_ties(ties, intr, pose, t_flat, ids_flat,
                               None if normals is None else normals.reshape(-1, 3))
        if not ranks:
            _ranks_to_ids(ids_flat, self.perm)

    def _resolve_ties(self, ties: NDArray[np.int64], intr: Intrinsics, pose: NDArray[np.float64],
                      t_hit: NDArray[np.float32], ids: NDArray[np.int32],
                      normals: NDArray[np.float32] | None) -> None:
        """Pixels whose ray meets two triangles at the same nearest depth (through a shared edge):
        which one ray casting reports depends on its tree, so those few rays are ray cast."""
        xs, ys = pinhole_axes(intr)  # pixel_rays(intr)[ties] without building all 307 k of them
        dirs = np.ones((ties.size, 3), np.float32)
        dirs[:, 0] = xs[ties % intr.width]
        dirs[:, 1] = ys[ties // intr.width]
        rays = np.empty((ties.size, 6), np.float32)
        fill_rays(rays, np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]), dirs)
        ans = self._ties.cast(rays)
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        won = self.rank[np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), 0)]
        t_hit[ties] = t
        ids[ties] = np.where(hit, won, -1)
        n = ans["primitive_normals"].numpy()
        if self._nrm.shape[0]:  # so that `normal_table()[ranks]` holds for these pixels too
            self._nrm[won[hit]] = n[hit]
        if normals is not None:
            normals[ties] = n
        self.stats[3] += ties.size

    def normal_table(self) -> NDArray[np.float32]:
        """Unit normal per triangle rank, valid for every rank `render(..., ranks=True)` (with
        `table`, the default) put in `ids` in its last frame (what `normals` gathers from): for the
        per-pixel pass, without a per-pixel copy."""
        return self._nrm

    def _dtab(self, intr: Intrinsics) -> NDArray[np.float64]:
        """Per-column and per-row ray products (rows 0-5), a polygon's line spans (6, 7) and its lines
        with a pixel centre (8)."""
        n = max(intr.width, intr.height)
        if self._tab.shape[1] < n:
            self._tab = np.zeros((9, n))
        return self._tab


class _TieCaster:
    """Open3D's scene of the mesh, built when the first tie needs it, shared by siblings."""

    def __init__(self, vx: NDArray[np.float32], tri: NDArray[np.int32]) -> None:
        self.vx: NDArray[np.float32] | None = vx
        self.tri: NDArray[np.int32] | None = tri
        self.scene: Any = None
        self.lock = threading.Lock()

    def cast(self, rays: NDArray[np.float32]) -> Any:
        with self.lock:  # the build, and Open3D's commit on the first cast, are not thread-safe
            if self.scene is None:
                o3d = open3d()
                mesh = o3d.t.geometry.TriangleMesh()
                # the arrays themselves (no copy: 180 MB fewer while Embree builds at 10 M
                # triangles), and let go of once the scene holds the triangles
                mesh.vertex.positions = o3d.core.Tensor.from_numpy(self.vx)
                mesh.triangle.indices = o3d.core.Tensor.from_numpy(self.tri)
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(mesh)
                scene.cast_rays(o3d.core.Tensor(rays[:1]), nthreads=1)
                self.scene = scene
                self.vx = self.tri = None
        return self.scene.cast_rays(open3d().core.Tensor(rays), nthreads=1)


@cache
def _pinhole_axes_cached(intr: Intrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    d = pixel_rays(intr)
    xs = np.ascontiguousarray(d[0, :, 0])
    ys = np.ascontiguousarray(d[:, 0, 1])
    if not (np.array_equal(d[..., 0], np.broadcast_to(xs, d.shape[:2]))
            and np.array_equal(d[..., 1], np.broadcast_to(ys[:, None], d.shape[:2]))
            and np.all(d[..., 2] == 1)):
        raise ValueError("the pixel rays are not a pinhole grid")
    return xs, ys


def pinhole_axes(intr: Intrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Camera-frame x of each column and y of each row of `pixel_rays(intr)` (z = 1)."""
    if intr.has_distortion:
        raise ValueError("the rasteriser needs a pinhole: cast rays for a stream with lens distortion")
    return _pinhole_axes_cached(intr)


def _calibration_scene(seed: int = 7) -> tuple[NDArray[np.float32], NDArray[np.int64], NDArray[np.float32]]:
    """Random triangles at room scale and rays from an off-centre origin that hit them."""
    rng = np.random.default_rng(seed)
    n = 400
    centre = rng.uniform(-3, 3, (n, 1, 3)) + np.array([5.0, -2.0, 1.0])
    vx = (centre + rng.normal(0, 0.2, (n, 3, 3))).reshape(-1, 3).astype(np.float32)
    tri = np.arange(3 * n).reshape(n, 3)
    origin = np.array([0.3, -0.7, 1.4], np.float32)
    bary = rng.dirichlet((1.0, 1.0, 1.0), size=(n, 8))
    pts = np.einsum("nkj,njc->nkc", bary, vx.reshape(n, 3, 3).astype(np.float64)).reshape(-1, 3)
    d = (pts - origin) * rng.uniform(0.2, 3.0, (len(pts), 1))
    rays = np.concatenate([np.broadcast_to(origin, d.shape), d], axis=1).astype(np.float32)
    return vx, tri, rays


@cache
def arithmetic() -> int:
    """The arithmetic variant that reproduces the installed Open3D's ray casting bit for bit on
    this CPU (measured once per process on 3200 rays; the best variant if none is exact)."""
    return _calibrate()[0]


@cache
def _calibrate() -> tuple[int, float]:
    o3d = open3d()
    vx, tri, rays = _calibration_scene()
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(vx)
    mesh.triangle.indices = o3d.core.Tensor(tri.astype(np.int32))
    scene.add_triangles(mesh)
    ans = scene.cast_rays(o3d.core.Tensor(rays), nthreads=1)
    t_ref = ans["t_hit"].numpy()
    ids = ans["primitive_ids"].numpy().astype(np.int64)
    ids[~np.isfinite(t_ref)] = -1
    n_ref = ans["primitive_normals"].numpy()
    hit = ids >= 0
    best, best_share = PLAIN_DIV, -1.0
    for mode in ((FMA_RCP, PLAIN_RCP, FMA_DIV, PLAIN_DIV) if _X86 else (FMA_DIV, PLAIN_DIV)):
        t = np.empty(len(rays), np.float32)
        n = np.zeros((len(rays), 3), np.float32)
        _probe(vx, tri, rays, ids, mode, t, n)
        same = (t[hit] == t_ref[hit]) & np.all(n[hit] == n_ref[hit], axis=1)
        share = float(same.mean()) if same.size else 0.0
        if share > best_share:
            best, best_share = mode, share
        if share == 1.0:
            break
    return best, best_share


def arithmetic_report() -> dict[str, Any]:
    """Which arithmetic the rasteriser uses and whether it reproduced Open3D exactly (result.json)."""
    mode, share = _calibrate()
    return {"arithmetic": ARITHMETIC_NAMES[mode], "bit_exact_share": share}
