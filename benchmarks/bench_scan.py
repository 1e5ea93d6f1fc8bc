"""Benchmark of the reference-scan study on the paper's workload (1334 frames of 640x480 against a
mesh of >= 1 M triangles), in one run:

1. Open3D ray casting alone (the reference renderer, both cores, rays prepared),
2. the rasteriser alone (`--renderer raster`, one core per process) and its equality with (1),
3. the whole study with each renderer (2 processes, chunks merged; the grids compared),
4. the nearest-neighbour approach the paper rejected (scipy cKDTree on the reference points).

Goals: whole study <= 0.5 x Open3D's casting alone, >= 15 x faster than nearest
neighbours, memory < 4 GiB. Wall times depend on what else runs on the machine; the CPU seconds
(this process and its workers) and the ratios between runs of the same invocation do much less.

Run by hand:  .venv/bin/python benchmarks/bench_scan.py [--frames 1334] [--distinct 32] [--cycles 3]
By mesh size: .venv/bin/python benchmarks/bench_scan.py --triangles 0.3,1,3,10 [--meshes even,uneven]
(one table: the study against casting alone, memory, nearest neighbour, 1280x720 frame rate;
docs/scan-study.md "By mesh size"; over 50 minutes on a loaded 2-core box with --frames 200).

`--cycles N` then measures N more times, back to back, Open3D's casting alone, the study in one
process and the nearest-neighbour baseline, and prints each cycle's two ratios and their medians:
on a shared box the state moves within minutes (the study's per-pixel pass by up to 60 %), so a
ratio of runs minutes apart says less than one of runs seconds apart.
Frames cycle over `--distinct` rendered depth images and poses (rendering 1334 frames would cost
as much as the study); the per-frame work of the study is the same as for distinct frames.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def build_mesh(subdivide: int, segments: int) -> Any:
    """The synthetic room with subdivided walls and a finely tessellated table (>= 1 M triangles),
    vertices jittered by 1 mm like a Poisson mesh of a TLS cloud."""
    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.synthetic import Room

    o3d = open3d()
    room = Room()
    mesh = room.mesh(segments=segments, subdivide_walls=subdivide)
    v = np.asarray(mesh.vertices)
    rng = np.random.default_rng(0)
    mesh.vertices = o3d.utility.Vector3dVector(v + rng.normal(0, 0.001, v.shape))
    mesh.compute_triangle_normals()
    return room, mesh


def split_triangles(v: Any, f: Any, k: int, first_new: int) -> tuple[Any, Any]:
    """Each triangle of (v, f) cut into k*k congruent ones on a barycentric lattice; the points on an
    edge are shared by the triangles on both sides of it (no cracks). Returns the new vertices
    (numbered from `first_new`) and the new triangles, same orientation as their parent."""
    if k == 1:
        return np.empty((0, 3)), f.copy()
    nf = len(f)
    pairs = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    lo, hi = pairs.min(1), pairs.max(1)
    key, inv = np.unique(lo * (int(f.max()) + 1) + hi, return_inverse=True)
    inv = inv.reshape(nf, 3)
    ea, eb = key // (int(f.max()) + 1), key % (int(f.max()) + 1)
    steps = np.arange(1, k)[None, :, None] / k
    edge_pts = (v[ea][:, None, :] + (v[eb] - v[ea])[:, None, :] * steps).reshape(-1, 3)
    n_edge = len(edge_pts)
    inner = [(i, j) for i in range(1, k) for j in range(1, k) if i + j < k]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    inner_pts = np.stack([a * ((k - i - j) / k) + b * (i / k) + c * (j / k) for i, j in inner], 1) \
        if inner else np.empty((nf, 0, 3))
    lat = np.empty((nf, k + 1, k + 1), np.int64)

    def on_edge(e: int, p: Any, q: Any, s: int) -> Any:
        """Index of the point s/k of the way from p to q on the face's edge e."""
        fwd = p < q
        return first_new + inv[:, e] * (k - 1) + np.where(fwd, s, k - s) - 1

    lat[:, 0, 0], lat[:, k, 0], lat[:, 0, k] = f[:, 0], f[:, 1], f[:, 2]
    for s in range(1, k):
        lat[:, s, 0] = on_edge(0, f[:, 0], f[:, 1], s)          # A -> B
        lat[:, k - s, s] = on_edge(1, f[:, 1], f[:, 2], s)      # B -> C
        lat[:, 0, k - s] = on_edge(2, f[:, 2], f[:, 0], s)      # C -> A
    for m, (i, j) in enumerate(inner):
        lat[:, i, j] = first_new + n_edge + np.arange(nf) * len(inner) + m
    tris = []
    for i in range(k):
        for j in range(k - i):
            tris.append(np.stack([lat[:, i, j], lat[:, i + 1, j], lat[:, i, j + 1]], 1))
            if i + j < k - 1:
                tris.append(np.stack([lat[:, i + 1, j], lat[:, i + 1, j + 1], lat[:, i, j + 1]], 1))
    return np.concatenate([edge_pts, inner_pts.reshape(-1, 3)]), np.concatenate(tris)


def sized_mesh(target_m: float, kind: str) -> Any:
    """The benchmark room at about `target_m` million triangles. 'even': a base room (walls
    subdivided, the table's slivers) with every triangle cut into k*k (the same scene at a finer
    tessellation); 'uneven': a coarser base cut patch by patch into two sizes (2:1 edges, by a
    smooth field over space, as an adaptive surface reconstruction refines where there is detail),
    so triangles of one frame range from several pixels to a fraction of one. New vertices are
    jittered by 0.3 mm (the base by 1 mm), so no two neighbours are coplanar."""
    from depthstation.core.lazy_open3d import open3d

    o3d = open3d()
    if kind == "even":
        options = [(7, 45_000, 1), (8, 100_000, 1), (7, 45_000, 3), (8, 100_000, 3), (8, 100_000, 4)]
        base_n = [(12 * 4**n + 3 * s) * k * k for n, s, k in options]
        n, segs, k = options[int(np.argmin([abs(np.log(b / (target_m * 1e6))) for b in base_n]))]
        _, base = build_mesh(n, segs)
        levels = [(k, np.ones(len(base.triangles), bool))]
    elif kind == "uneven":
        _, base = build_mesh(6, 15_000)
        nb = len(base.triangles)
        m = max(target_m * 1e6 / nb, 1.0)
        ks = [1, 2, 4, 8, 16, 32]
        lo = max(kk for kk in ks if kk * kk <= m)
        hi = 2 * lo
        p = (m - lo * lo) / (hi * hi - lo * lo)
        cen = np.asarray(base.vertices)[np.asarray(base.triangles)].mean(1)
        field = (np.sin(cen[:, 0] * 2.3 + 0.4) + np.sin(cen[:, 1] * 3.1 + 1.3) + np.sin(cen[:, 2] * 4.7)
                 + 0.5 * np.sin((cen[:, 0] + cen[:, 1]) * 7.9))
        fine = field >= np.quantile(field, 1 - p) if p > 0 else np.zeros(nb, bool)
        levels = [(lo, ~fine), (hi, fine)]
    else:
        raise ValueError(f"mesh kind {kind!r} (even, uneven)")
    v = np.asarray(base.vertices)
    f = np.asarray(base.triangles).astype(np.int64)
    verts, faces = [v], []
    rng = np.random.default_rng(1)
    for k, sel in levels:
        if not sel.any():
            continue
        nv = sum(len(x) for x in verts)
        new_v, new_f = split_triangles(v, f[sel], k, nv)
        verts.append(new_v + rng.normal(0, 0.0003, new_v.shape))
        faces.append(new_f)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate(verts)),
                                     o3d.utility.Vector3iVector(np.concatenate(faces).astype(np.int32)))
    mesh.compute_triangle_normals()
    return mesh


def make_workload(frames: int, distinct: int, width: int, height: int) -> Any:
    from depthstation.evaluate.scan.synthetic import SyntheticSequence, make_sequence

    base = make_sequence(frames=distinct, width=width, height=height, depth_units_m=0.001, seed=1)
    idx = [k % distinct for k in range(frames)]
    stamps = [base.timestamps_ns[0] + round(k * 1e9 / 30) for k in range(frames)]
    seq = SyntheticSequence(base.info, [base.depth[i] for i in idx], stamps, base.poses[idx], "bench")
    return seq


def cpu_seconds() -> float:
    """User + system CPU of this process and its reaped children."""
    import resource

    a = resource.getrusage(resource.RUSAGE_SELF)
    b = resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _proc_stats(pid: int) -> tuple[float, float]:
    """(CPU seconds, peak resident GiB) of a live process, from /proc."""
    with Path(f"/proc/{pid}/stat").open() as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    peak = 0.0
    with Path(f"/proc/{pid}/status").open() as f:
        for line in f:
            if line.startswith("VmHWM:"):
                peak = int(line.split()[1]) / 2**20
    return cpu, peak


def time_study(seq: Any, mesh_path: Path, workers: int, renderer: str, chunk: int) -> dict[str, Any]:
    """The whole study (chunks on `workers` processes, merged), from the mesh file as a command
    starts it: wall, CPU and peak memory of this process plus its workers (read before the pool
    closes: forkserver workers are not our children)."""
    from depthstation.core.parallel import ChunkRunner
    from depthstation.evaluate.scan.chunks import clear_cache, run_scan_chunks
    from depthstation.evaluate.scan.study import StudyConfig
    from depthstation.evaluate.scan.trajectory import Trajectory

    traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    config = StudyConfig(nthreads=0 if workers == 1 else 1, renderer=renderer)
    # every timed study reads and prepares its mesh and builds its scene for ties, as a command
    # does: the renderer an earlier study of this process kept would hide ~1 s of that
    clear_cache()
    c0 = cpu_seconds()
    t = time.perf_counter()
    with ChunkRunner(workers) as runner:
        res = run_scan_chunks(seq, mesh_path, traj, config, runner, chunk_frames=chunk)
        wall = time.perf_counter() - t
        pool = getattr(runner, "_pool", None)
        pids = list(getattr(pool, "_processes", {}) or {})
        worker = [_proc_stats(p) for p in pids]
    cpu = cpu_seconds() - c0 + sum(c for c, _ in worker)
    peak = _proc_stats(os.getpid())[1] + sum(m for _, m in worker)
    return {"wall": wall, "cpu": cpu, "peak_gib": peak, "result": res}


def time_renderer(renderer: Any, poses: Any, n: int) -> tuple[float, float]:
    """(wall, CPU) seconds per frame of `renderer.cast` over n poses (one pass over the first 8
    warms up: compiled kernels, and the rasteriser's scene for ties, built once per process)."""
    for pose in poses[:8]:
        renderer.cast(pose)
    t = time.perf_counter()
    c = time.process_time()
    for k in range(n):
        renderer.cast(poses[k % len(poses)])
    return (time.perf_counter() - t) / n, (time.process_time() - c) / n


def compare_renderers(mesh: Any, seq: Any, n: int) -> dict[str, float]:
    """Pixel by pixel, the rasteriser against Open3D's ray casting over n frames."""
    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.rasterise import MeshRasteriser
    from depthstation.evaluate.scan.raycast import MeshCaster

    o3d = open3d()
    intr = seq.info.depth_intrinsics
    caster = MeshCaster(mesh, intr, 0)
    raster = MeshRasteriser(mesh, intr)
    tot = {"pixels": 0, "hit_agree": 0, "both_hit": 0, "t_equal": 0, "triangle_equal": 0, "normal_equal": 0}
    max_dt = 0.0
    for k in range(n):
        pose = seq.poses[k % len(seq.poses)]
        t_r, n_r = raster.cast(pose)
        ids_r = raster._ids.copy()
        caster.cast(pose)
        ans = caster.scene.cast_rays(o3d.core.Tensor.from_numpy(caster.rays), nthreads=0)
        t_c = ans["t_hit"].numpy()
        ids_c = np.where(np.isfinite(t_c), ans["primitive_ids"].numpy().astype(np.int64), -1)
        n_c = ans["primitive_normals"].numpy()
        hit_r, hit_c = ids_r >= 0, ids_c >= 0
        both = hit_r & hit_c
        tot["pixels"] += t_c.size
        tot["hit_agree"] += int(np.sum(hit_r == hit_c))
        tot["both_hit"] += int(both.sum())
        tot["t_equal"] += int(np.sum(t_r[both] == t_c[both]))
        tot["triangle_equal"] += int(np.sum(ids_r[both] == ids_c[both]))
        tot["normal_equal"] += int(np.sum(np.all(n_r[both] == n_c[both], axis=1)))
        if both.any():
            max_dt = max(max_dt, float(np.abs(t_r[both].astype(np.float64) - t_c[both]).max()))
    return {**tot, "max_abs_dt_m": max_dt}


def time_kdtree(seq: Any, mesh: Any, n: int, points: int) -> tuple[float, float, float]:
    """The rejected approach per frame: back-project measured depth, nearest reference point in a
    cKDTree (both cores), reference z and inclination from that point, same Welford grid."""
    from scipy.spatial import cKDTree

    from depthstation.core.grid import Grid
    from depthstation.evaluate.scan.reference import sample_reference_points

    pc = sample_reference_points(mesh, points)
    pc.estimate_normals()
    ref = np.asarray(pc.points)
    nrm = np.asarray(pc.normals)
    t = time.perf_counter()
    tree = cKDTree(ref)
    t_build = time.perf_counter() - t
    intr = seq.info.depth_intrinsics
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    x = ((u - intr.ppx) / intr.fx).ravel()
    y = ((v - intr.ppy) / intr.fy).ravel()
    grid = Grid.empty()
    t = time.perf_counter()
    c0 = cpu_seconds()
    for k in range(n):
        pose = seq.poses[k]
        z = seq.depth[k].ravel() * seq.info.depth_units_m
        ok = z > 0
        pc_cam = np.stack([x[ok] * z[ok], y[ok] * z[ok], z[ok]], -1)
        pw = pc_cam @ pose[:3, :3].T + pose[:3, 3]
        _, idx = tree.query(pw, workers=-1)
        q_cam = (ref[idx] - pose[:3, 3]) @ pose[:3, :3]
        n_cam = nrm[idx] @ pose[:3, :3]
        z_ref = q_cam[:, 2]
        ray = pc_cam / np.linalg.norm(pc_cam, axis=1, keepdims=True)
        inc = np.degrees(np.arccos(np.clip(np.abs((n_cam * ray).sum(1)), 0, 1)))
        grid.add(z_ref, inc, z[ok] - z_ref)
    return (time.perf_counter() - t) / n, t_build, (cpu_seconds() - c0) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1334)
    ap.add_argument("--distinct", type=int, default=32)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--subdivide", type=int, default=8, help="wall subdivisions (12 * 4^n triangles)")
    ap.add_argument("--segments", type=int, default=100_000, help="table segments (3 triangles each)")
    ap.add_argument("--render-frames", type=int, default=40, help="frames for the renderers alone")
    ap.add_argument("--kdtree-frames", type=int, default=20)
    ap.add_argument("--kdtree-points", type=int, default=2_000_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cycles", type=int, default=0,
                    help="then N back-to-back cycles: casting alone, 1-process study, nearest neighbour")
    ap.add_argument("--skip", default="",
                    help="comma list of runs to skip: alone,compare,raster,raster-w1,raycast,kdtree")
    ap.add_argument("--triangles", default="",
                    help="comma list of mesh sizes in millions (e.g. 0.3,1,3,10): the study against casting "
                         "alone, memory and nearest neighbour at each size, as one table (then nothing else)")
    ap.add_argument("--meshes", default="even,uneven", help="with --triangles: mesh kinds (even, uneven)")
    ap.add_argument("--size-cycles", type=int, default=2,
                    help="with --triangles: casting alone and the study, alternating, N times per mesh")
    ap.add_argument("--kdtree-max", type=float, default=1.2,
                    help="with --triangles: nearest neighbour up to this many million triangles")
    ap.add_argument("--hd", default="1,3", help="with --triangles: sizes (millions) with a 1280x720 run")
    ap.add_argument("--hd-frames", type=int, default=64)
    ap.add_argument("--study-child", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    if args.study_child:
        study_child(args)
        return
    if args.triangles:
        run_sizes(args)
        return

    from depthstation.core.lazy_open3d import open3d
    from depthstation.core.raster import arithmetic_report
    from depthstation.evaluate.scan.rasterise import MeshRasteriser
    from depthstation.evaluate.scan.raycast import MeshCaster

    o3d = open3d()
    load = os.getloadavg()
    print(f"cpus available: {len(os.sched_getaffinity(0))}; "
          f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    t = time.perf_counter()
    _, mesh = build_mesh(args.subdivide, args.segments)
    seq = make_workload(args.frames, args.distinct, args.width, args.height)
    tmp = Path(tempfile.mkdtemp(prefix="bench_scan_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # the 28 MB mesh file goes with the run
    mesh_path = tmp / "mesh.ply"
    o3d.io.write_triangle_mesh(str(mesh_path), mesh)
    px = args.width * args.height
    rays = args.frames * px
    print(f"mesh: {len(mesh.triangles):,} triangles; workload: {args.frames} frames of "
          f"{args.width}x{args.height} = {rays / 1e6:.0f} M rays (setup {time.perf_counter() - t:.1f} s); "
          f"rasteriser arithmetic: {arithmetic_report()}")

    # the objects made so far (imports, the mesh, the workload) frozen out of the cyclic garbage
    # collector, as the console script freezes its imports (app/cli.py: main): unfrozen, its
    # full passes took 0.46 s of a 26 s study here, holding the GIL both threads need between frames
    gc.freeze()
    cast_wall = None
    if "alone" not in skip:
        n = args.render_frames
        cw, cc = time_renderer(MeshCaster(mesh, seq.info.depth_intrinsics, 0), seq.poses, n)
        rw, rc = time_renderer(MeshRasteriser(mesh, seq.info.depth_intrinsics), seq.poses, n)
        cast_wall = cw * args.frames
        print(f"Open3D ray casting alone (nthreads=0, {n} frames): {cw * 1000:.1f} ms/frame wall, "
              f"{cc * 1000:.1f} ms CPU -> {cast_wall:.1f} s for the workload ({px / cw / 1e6:.1f} M rays/s)")
        print(f"rasteriser alone (one thread, {n} frames): {rw * 1000:.1f} ms/frame wall, "
              f"{rc * 1000:.1f} ms CPU -> {rw * args.frames / 2:.1f} s for the workload on 2 cores; "
              f"{cc / rc:.2f}x less CPU than ray casting")
    if "compare" not in skip:
        cmp = compare_renderers(mesh, seq, min(args.distinct, 32))
        b = max(cmp["both_hit"], 1)
        print(f"rasteriser vs ray casting, {cmp['pixels']:,} pixels: hit/miss agree "
              f"{cmp['hit_agree'] / cmp['pixels']:.6%}; where both hit: depth bit-equal "
              f"{cmp['t_equal'] / b:.6%} "
              f"(max |dt| {cmp['max_abs_dt_m']:.2g} m), same triangle {cmp['triangle_equal'] / b:.6%}, "
              f"same normal {cmp['normal_equal'] / b:.6%}")
    studies: dict[str, dict[str, Any]] = {}
    runs = [("raster", args.workers), ("raster", 1), ("raycast", args.workers)]
    for renderer, workers in runs:
        key = renderer if workers == args.workers else f"{renderer}-w{workers}"
        if renderer in skip or key in skip:
            continue
        s = time_study(seq, mesh_path, workers, renderer, chunk=64)
        studies[key] = s
        res = s["result"]
        vs = f"; {s['wall'] / cast_wall:.2f}x Open3D's casting alone" if cast_wall else ""
        one = "1 process, a thread per core" if renderer == "raster" else "1 process"
        how = f"{workers} processes" if workers > 1 else one
        print(f"whole study, --renderer {renderer}, {how}: {s['wall']:.1f} s wall "
              f"({args.frames / s['wall']:.1f} frames/s{vs}), CPU {s['cpu']:.1f} s "
              f"(= {s['cpu'] / 2:.1f} s on 2 quiet cores), peak memory {s['peak_gib']:.2f} GiB, "
              f"{res.grid.total:,} samples binned")
    if "raster-w1" in studies and "raster" in studies:
        a, b2 = studies["raster-w1"]["result"].grid, studies["raster"]["result"].grid
        print(f"1 process vs {args.workers} processes: counts equal {np.array_equal(a.count, b2.count)}, "
              f"means within 1e-12 m {bool(np.allclose(a.mean, b2.mean, rtol=0, atol=1e-12))}")
    if "raster" in studies and "raycast" in studies:
        a, b2 = studies["raster"]["result"].grid, studies["raycast"]["result"].grid
        same = np.array_equal(a.count, b2.count)
        both = (a.count > 0) & (b2.count > 0)
        dm = float(np.abs(a.mean[both] - b2.mean[both]).max()) if both.any() else 0.0
        bit = same and np.array_equal(a.mean, b2.mean) and np.array_equal(a.m2, b2.m2)
        ra, rc_ = studies["raster"], studies["raycast"]
        print(f"grids of the two studies: counts equal {same}, max |mean difference| per cell {dm:.3g} m, "
              f"bit-identical {bit}; raster study {rc_['wall'] / ra['wall']:.2f}x faster in wall time, "
              f"{rc_['cpu'] / ra['cpu']:.2f}x less CPU")
    if "kdtree" not in skip:
        raster_runs = [v for k, v in studies.items() if k.startswith("raster")]
        best = min(raster_runs, key=lambda v: v["wall"]) if raster_runs else studies.get("raycast")
        kd, build, kd_cpu = time_kdtree(seq, mesh, args.kdtree_frames, args.kdtree_points)
        if best is not None:
            per_frame = best["wall"] / args.frames
            per_frame_cpu = best["cpu"] / args.frames
            print(f"nearest neighbour (cKDTree, {args.kdtree_points:,} points, build {build:.1f} s): "
                  f"{kd * 1000:.0f} ms/frame wall vs the whole study {per_frame * 1000:.1f} ms/frame -> "
                  f"{kd / per_frame:.1f}x slower ({args.kdtree_frames} frames; whole workload "
                  f"~{kd * args.frames:.0f} s); in CPU {kd_cpu * 1000:.0f} vs "
                  f"{per_frame_cpu * 1000:.1f} ms/frame "
                  f"-> {kd_cpu / per_frame_cpu:.1f}x")
    if args.cycles > 0:
        run_cycles(args, mesh, mesh_path, seq)
    load = os.getloadavg()
    print(f"load average at the end {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")


def run_cycles(args: Any, mesh: Any, mesh_path: Path, seq: Any) -> None:
    """Casting alone, the 1-process study and the nearest-neighbour baseline, back to back, N times:
    the ratios within each cycle and their medians."""
    from depthstation.evaluate.scan.raycast import MeshCaster

    caster = MeshCaster(mesh, seq.info.depth_intrinsics, 0)
    vs_cast, vs_kd = [], []
    for k in range(args.cycles):
        cw, _ = time_renderer(caster, seq.poses, args.render_frames)
        s = time_study(seq, mesh_path, 1, "raster", chunk=64)
        kd, _, _ = time_kdtree(seq, mesh, args.kdtree_frames, args.kdtree_points)
        vs_cast.append(s["wall"] / (cw * args.frames))
        vs_kd.append(kd / (s["wall"] / args.frames))
        print(f"cycle {k + 1}: casting alone {cw * 1000:.1f} ms/frame, study {s['wall']:.1f} s "
              f"(CPU {s['cpu']:.1f} s) = {vs_cast[-1]:.2f}x casting alone; nearest neighbour "
              f"{kd * 1000:.0f} ms/frame = {vs_kd[-1]:.1f}x the study", flush=True)
    print(f"over {args.cycles} cycles: study / casting alone median {np.median(vs_cast):.2f}x "
          f"(range {min(vs_cast):.2f}-{max(vs_cast):.2f}); nearest neighbour / study median "
          f"{np.median(vs_kd):.1f}x (range {min(vs_kd):.1f}-{max(vs_kd):.1f})")


def study_child(args: Any) -> None:
    """One study in a process of its own (`--study-child MESH`), so that its peak memory is the
    study's (this process and its workers) and not the benchmark's meshes and scenes: a JSON line."""
    import json

    seq = make_workload(args.frames, args.distinct, args.width, args.height)
    gc.freeze()
    s = time_study(seq, Path(args.study_child), args.workers, "raster", chunk=64)
    print(json.dumps({"wall": s["wall"], "cpu": s["cpu"], "peak_gib": s["peak_gib"]}))


def child_study(mesh_path: Path, args: Any, workers: int, frames: int, width: int,
                height: int) -> dict[str, float]:
    import json
    import subprocess
    import sys

    cmd = [sys.executable, __file__, "--study-child", str(mesh_path), "--workers", str(workers),
           "--frames", str(frames), "--width", str(width), "--height", str(height),
           "--distinct", str(args.distinct)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return dict(json.loads(out.strip().splitlines()[-1]))


def run_sizes(args: Any) -> None:
    """`--triangles 0.3,1,3,10`: per mesh kind and size, the renderers' equality, casting alone and
    the study (1 process) alternating `--size-cycles` times (the ratio of each pair: the box's state
    moves less within a pair than between runs), the study's peak memory with `--workers` processes
    (in a process of its own), nearest neighbour at the smaller sizes and the 1280x720 frame rate."""
    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.raycast import MeshCaster

    o3d = open3d()
    sizes = [float(x) for x in args.triangles.split(",") if x]
    hd = {float(x) for x in args.hd.split(",") if x}
    load = os.getloadavg()
    print(f"cpus available: {len(os.sched_getaffinity(0))}; "
          f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; "
          f"{args.frames} frames of {args.width}x{args.height} per study, casting alone over "
          f"{args.render_frames} frames, {args.size_cycles} alternating pairs", flush=True)
    seq = make_workload(args.frames, args.distinct, args.width, args.height)
    tmp = Path(tempfile.mkdtemp(prefix="bench_scan_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    rows = []
    for kind in args.meshes.split(","):
        for size in sizes:
            t0 = time.perf_counter()
            mesh = sized_mesh(size, kind)
            mesh_path = tmp / "mesh.ply"
            o3d.io.write_triangle_mesh(str(mesh_path), mesh)
            ntri = len(mesh.triangles)
            took = time.perf_counter() - t0
            print(f"{kind} {ntri / 1e6:.2f} M triangles (built and written in {took:.0f} s)", flush=True)
            cmp = compare_renderers(mesh, seq, 4)
            b = max(cmp["both_hit"], 1)
            equal = min(cmp["hit_agree"] / cmp["pixels"], cmp["t_equal"] / b, cmp["triangle_equal"] / b)
            print(f"  rasteriser vs ray casting over 4 frames: hit/miss, depth and triangle equal on "
                  f"{equal:.6%} of {cmp['pixels']:,} pixels", flush=True)
            caster = MeshCaster(mesh, seq.info.depth_intrinsics, 0)
            ratios, studies, casts = [], [], []
            for _ in range(args.size_cycles):
                cw, _c = time_renderer(caster, seq.poses, args.render_frames)
                s = time_study(seq, mesh_path, 1, "raster", chunk=64)
                casts.append(cw * 1000)
                studies.append(s["wall"] / args.frames * 1000)
                ratios.append(s["wall"] / (cw * args.frames))
                print(f"  casting alone {cw * 1000:.1f} ms/frame, study {studies[-1]:.1f} ms/frame "
                      f"-> {ratios[-1]:.2f}x", flush=True)
            del caster
            gc.collect()
            mem = child_study(mesh_path, args, args.workers, max(args.frames, 128), args.width, args.height)
            print(f"  study with --workers {args.workers}: peak memory {mem['peak_gib']:.2f} GiB", flush=True)
            kd = None
            if ntri <= args.kdtree_max * 1e6:
                kdw, _b, _k = time_kdtree(seq, mesh, args.kdtree_frames, args.kdtree_points)
                kd = kdw * 1000 / float(np.median(studies))
                print(f"  nearest neighbour {kdw * 1000:.0f} ms/frame = {kd:.1f}x the study", flush=True)
            fps = cast_fps = None
            if any(abs(size - h) < 1e-9 for h in hd):
                seq_hd = make_workload(args.hd_frames, args.distinct, 1280, 720)
                caster = MeshCaster(mesh, seq_hd.info.depth_intrinsics, 0)
                cw, _c = time_renderer(caster, seq_hd.poses, min(args.render_frames, args.hd_frames))
                del caster
                s = time_study(seq_hd, mesh_path, 1, "raster", chunk=64)
                fps, cast_fps = args.hd_frames / s["wall"], 1 / cw
                print(f"  1280x720: the study {fps:.1f} frames/s, casting alone {cast_fps:.1f} frames/s "
                      f"(the camera: 30)", flush=True)
            rows.append((kind, ntri, float(np.median(studies)), float(np.median(casts)), ratios,
                         mem["peak_gib"], kd, fps, cast_fps))
            del mesh
            gc.collect()
    load = os.getloadavg()
    print(f"\nload average at the end {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}\n")
    print("| mesh | triangles | study ms/frame | casting alone ms/frame | study / casting (each pair) "
          f"| peak memory, --workers {args.workers} | nearest neighbour / study "
          "| 1280x720 study fps (casting) |")
    print("|---|---|---|---|---|---|---|---|")
    for kind, ntri, st, ca, rs, mem_gib, kd, fps, cfps in rows:
        pairs = ", ".join(f"{r:.2f}" for r in rs)
        print(f"| {kind} | {ntri / 1e6:.2f} M | {st:.1f} | {ca:.1f} | **{np.median(rs):.2f}x** ({pairs}) "
              f"| {mem_gib:.2f} GiB | {'' if kd is None else f'{kd:.1f}x'} "
              f"| {'' if fps is None else f'{fps:.1f} ({cfps:.1f})'} |")


if __name__ == "__main__":
    main()
