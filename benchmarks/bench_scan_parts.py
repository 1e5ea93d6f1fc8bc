"""The scan study's two per-frame kernels, this tree against another checkout, frame by frame.

Why: on a shared 2-core machine whole-study timings move by 20-50 % with the neighbours' load;
the rasteriser and the per-pixel pass of two versions, run alternately on the same frames in one
process, compare to a few percent (medians of per-frame CPU times). Each also checks that the two
versions agree: the rasteriser bit for bit (depth, triangle, normal), the pass by its cells
(counts equal, largest difference of a cell mean and of M2, frame moments).

A third part, `frame`, times the study's whole per-frame step (`bin_frame` of the rasteriser:
render, ties, the pass) of both trees, with the grid and frame moments they accumulate compared:
the base is imported as a package of its own (a copy of DIR with its imports renamed), so changes
that span modules (the rasteriser's ids and the pass's table) are measured together.

Run by hand (the base: any checkout of the package, e.g. `git archive <commit> | tar -x -C DIR`):
    .venv/bin/python benchmarks/bench_scan_parts.py --base DIR [--frames 64] [--distinct 16]
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import importlib.util
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np


def load_as(name: str, path: Path) -> ModuleType:
    """A module of the base checkout under its own name (its own numba cache beside it)."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {path}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def import_tree(root: Path, tmp: Path) -> str:
    """The package of checkout `root` importable as `base_depthstation` (its files copied, links
    followed, `depthstation` imports renamed); returns the name."""
    name = "base_depthstation"
    dst = tmp / name
    shutil.copytree(root / "depthstation", dst, symlinks=False,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    word = re.compile(r"\bdepthstation\b(?=[. ])")
    for f in dst.rglob("*.py"):
        f.write_text(word.sub(name, f.read_text()))
    sys.path.insert(0, str(tmp))
    importlib.invalidate_caches()
    return name


def median_ms(times: list[float], skip: int = 4) -> float:
    return float(np.median(times[skip:]) * 1e3)


def bench_raster(old: ModuleType, mesh: Any, intr: Any, poses: Any, frames: int) -> None:
    """Both rasterisers over the same poses, alternating which goes first."""
    from depthstation.core import raster as new
    from depthstation.evaluate.scan.rasterise import mesh_arrays

    v, t = mesh_arrays(mesh)
    r_old, r_new = old.MeshRaster(v, t), new.MeshRaster(v, t)
    n = intr.width * intr.height
    bufs = {k: (np.empty(n, np.float32), np.empty(n, np.int32), np.empty((n, 3), np.float32)) for k in "on"}
    times: dict[str, list[float]] = {"o": [], "n": []}
    same = True
    for f in range(frames):
        order = (("o", r_old), ("n", r_new)) if f % 2 else (("n", r_new), ("o", r_old))
        for key, r in order:
            c = time.process_time()
            r.render(intr, poses[f % len(poses)], *bufs[key])
            times[key].append(time.process_time() - c)
        a, b = bufs["o"], bufs["n"]
        same &= all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    print(f"rasteriser: base {median_ms(times['o']):.2f} ms, this tree {median_ms(times['n']):.2f} ms "
          f"CPU/frame (median of {frames}; ratio {median_ms(times['n']) / median_ms(times['o']):.2f}); "
          f"bit-identical {same}")


def bench_pass(old: ModuleType, mesh: Any, intr: Any, poses: Any, depth: Any, frames: int) -> None:
    """Both per-pixel passes over the same rendered frames (rendered once, outside the timing)."""
    from depthstation.core.grid import FrameMoments
    from depthstation.core.raster import fill_rays
    from depthstation.evaluate.scan import raycast as new
    from depthstation.evaluate.scan.rasterise import MeshRasteriser
    from depthstation.evaluate.scan.study import StudyConfig

    r = MeshRasteriser(mesh, intr)
    rendered = []
    for pose in poses:
        t, normals = r.cast(pose)
        rendered.append((t.copy(), normals.copy()))

    class Replay:
        """A renderer that hands back the frame rendered before (the rays filled as the base's
        pass reads them, outside the timing)."""

        cur = 0

        def cast(self, pose: Any) -> Any:
            return rendered[self.cur]

    base_renderer: Any = old.FrameRenderer

    class OldReplay(Replay, base_renderer):  # type: ignore[misc]
        pass

    class NewReplay(Replay, new.FrameRenderer):
        pass

    ro, rn = OldReplay(intr), NewReplay(intr)
    grid = StudyConfig().empty_grid()
    acc = {k: (new.CellAccumulator.for_grid(grid), FrameMoments.zeros(grid.shape), np.zeros(6, np.int64))
           for k in "on"}
    times: dict[str, list[float]] = {"o": [], "n": []}
    for f in range(frames):
        k = f % len(poses)
        pose = poses[k]
        fill_rays(ro.rays, pose[:3, 3].copy(), pose[:3, :3].copy(), ro.dirs)
        order = (("o", ro), ("n", rn)) if f % 2 else (("n", rn), ("o", ro))
        for key, rr in order:
            rr.cur = k
            cells, moments, stats = acc[key]
            c = time.process_time()
            rr.bin_frame(pose, depth[k], 0.001, cells, stats, None, moments)
            times[key].append(time.process_time() - c)
    (co, mo, so), (cn, mn, sn) = acc["o"], acc["n"]
    a, b = co.cells, cn.cells
    hit = a[..., 0] > 0
    dmean = float(np.abs(a[..., 1][hit] - b[..., 1][hit]).max()) if hit.any() else 0.0
    dm2 = float(np.abs(a[..., 2][hit] - b[..., 2][hit]).max()) if hit.any() else 0.0
    print(f"per-pixel pass: base {median_ms(times['o']):.2f} ms, this tree {median_ms(times['n']):.2f} ms "
          f"CPU/frame (ratio {median_ms(times['n']) / median_ms(times['o']):.2f}); counts equal "
          f"{np.array_equal(a[..., 0], b[..., 0])}, pixel counts equal {np.array_equal(so, sn)}, "
          f"max |mean difference| {dmean:.2g} m, max |M2 difference| {dm2:.2g} m^2, frames per cell equal "
          f"{np.array_equal(mo.frames, mn.frames)}")


def bench_frame(base: str, mesh: Any, intr: Any, poses: Any, depth: Any, frames: int) -> None:
    """Both trees' study step per frame (`MeshRasteriser.bin_frame`), alternating which goes first."""
    from depthstation.core.grid import FrameMoments
    from depthstation.evaluate.scan import raycast as new_pass
    from depthstation.evaluate.scan.rasterise import MeshRasteriser
    from depthstation.evaluate.scan.study import StudyConfig

    old = importlib.import_module(f"{base}.evaluate.scan.rasterise")
    old_pass = importlib.import_module(f"{base}.evaluate.scan.raycast")
    old_grid = importlib.import_module(f"{base}.core.grid")
    grid = StudyConfig().empty_grid()
    run: dict[str, Any] = {
        "o": (old.MeshRasteriser(mesh, intr), old_pass.CellAccumulator(grid, np.zeros((*grid.shape, 3))),
              old_grid.FrameMoments.zeros(grid.shape), np.zeros(6, np.int64)),
        "n": (MeshRasteriser(mesh, intr), new_pass.CellAccumulator.for_grid(grid),
              FrameMoments.zeros(grid.shape), np.zeros(6, np.int64))}
    times: dict[str, list[float]] = {"o": [], "n": []}
    for f in range(frames):
        k = f % len(poses)
        for key in ("on" if f % 2 else "no"):
            r, cells, moments, stats = run[key]
            c = time.process_time()
            r.bin_frame(poses[k], depth[k], 0.001, cells, stats, None, moments)
            times[key].append(time.process_time() - c)
    (_, co, mo, so), (_, cn, mn, sn) = run["o"], run["n"]
    same = (np.array_equal(co.cells, cn.cells) and np.array_equal(so, sn)
            and all(np.array_equal(getattr(mo, a), getattr(mn, a))
                    for a in ("frames", "n2", "n2_mean", "n2_mean2")))
    to, tn = median_ms(times["o"]), median_ms(times["n"])
    print(f"study step per frame (render, ties, pass): base {to:.2f} ms, this tree {tn:.2f} ms CPU/frame "
          f"(ratio {tn / to:.3f}); cells, pixel counts and frame moments bit-identical {same}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", type=Path, required=True, help="a checkout holding depthstation/ of the base")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--distinct", type=int, default=16)
    ap.add_argument("--skip", default="", help="raster,pass,frame")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_scan

    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.synthetic import make_sequence

    pkg = args.base / "depthstation"
    _, mesh = bench_scan.build_mesh(8, 100_000)
    tmp = Path(tempfile.mkdtemp(prefix="bench_parts_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # the 28 MB mesh file goes with the run
    mesh_path = tmp / "mesh.ply"
    open3d().io.write_triangle_mesh(str(mesh_path), mesh)
    seq = make_sequence(frames=args.distinct, width=640, height=480, depth_units_m=0.001, seed=1)
    intr = seq.info.depth_intrinsics
    if "raster" not in skip:
        base_raster = load_as("base_raster", pkg / "core" / "raster.py")
        bench_raster(base_raster, mesh_path, intr, seq.poses, args.frames)
    if "pass" not in skip:
        bench_pass(load_as("base_raycast", pkg / "evaluate" / "scan" / "raycast.py"), mesh_path, intr,
                   seq.poses, seq.depth, args.frames)
    if "frame" not in skip:
        bench_frame(import_tree(args.base, tmp), mesh_path, intr, seq.poses, seq.depth, args.frames)


if __name__ == "__main__":
    main()
