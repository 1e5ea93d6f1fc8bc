"""Poisson meshing of a reference cloud: one thread (the default, repeatable) against all cores.

Samples the synthetic room as a TLS-like cloud, orients its normals as the study does, meshes it
`--repeats` times per thread setting (interleaved, so both see the same box) and prints the median
time, the ratio, and whether the repeats gave identical vertices.
Run: .venv/bin/python benchmarks/bench_poisson.py [--points 300000] [--depth 9] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from depthstation.core.lazy_open3d import open3d
from depthstation.evaluate.scan.reference import PoissonParams, orient_normals, poisson_mesh
from depthstation.evaluate.scan.synthetic import Room


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--depth", type=int, default=9)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    o3d = open3d()
    o3d.utility.random.seed(0)
    base = Room().mesh(segments=128).sample_points_uniformly(args.points)
    params = PoissonParams(depth=args.depth)
    base.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.normal_radius_m,
                                                               max_nn=params.normal_max_nn))
    orient_normals(base, viewpoints=np.array([[3.0, 2.5, 1.5]]))
    times: dict[int, list[float]] = {1: [], 0: []}
    verts: dict[int, list[np.ndarray]] = {1: [], 0: []}
    for _ in range(args.repeats):
        for threads in (1, 0):
            t = time.perf_counter()
            mesh, _, _ = poisson_mesh(o3d.geometry.PointCloud(base),
                                   PoissonParams(depth=args.depth, threads=threads))
            times[threads].append(time.perf_counter() - t)
            verts[threads].append(np.asarray(mesh.vertices).copy())
    for threads, label in ((1, "1 thread"), (0, "all cores")):
        same = all(v.shape == verts[threads][0].shape and np.array_equal(v, verts[threads][0])
                   for v in verts[threads])
        print(f"{label:>9}: median {statistics.median(times[threads]):6.2f} s "
              f"({', '.join(f'{t:.2f}' for t in times[threads])}); repeats "
              f"{'identical' if same else 'DIFFER'}")
    print(f"1 thread / all cores: {statistics.median(times[1]) / statistics.median(times[0]):.2f}x "
          f"({args.points} points, depth {args.depth})")


if __name__ == "__main__":
    main()
