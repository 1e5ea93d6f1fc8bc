"""Where the study's renderer stands against ray casting as the mesh grows: per mesh size, the
rasteriser alone (`MeshRaster.render`, one thread) and Open3D's casting alone (all cores), frame by
frame, alternating, in CPU seconds per frame, with the rasteriser's counts per frame (clusters kept,
triangles bounded, set up, pixel tests). Why: the study's cost follows the triangles in view (each
is bounded once per frame), casting's the pixels (and the log of the triangles); the counts say
where the crossover comes from.

Run by hand:  .venv/bin/python benchmarks/bench_scan_sizes.py [--meshes even,uneven]
              [--triangles 0.3,1,3,10] [--frames 12]
Meshes: `bench_scan.sized_mesh` (the benchmark room cut into finer triangles, evenly or patch by patch).
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_scan import make_workload, sized_mesh

from depthstation.core.raster import MeshRaster
from depthstation.evaluate.scan.rasterise import mesh_arrays
from depthstation.evaluate.scan.raycast import MeshCaster


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", default="even,uneven")
    ap.add_argument("--triangles", default="0.3,1,3,10", help="mesh sizes in millions")
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args()
    n = args.frames
    seq = make_workload(32, 32, 640, 480)
    intr = seq.info.depth_intrinsics
    t_buf = np.empty(intr.width * intr.height, np.float32)
    i_buf = np.empty(intr.width * intr.height, np.int32)
    for kind in args.meshes.split(","):
        for size in (float(x) for x in args.triangles.split(",") if x):
            mesh = sized_mesh(size, kind)
            v, f = mesh_arrays(mesh)
            c0 = time.process_time()
            raster = MeshRaster(v, f)
            prep = time.process_time() - c0
            caster = MeshCaster(mesh, intr, 0)
            for pose in seq.poses[:3]:  # compiled kernels, caches
                raster.render(intr, pose, t_buf, i_buf, None, ranks=True)
                caster.cast(pose)
            raster.stats[:] = 0
            rc, cc = [], []
            for k in range(n):
                pose = seq.poses[k % len(seq.poses)]
                c0 = time.process_time()
                raster.render(intr, pose, t_buf, i_buf, None, ranks=True)
                rc.append(time.process_time() - c0)
                c0 = time.process_time()
                caster.cast(pose)
                cc.append(time.process_time() - c0)
            st = raster.stats / n
            pair = float(np.median(np.array(rc) / np.array(cc)))
            print(f"{kind} {len(f) / 1e6:.2f} M triangles: prepared in {prep:.1f} s CPU; rasteriser "
                  f"{np.median(rc) * 1e3:.1f} ms CPU/frame, casting {np.median(cc) * 1e3:.1f} ms CPU/frame "
                  f"(pairwise median {pair:.2f}x); per frame: clusters {st[0]:.0f}, triangles bounded "
                  f"{st[4] / 1e3:.0f} k, set up {st[1] / 1e3:.0f} k, pixel tests {st[2] / 1e3:.0f} k; "
                  f"{np.median(rc) * 1e9 / max(st[4], 1):.1f} ns per bounded triangle", flush=True)
            del raster, caster, mesh
            gc.collect()


if __name__ == "__main__":
    main()
