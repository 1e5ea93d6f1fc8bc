"""Benchmark: the scan study against a cloud's points (`--reference-mode points`) against the same
study on the cloud's Poisson mesh (`--reference-mode mesh`), in one run on one prepared mesh.

Workload: a TLS scan of the synthetic room (standpoints on an azimuth x elevation grid, 1.5 mm range
noise, holes), meshed by Poisson once; then the study of a walk (frames cycled over `--distinct`
rendered 640x480 depth images) in both modes, alternating, `--cycles` times. Reported: the study's
wall and CPU time per mode and their ratio per cycle (goal: points <= 1.5x mesh), and the one-off
cost of fitting the planes against the Poisson meshing itself.

The paper's workload: 1334 frames against a few million points:
    .venv/bin/python benchmarks/bench_point_reference.py --frames 1334 --stations 3 --density 2
A scaled run for a loaded 2-core box (about 0.35 M points, 200 frames):
    .venv/bin/python benchmarks/bench_point_reference.py --frames 200
"""

from __future__ import annotations

import argparse
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

STATIONS = ((1.4, 1.3, 1.6), (4.6, 3.7, 1.5), (4.7, 1.2, 1.4))
HOLES = (((0.0, 2.0, 1.5), 0.35), ((6.0, 1.0, 1.0), 0.3), ((3.0, 5.0, 2.0), 0.4), ((2.0, 4.0, 0.0), 0.3))


def cpu_seconds() -> float:
    a = resource.getrusage(resource.RUSAGE_SELF)
    b = resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def tls_cloud(stations: int, density: float, seed: int = 1) -> np.ndarray:
    """The room as `stations` TLS standpoints see it: 1074 x 345 rays (x density per axis) each."""
    from depthstation.evaluate.scan.synthetic import Room

    room, rng, parts = Room(), np.random.default_rng(seed), []
    n_az, n_el = round(1074 * density), round(345 * density)
    az = np.radians(np.arange(n_az) * 360.0 / n_az)
    el = np.radians(np.linspace(-65.0, 90.0, n_el))
    a, e = np.meshgrid(az, el)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    for origin in STATIONS[:stations]:
        t, _ = room.intersect(np.asarray(origin), d)
        ok = np.isfinite(t)
        parts.append(np.asarray(origin) + (t[ok] + rng.normal(0, 0.0015, ok.sum()))[:, None] * d[ok])
    pts = np.concatenate(parts)
    keep = rng.random(len(pts)) > 0.05
    for c, r in HOLES:
        keep &= np.linalg.norm(pts - np.asarray(c), axis=1) > r
    return np.asarray(pts[keep])


def workload(frames: int, distinct: int, width: int, height: int) -> Any:
    from depthstation.evaluate.scan.synthetic import SyntheticSequence, make_sequence

    base = make_sequence(frames=distinct, width=width, height=height, depth_units_m=0.001, seed=1)
    idx = [k % distinct for k in range(frames)]
    stamps = [base.timestamps_ns[0] + round(k * 1e9 / 30) for k in range(frames)]
    return SyntheticSequence(base.info, [base.depth[i] for i in idx], stamps, base.poses[idx], "bench")


def time_study(seq: Any, mesh_path: Path, config: Any, workers: int, chunk: int) -> dict[str, Any]:
    from depthstation.core.parallel import ChunkRunner
    from depthstation.evaluate.scan.chunks import clear_cache, run_scan_chunks
    from depthstation.evaluate.scan.trajectory import Trajectory

    traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    clear_cache()  # each study reads and prepares its mesh (and fits) as a command does
    c0, t0 = cpu_seconds(), time.perf_counter()
    with ChunkRunner(workers) as runner:
        res = run_scan_chunks(seq, mesh_path, traj, config, runner, chunk_frames=chunk)
    return {"wall": time.perf_counter() - t0, "cpu": cpu_seconds() - c0, "result": res}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--distinct", type=int, default=16)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--stations", type=int, default=1)
    ap.add_argument("--density", type=float, default=1.0, help="rays per axis, times 1074 x 345")
    ap.add_argument("--poisson-depth", type=int, default=9)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--chunk-frames", type=int, default=64)
    ap.add_argument("--cycles", type=int, default=2)
    args = ap.parse_args()

    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.point_reference import POINT_FITS, PointParams, fit_triangles
    from depthstation.evaluate.scan.reference import PoissonParams, reference_mesh, unmeasured_file
    from depthstation.evaluate.scan.study import StudyConfig

    o3d = open3d()
    tmp = Path(tempfile.mkdtemp(prefix="bench_points_"))
    try:
        pts = tls_cloud(args.stations, args.density)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        o3d.io.write_point_cloud(str(tmp / "cloud.ply"), cloud)
        print(f"cloud: {len(pts) / 1e6:.2f} M points ({args.stations} standpoint(s), "
              f"density {args.density:g})")
        t0 = time.perf_counter()
        mesh, mesh_path, info = reference_mesh(tmp / "cloud.ply", tmp / "ref",
                                               PoissonParams(depth=args.poisson_depth))
        t_mesh = time.perf_counter() - t0
        t0 = time.perf_counter()
        fits, fit_info = fit_triangles(np.asarray(mesh.vertices), np.asarray(mesh.triangles), pts,
                                       PointParams())
        t_fit = time.perf_counter() - t0
        fits.save(tmp / "ref" / POINT_FITS)
        print(f"Poisson mesh {len(mesh.triangles) / 1e6:.2f} M triangles in {t_mesh:.1f} s; plane fits in "
              f"{t_fit:.1f} s ({t_fit / t_mesh:.2f}x the meshing); supported {fit_info['supported']} of "
              f"{fit_info['triangles']}, median sigma {1e3 * fit_info['median_sigma_m']:.2f} mm")
        seq = workload(args.frames, args.distinct, args.width, args.height)
        nthreads = 0 if args.workers == 1 else 1
        mesh_cfg = StudyConfig(nthreads=nthreads, renderer="raster",
                               unmeasured=unmeasured_file(mesh_path, info))
        point_cfg = StudyConfig(nthreads=nthreads, renderer="raster", point_fits=tmp / "ref" / POINT_FITS)
        ratios_wall, ratios_cpu = [], []
        for cycle in range(args.cycles):
            a = time_study(seq, mesh_path, mesh_cfg, args.workers, args.chunk_frames)
            b = time_study(seq, mesh_path, point_cfg, args.workers, args.chunk_frames)
            ratios_wall.append(b["wall"] / a["wall"])
            ratios_cpu.append(b["cpu"] / a["cpu"])
            pa, pb = a["result"].summary()["pixels"], b["result"].summary()["pixels"]
            print(f"cycle {cycle + 1}: {args.frames} frames {args.width}x{args.height}: mesh "
                  f"{a['wall']:.1f} s wall / {a['cpu']:.1f} s CPU ({pa['binned']} px binned), points "
                  f"{b['wall']:.1f} s / "
                  f"{b['cpu']:.1f} s ({pb['binned']} px binned, {pb['unmeasured_surface']} left out): "
                  f"{ratios_wall[-1]:.2f}x wall, {ratios_cpu[-1]:.2f}x CPU")
        print(f"points / mesh: median {statistics.median(ratios_wall):.2f}x wall, "
              f"{statistics.median(ratios_cpu):.2f}x CPU over {args.cycles} cycle(s) (goal <= 1.5x)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
