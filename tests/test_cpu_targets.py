"""Same result on every CPU: the kernels whose outputs are compared exactly give the same bytes when
numba compiles them for another CPU (docs/conventions.md, "Same result on every CPU").

Why: numba compiles for the CPU it runs on. With fast maths LLVM contracted a * b + c into an FMA
where the CPU has one and reordered sums to its vector width, and the scan pass put a few pixels
near a bin edge in the neighbouring bin on an AVX2 machine without AVX-512. Here the host's
outputs (this process) are compared with those of this module run as a script per target, in a
subprocess with its own numba cache (a cache compiled for one target must not serve another):
Haswell's features (AVX2 and FMA, no AVX-512; the features string emptied, else numba adds the
host's) and generic x86-64 (SSE2, no FMA), the last also with the C library's FMA and AVX2
variants (cos, acos, exp) and numpy's AVX2/AVX-512 loops switched off, as on an older CPU. Each
prints a hash per output; all must be equal.

The cases: grid binning with samples on and next to the bin edges, and a merge; the scan pass
(pinhole and per-pixel rays) over normals within 1e-7 deg of an inclination edge and distances
next to distance edges, with its fold into cells and frame moments; the rasteriser and the pass
behind it over a small mesh (generic only); the checkerboard's moment kernel; the simulator's fused sampler,
dropout and z16 kernels.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

try:  # numpy 2
    from numpy._core import _multiarray_umath
except ImportError:  # pragma: no cover - numpy 1.26
    from numpy.core import _multiarray_umath

# target name -> (environment, cases); NUMBA_CPU_FEATURES="" keeps only the named CPU's features.
# The rasteriser (its compilation ~30 s of CPU) runs on generic only: generic and the host differ in
# both FMA (software there) and vector width; Haswell adds the AVX2 CPU the cheaper cases ran wrong on.
CHEAP = ("grid", "pass", "checkerboard", "simulate")
TARGETS: dict[str, tuple[dict[str, str], tuple[str, ...]]] = {
    "haswell": ({"NUMBA_CPU_NAME": "haswell", "NUMBA_CPU_FEATURES": ""}, CHEAP),
    "generic": ({"NUMBA_CPU_NAME": "generic", "NUMBA_CPU_FEATURES": "",
                 "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-FMA4,-AVX512F",
                 # every loop numpy picks by the CPU (names differ between numpy versions)
                 "NPY_DISABLE_CPU_FEATURES": " ".join(_multiarray_umath.__cpu_dispatch__)},
                (*CHEAP, "raster")),
}


def _digest(*arrays: Any) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _near(edges: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """n values on the edges and up to 3 doubles either side of them."""
    e = rng.choice(edges, n)
    for _ in range(3):
        step = rng.integers(-1, 2, n)
        e = np.where(step > 0, np.nextafter(e, np.inf), np.where(step < 0, np.nextafter(e, -np.inf), e))
    return e


def _grid_case(rng: np.random.Generator) -> dict[str, str]:
    from depthstation.core.grid import Grid

    out = {}
    grids = []
    for _ in range(2):
        g = Grid.empty(0.05, 1.0, 6.0, 90.0)
        n = 20_000
        d = np.concatenate([rng.uniform(-0.1, 6.1, n), _near(g.distance_edges_m, rng, n)])
        a = np.concatenate([_near(g.inclination_edges_deg, rng, n), rng.uniform(-1, 91, n)])
        v = rng.normal(0.01, 0.003, 2 * n)
        g.add(d, a, v)
        grids.append(g)
    out["grid_add"] = _digest(grids[0].count, grids[0].mean, grids[0].m2)
    grids[0].merge(grids[1])
    out["grid_merge"] = _digest(grids[0].count, grids[0].mean, grids[0].m2)
    out["grid_n"] = str(int(grids[0].count.sum()))
    return out


def _rotation(rng: np.random.Generator, angle: float) -> np.ndarray:
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _pass_case(rng: np.random.Generator) -> dict[str, str]:
    """The pass over fixed hits: normals at inclinations within 1e-7 deg of a 0.1 deg edge for 1 %
    of the pixels, reference distances next to the 5 mm distance edges for 10 %."""
    from depthstation.core.camera_model import Intrinsics, pixel_rays
    from depthstation.core.grid import FrameMoments, Grid
    from depthstation.evaluate.scan.raycast import CellAccumulator, FrameRenderer

    class Fixed(FrameRenderer):
        def __init__(self, intr: Intrinsics, t_hit: np.ndarray, normals: np.ndarray) -> None:
            super().__init__(intr)
            self.t_hit, self.normals = t_hit, normals

        def cast(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return self.t_hit, self.normals

    out = {}
    lens = ("brown_conrady", (0.05, -0.02, 0.001, -0.002, 0.0))
    for name, intr in (("pinhole", Intrinsics(97, 61, 71.3, 70.9, 47.2, 31.7)),
                       ("lens", Intrinsics(97, 61, 71.3, 70.9, 47.2, 31.7, *lens))):
        g = Grid.empty()
        cells, frame_cells = CellAccumulator.for_grid(g), CellAccumulator.for_grid(g)
        moments = FrameMoments.zeros(g.shape)
        stats = np.zeros(6, np.int64)
        n = intr.width * intr.height
        dirs = pixel_rays(intr).reshape(-1, 3).astype(np.float64)
        for f in range(3):
            pose = np.eye(4)
            pose[:3, :3] = _rotation(rng, 0.3 + 0.4 * f)
            pose[:3, 3] = rng.uniform(-1, 1, 3)
            world = dirs @ pose[:3, :3].T
            world /= np.linalg.norm(world, axis=1)[:, None]
            on_edge = rng.integers(1, 900, n) / 10 + rng.normal(0, 1e-7, n)
            inc = np.radians(np.where(rng.random(n) < 0.01, on_edge, rng.uniform(0, 90, n)))
            side = np.cross(world, rng.normal(size=(n, 3)))
            side /= np.linalg.norm(side, axis=1)[:, None]
            normals = (np.cos(inc)[:, None] * world + np.sin(inc)[:, None] * side).astype(np.float32)
            t_hit = np.where(rng.random(n) < 0.1, _near(g.distance_edges_m, rng, n),
                             rng.uniform(0.3, 5.9, n)).astype(np.float32)
            t_hit[rng.random(n) < 0.05] = np.inf
            depth = rng.integers(0, 6000, n).astype(np.uint16)
            Fixed(intr, t_hit, normals).bin_frame(pose, depth, 0.001, cells, stats, frame_cells, moments)
        out[f"pass_{name}"] = _digest(cells.cells, frame_cells.cells, stats)
        out[f"pass_{name}_moments"] = _digest(moments.frames, moments.n2, moments.n2_mean, moments.n2_mean2)
        out[f"pass_{name}_binned"] = str(int(stats[4]))
    return out


def _mesh(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A wavy wall 2 m ahead (40 x 30 vertices) and a few loose triangles in front of it."""
    x, y = np.meshgrid(np.linspace(-2, 2, 40), np.linspace(-1.5, 1.5, 30))
    z = 2.0 + 0.2 * np.sin(3 * x) * np.cos(2 * y) + rng.normal(0, 0.01, x.shape)
    v = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    i = np.arange(39)[None, :] + 40 * np.arange(29)[:, None]
    quads = np.stack([i, i + 1, i + 41, i, i + 41, i + 40], axis=-1).reshape(-1, 3)
    loose = rng.uniform([-1, -1, 0.8], [1, 1, 1.6], (60, 3))
    tri = np.concatenate([quads, len(v) + np.arange(60).reshape(-1, 3)])
    return np.concatenate([v, loose]), tri


def _raster_case(rng: np.random.Generator) -> dict[str, str]:
    from depthstation.core.camera_model import Intrinsics
    from depthstation.core.grid import FrameMoments, Grid
    from depthstation.core.raster import MeshRaster
    from depthstation.evaluate.scan.rasterise import MeshRasteriser
    from depthstation.evaluate.scan.raycast import CellAccumulator

    v, tri = _mesh(rng)
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    r = MeshRasteriser(None, intr, MeshRaster(v, tri))
    g = Grid.empty()
    cells, moments, stats = CellAccumulator.for_grid(g), FrameMoments.zeros(g.shape), np.zeros(6, np.int64)
    n = intr.width * intr.height
    out = {}
    for f in range(2):
        pose = np.eye(4)
        pose[:3, :3] = _rotation(rng, 0.1 + 0.05 * f)
        pose[:3, 3] = rng.uniform(-0.2, 0.2, 3)
        t = np.empty(n, np.float32)
        ids = np.empty(n, np.int32)
        nrm = np.empty((n, 3), np.float32)
        r.raster.render(intr, pose, t, ids, nrm)
        out[f"raster_{f}"] = _digest(t, ids, nrm)
        out[f"raster_{f}_hits"] = str(int((ids >= 0).sum()))
        depth = np.where(np.isfinite(t), t * 1000 + rng.normal(0, 5, n), 0).clip(0, 65535).astype(np.uint16)
        r.bin_frame(pose, depth, 0.001, cells, stats, None, moments)
    out["raster_pass"] = _digest(cells.cells, stats, moments.frames, moments.n2, moments.n2_mean,
                                 moments.n2_mean2)
    return out


def _checkerboard_case(rng: np.random.Generator) -> dict[str, str]:
    from depthstation.evaluate.checkerboard.kernels import board_moments

    h, w = 50, 70
    raw = rng.integers(0, 3000, (h, w)).astype(np.uint16)
    inside = rng.random((h, w)) < 0.9
    colour = rng.integers(0, 3, (h, w)).astype(np.uint8)
    rx = np.broadcast_to(((np.arange(w) - 34.6) / 60.1).astype(np.float32), (h, w)).copy()
    ry = np.broadcast_to(((np.arange(h)[:, None] - 24.2) / 60.3).astype(np.float32), (h, w)).copy()
    valid, m = board_moments(raw, inside, colour, rx, ry, 0.001, np.array([0.01, -0.02, 1.5]))
    return {"checkerboard": _digest(np.int64(valid), *(m[k] for k in sorted(m)))}


def _simulate_case(rng: np.random.Generator) -> dict[str, str]:
    from depthstation.simulate.effects.dropout import _exponents, _keep
    from depthstation.simulate.fastpath import _fused
    from depthstation.simulate.view_renderer import _z16

    n = 20_000
    z = rng.uniform(0.3, 8.0, n).astype(np.float32)
    inc = rng.uniform(0, 90, n).astype(np.float32)
    e1, e2, keep = np.empty(n), np.empty(n), np.empty(n)
    _exponents(z, inc, 4.0, 0.8, 75.0, 4.0, e1, e2)
    # `Dropout` takes numpy's exp here, whose float64 loop differs in the last bit with AVX-512
    # (not a kernel's doing); the long double exp has one implementation
    e1, e2 = (np.exp(e.astype(np.longdouble)).astype(np.float64) for e in (e1, e2))
    _keep(z, rng.uniform(-0.1, 1.1, n).astype(np.float32), 38.2, 126.0, 0.3, e1, e2, keep)
    d0 = (38.2 / z).astype(np.float32)
    d0[rng.random(n) < 0.05] = 0
    out_z = np.empty(n, np.float32)
    field, sigma = rng.normal(0, 0.1, n).astype(np.float32), rng.uniform(0.05, 0.2, n).astype(np.float32)
    noise = rng.normal(size=n).astype(np.float32)
    _fused(d0, field, np.float32(0.7), sigma, noise, 38.2, 1 / 32, 1.0, 0.001, keep, rng.random(n), out_z)
    z16 = np.empty(n, np.uint16)
    _z16(out_z, np.float32(1000.0), z16)
    return {"simulate_keep": _digest(keep), "simulate_fused": _digest(out_z), "simulate_z16": _digest(z16)}


def run_cases(names: tuple[str, ...]) -> dict[str, str]:
    """The named cases' hashes (fixed seeds: the inputs are the same in every process), and the CPU
    seconds each took."""
    cases = {"grid": _grid_case, "pass": _pass_case, "raster": _raster_case,
             "checkerboard": _checkerboard_case, "simulate": _simulate_case}
    out: dict[str, str] = {}
    for i, (name, case) in enumerate(cases.items()):
        if name in names:
            t = time.process_time()
            out.update(case(np.random.default_rng(100 + i)))
            out[f"seconds_{name}"] = f"{time.process_time() - t:.1f}"
    return out


def _start(name: str, cache: Path) -> subprocess.Popen[str]:
    """This module as a script under target `name`, with its own numba cache."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("NUMBA_CPU", "NUMBA_CACHE_DIR", "GLIBC_TUNABLES", "NPY_DISABLE"))}
    target_env, cases = TARGETS[name]
    env.update(target_env)
    env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.Popen([sys.executable, __file__, ",".join(cases)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="x86-64 CPU names")
def test_exactly_compared_kernels_give_the_same_bytes_on_every_cpu_target(tmp_path: Path) -> None:
    """The host's hashes (this process: its kernels as the suite compiled them) against each target's,
    compiled afresh in a subprocess (both at once: compiling dominates)."""
    procs = {name: _start(name, tmp_path / f"numba-{name}") for name in TARGETS}
    host = run_cases(tuple({c for _, cases in TARGETS.values() for c in cases}))
    # the cases are not vacuous: most pixels binned, the raster hits the whole view
    assert int(host["pass_pinhole_binned"]) > 3 * 97 * 61 // 2
    assert int(host["raster_0_hits"]) > 80 * 60 // 2
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, f"{name}: {stderr[-3000:]}"
        got = json.loads(stdout.strip().splitlines()[-1])
        keys = [k for k in got if not k.startswith("seconds_")]
        assert keys, f"{name}: no results"
        differ = [k for k in keys if got[k] != host[k]]
        assert not differ, f"{name} differs from the host in {differ}"


if __name__ == "__main__":
    print(json.dumps(run_cases(tuple(sys.argv[1].split(",")))))
