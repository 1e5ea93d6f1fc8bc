"""The `evaluate scan` result folder: load, register, cast, bin, write grid/summary/figures/.rrd.

Kept apart from the typer command so tests, the station and notebooks can call it directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.errors import EvaluationError, InputError
from depthstation.viz import RerunTarget
from evaluate.grid import GRID_FILE, Grid
from evaluate.scan.study import PER_FRAME_DIR, ChunkResult, StudyConfig

SUMMARY_FILE = "summary.json"


@dataclass
class ScanOptions:
    """Everything the command line can set besides the four paths."""

    similarity: Path | None = None
    pass_points: Path | None = None
    icp: bool = True
    icp_band_m: tuple[float, float] = (0.5, 2.0)
    icp_every: int = 10
    frames: int | None = None
    every: int = 1
    per_frame_grids: bool = False
    workers: int = 1
    cluster: str | None = None
    chunk_frames: int = 64
    tolerance_s: float = 0.01
    distance_bin_m: float = 0.005
    inclination_bin_deg: float = 0.1
    distance_max_m: float = 6.0
    min_count_frame: int = 10
    min_count_sequence: int = 2000
    figure_frame: int | None = None
    intrinsics: Path | None = None
    poisson_depth: int = 9
    density_quantile: float = 0.05
    target: RerunTarget = field(default_factory=RerunTarget)

    def to_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k != "target"}
        d["rrd"] = self.target.rrd
        return d


def _log_grid(rec: Any, grid: Grid, min_count: int) -> None:
    import rerun as rr

    from evaluate.scan.figures import colorize

    count, mean, std = grid.masked(min_count)
    # rows = inclination (top = 90 deg), columns = distance, as in the PNG heatmaps
    flip = (slice(None, None, -1), slice(None))
    cnt = np.log10(np.ma.filled(count.astype(float), np.nan))
    rec.log("grid/count_log10", rr.Image(colorize(cnt.T[flip], "viridis", 0, max(np.nanmax(cnt), 1))))
    m = mean * 1000
    lim = float(np.percentile(np.abs(m.compressed()), 98)) if m.count() else 1.0
    rec.log("grid/mean_mm", rr.Image(colorize(m.T[flip], "RdBu_r", -lim, lim)))
    s = std * 1000
    smax = float(np.percentile(s.compressed(), 98)) if s.count() else 1.0
    rec.log("grid/std_mm", rr.Image(colorize(s.T[flip], "magma", 0, smax)))


def _log_grid_tensors(rec: Any, grid: Grid, min_count: int) -> None:
    """The final grid as tensors with named dimensions and units (what a reader of the .rrd needs)."""
    from depthstation.viz import send_heatmap

    _, mean, std = grid.masked(min_count)
    edges = (grid.distance_edges_m, grid.inclination_edges_deg)
    send_heatmap(rec, "tensors/count", np.asarray(grid.count, dtype=np.float64), *edges,
                 quantity="samples per cell", unit="1")
    send_heatmap(rec, "tensors/mean_error_m", np.ma.filled(mean.astype(float), np.nan), *edges,
                 quantity=f"mean depth error (cells with >= {min_count} samples)", unit="m")
    send_heatmap(rec, "tensors/std_error_m", np.ma.filled(std.astype(float), np.nan), *edges,
                 quantity=f"std of depth error (cells with >= {min_count} samples)", unit="m")


def run_scan(sequence: Path, poses: Path, reference: Path, out: Path,
             options: ScanOptions | None = None) -> dict[str, Any]:
    """The reference-scan study (paper Section 3.2) into the result folder `out`; returns the summary."""
    from depthstation.progress import progress
    from depthstation.results import write_json, write_result_info
    from depthstation.viz import recording
    from evaluate.scan.figures import frame_figure, grid_figure
    from evaluate.scan.raycast import MeshCaster
    from evaluate.scan.reference import PoissonParams, reference_mesh, sample_reference_points
    from evaluate.scan.registration import read_pass_points, read_similarity, register
    from evaluate.scan.sequence import open_sequence
    from evaluate.scan.study import evaluate_chunk, frame_images, run_study
    from evaluate.scan.trajectory import read_tum

    opt = options or ScanOptions()
    if opt.similarity is not None and opt.pass_points is not None:
        raise InputError(None, "give either --similarity or --pass-points, not both")
    if opt.every < 1 or opt.workers < 1:
        raise InputError(None, "--every and --workers must be at least 1")
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    source = open_sequence(sequence, opt.intrinsics)
    traj = read_tum(poses)
    similarity = read_similarity(opt.similarity) if opt.similarity is not None else None
    pass_points = read_pass_points(opt.pass_points) if opt.pass_points is not None else None
    mesh, mesh_path, mesh_info = reference_mesh(
        reference, out, PoissonParams(depth=opt.poisson_depth, density_quantile=opt.density_quantile))
    t_mesh = time.perf_counter()
    reg = register(source, traj, mesh, sample_reference_points(mesh), similarity=similarity,
                   pass_points=pass_points, icp=opt.icp, band_m=opt.icp_band_m,
                   tolerance_s=opt.tolerance_s, every=opt.icp_every)
    posed = traj.transformed(reg.matrix)
    t_reg = time.perf_counter()

    nthreads = 1 if opt.workers > 1 or opt.cluster is not None else 0
    config = StudyConfig(opt.distance_bin_m, opt.inclination_bin_deg, opt.distance_max_m, 90.0,
                         every=opt.every, max_frames=opt.frames, tolerance_s=opt.tolerance_s,
                         nthreads=nthreads,
                         per_frame_dir=out / PER_FRAME_DIR if opt.per_frame_grids else None)
    n_frames = source.frame_count
    if n_frames is not None and opt.frames is not None:
        n_frames = min(n_frames, opt.frames * opt.every)
    description = ("Reference-scan study (paper Section 3.2): every depth pixel is ray cast against "
                   "the reference mesh; errors (measured - reference z-depth) are binned over "
                   "distance x inclination. `grid/*` shows the growing grid (x: distance, y: "
                   "inclination, top = 90 deg).")
    with recording("depthstation-scan", opt.target, description=description) as rec, \
            progress() as bar:
        task = bar.add_task("scan", total=n_frames, status="")
        done = {"frames": 0}

        def on_frame(index: int, grid: Grid, stats: np.ndarray[Any, Any]) -> None:
            done["frames"] += 1
            bar.update(task, completed=index + 1, status=f"{int(stats[3])} px")
            if rec is not None:
                import rerun as rr

                rec.set_time("frame", sequence=index)
                rec.log("pixels/evaluated", rr.Scalars(float(stats[3])))
                rec.log("pixels/no_depth", rr.Scalars(float(stats[1])))
                rec.log("pixels/no_hit", rr.Scalars(float(stats[2])))

        def on_chunk(k: int, n: int, total: ChunkResult) -> None:
            if opt.workers > 1:
                last = max(total.used) if total.used else 0
                bar.update(task, completed=last + 1, status=f"chunk {k + 1}/{n}")
            if rec is not None:
                last = max(total.used) if total.used else 0
                rec.set_time("frame", sequence=last)
                _log_grid(rec, total.grid, opt.min_count_sequence if k + 1 == n else opt.min_count_frame)

        if opt.cluster is not None:
            # chunks of frames as tasks on a Dask scheduler: each worker reads its own frames
            from evaluate.batch import run_scan as run_on_cluster

            def on_task(done: int, total: int) -> None:
                bar.update(task, completed=round((n_frames or total) * done / max(total, 1)),
                           status=f"chunk {done}/{total}")

            result = run_on_cluster(sequence, mesh_path, posed, config, chunk_frames=opt.chunk_frames,
                                    workers=opt.workers, cluster=opt.cluster,
                                    intrinsics=opt.intrinsics, progress=on_task)
        else:
            result = run_study(sequence if opt.workers > 1 and not _is_object(source) else source,
                               mesh_path, posed, config, workers=opt.workers,
                               chunk_frames=opt.chunk_frames,
                               on_frame=on_frame if opt.workers == 1 else None, on_chunk=on_chunk)
        if rec is not None:
            _log_grid_tensors(rec, result.grid, opt.min_count_sequence)
    t_study = time.perf_counter()
    if not result.used:
        raise EvaluationError(f"no frame could be evaluated ({len(result.no_pose)} frames had no pose "
                              f"within {opt.tolerance_s} s)")

    grid = result.grid
    grid.save(out / GRID_FILE)
    figures: dict[str, str] = {}
    fig_index = (opt.figure_frame if opt.figure_frame is not None
                 else sorted(result.used)[len(result.used) // 2])
    caster = MeshCaster(mesh_path, source.info.depth_intrinsics)
    images = frame_images(caster, source, posed, fig_index, opt.tolerance_s)
    if images is not None:
        frame_cfg = StudyConfig(opt.distance_bin_m, opt.inclination_bin_deg, opt.distance_max_m, 90.0,
                                tolerance_s=opt.tolerance_s)
        one = evaluate_chunk(caster, source, posed, frame_cfg, fig_index, 1)
        figures["frame"] = str(frame_figure(images, out / "fig8_frame.png",
                                            f"frame {fig_index}: measured vs reference"))
        figures["frame_grid"] = str(grid_figure(one.grid, out / "fig9_frame_grid.png", opt.min_count_frame,
                                                f"frame {fig_index}"))
    figures["sequence_grid"] = str(grid_figure(grid, out / "fig10_sequence_grid.png",
                                               opt.min_count_sequence, f"{source.name}: all frames"))
    t_end = time.perf_counter()
    summary = {
        "inputs": {"sequence": str(sequence), "poses": str(poses), "reference": str(reference),
                   "similarity": opt.similarity, "pass_points": opt.pass_points},
        "sequence": {"name": source.name, "frame_count": source.frame_count,
                     "intrinsics": source.info.depth_intrinsics.to_dict(),
                     "depth_units_m": source.info.depth_units_m},
        "trajectory": {"poses": len(traj), "tolerance_s": opt.tolerance_s},
        "reference_mesh": {"path": str(mesh_path), **mesh_info},
        "registration": reg.to_dict(),
        "frames": {"used": len(result.used), "skipped_no_pose": len(result.no_pose),
                   "skipped_no_depth": len(result.no_depth), "every": opt.every,
                   "figure_frame": fig_index, "no_pose_indices": result.no_pose[:1000]},
        "pixels": result.summary()["pixels"],
        "grid": {**grid.summary(), "file": GRID_FILE, "shape": list(grid.shape),
                 "distance_bin_m": opt.distance_bin_m, "inclination_bin_deg": opt.inclination_bin_deg,
                 "min_count_frame": opt.min_count_frame, "min_count_sequence": opt.min_count_sequence},
        "figures": figures,
        "timing_s": {"reference": t_mesh - t0, "registration": t_reg - t_mesh,
                     "study": t_study - t_reg, "figures": t_end - t_study, "total": t_end - t0,
                     "workers": opt.workers},
    }
    write_json(out / SUMMARY_FILE, summary)
    write_result_info(out, "scan", [str(sequence), str(poses), str(reference)], opt.to_dict(),
                      device=dict(source.info.device),
                      extra={"summary": SUMMARY_FILE, "grid": GRID_FILE,
                             "registration": {"scale": reg.scale, "mean_c2c_m": reg.mean_c2c_m}})
    return summary


def _is_object(source: Any) -> bool:
    """True for in-memory sources that pickle by value (a TUM folder reader does)."""
    from evaluate.scan.sequence import TumSequence

    return isinstance(source, TumSequence)
