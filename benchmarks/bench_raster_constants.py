"""The rasteriser's size constants (CLUSTER_SIZE, SMALL_BOX, BLOCK_SIZE) measured on this CPU.

Why: the constants were set on one CPU and cost 1.3x the CPU per frame on another (clusters of 64
on a 2-vCPU AMD EPYC: the per-cluster bounds loop alone took 7.0 ms per frame at 64 triangles per
cluster, 3.4 ms at 512; benchmarks/HISTORY.md, the scan study). This script makes a copy of
`depthstation/core/raster.py` per setting (its own module and numba cache, in a temporary folder),
renders the benchmark room's frames with each, alternating the order frame by frame, and prints
each setting's median CPU per frame against the first and whether its output is bit-identical to
the first's (depth, triangle, normal): the constants move the cost, never the answer.

Run by hand (a setting is CLUSTER_SIZE:SMALL_BOX[:BLOCK_SIZE], the block size 128 if left out):
    .venv/bin/python benchmarks/bench_raster_constants.py [--settings 1024:16,512:16:64] [--rounds 3]
"""

from __future__ import annotations

import argparse
import atexit
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_scan import build_mesh, make_workload  # noqa: E402
from bench_scan_parts import load_as  # noqa: E402


def variant(folder: Path, cluster: int, small: int, block: int = 128) -> ModuleType:
    """core/raster.py with the constants replaced, imported under its own name."""
    src = (HERE.parent / "depthstation" / "core" / "raster.py").read_text()
    src, n1 = re.subn(r"^CLUSTER_SIZE = \d+", f"CLUSTER_SIZE = {cluster}", src, flags=re.M)
    src, n2 = re.subn(r"^SMALL_BOX = \d+", f"SMALL_BOX = {small}", src, flags=re.M)
    src, n3 = re.subn(r"^BLOCK_SIZE = \d+", f"BLOCK_SIZE = {block}", src, flags=re.M)
    if n1 != 1 or n2 != 1 or n3 != 1:
        raise SystemExit("core/raster.py no longer defines CLUSTER_SIZE, SMALL_BOX and BLOCK_SIZE at "
                         "module level")
    name = f"raster_c{cluster}_s{small}_b{block}"
    path = folder / f"{name}.py"
    path.write_text(src)
    return load_as(name, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--settings", default="1024:16,512:16,2048:16,256:16,1024:16:64,1024:16:256,2048:16:64",
                    help="comma list of CLUSTER_SIZE:SMALL_BOX[:BLOCK_SIZE] (SMALL_BOX <= 16; BLOCK_SIZE "
                         "divides CLUSTER_SIZE into at most 32 blocks; 128 if left out); the first is the "
                         "reference")
    ap.add_argument("--rounds", type=int, default=3, help="passes over the distinct frames")
    ap.add_argument("--distinct", type=int, default=32)
    args = ap.parse_args()
    settings = [tuple(int(x) for x in s.split(":")) for s in args.settings.split(",")]
    if any(not 1 <= s[1] <= 16 for s in settings):
        raise SystemExit("SMALL_BOX must be 1-16: the bounds loop checks 16 pixel centres of a small box")
    for s in settings:
        block = s[2] if len(s) > 2 else 128
        if s[0] % block or s[0] // block > 32:
            raise SystemExit(f"BLOCK_SIZE {block} must divide CLUSTER_SIZE {s[0]} into at most 32 blocks")

    folder = Path(tempfile.mkdtemp(prefix="bench_raster_constants_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    _, mesh = build_mesh(8, 100_000)
    seq = make_workload(args.distinct, args.distinct, 640, 480)
    intr = seq.info.depth_intrinsics
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    rasters: dict[tuple[int, ...], Any] = {s: variant(folder, *s).MeshRaster(v, t) for s in settings}
    n = intr.width * intr.height
    bufs = {s: (np.empty(n, np.float32), np.empty(n, np.int32), np.empty((n, 3), np.float32))
            for s in settings}
    for s, r in rasters.items():  # compile (or load) and warm up
        for pose in seq.poses[:4]:
            r.render(intr, pose, *bufs[s])
    times: dict[tuple[int, ...], list[float]] = {s: [] for s in settings}
    same = dict.fromkeys(settings, True)
    for f in range(args.rounds * len(seq.poses)):
        order = settings if f % 2 == 0 else settings[::-1]
        for s in order:
            c = time.thread_time()
            rasters[s].render(intr, seq.poses[f % len(seq.poses)], *bufs[s])
            times[s].append(time.thread_time() - c)
        ref = bufs[settings[0]]
        for s in settings[1:]:
            same[s] &= all(np.array_equal(x, y) for x, y in zip(ref, bufs[s], strict=True))
    base = np.median(times[settings[0]])
    for s in settings:
        med = float(np.median(times[s]))
        block = s[2] if len(s) > 2 else 128
        print(f"CLUSTER_SIZE {s[0]:5d}, SMALL_BOX {s[1]:3d}, BLOCK_SIZE {block:4d}: {med * 1e3:6.2f} ms "
              f"CPU/frame (median of {len(times[s])}), {med / base:.3f}x the first; bit-identical {same[s]}")


if __name__ == "__main__":
    main()
