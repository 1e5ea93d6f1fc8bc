"""The scan study's result folder: grid.npz, summary.json, the paper's figures, result.json.

The command and a batch item both end here, so they write the same files.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from depthstation.core.grid import GRID_FILE
from depthstation.core.lazy_open3d import open3d
from depthstation.core.results import SUMMARY_FILE, inside, write_json, write_result_info
from depthstation.core.run_warnings import warn
from depthstation.evaluate.scan.chunks import renderer_for
from depthstation.evaluate.scan.figures import frame_figure, grid_figure
from depthstation.evaluate.scan.point_reference import PIXEL_NAMES, REASONS, reference_u_into
from depthstation.evaluate.scan.reference import appearance_image
from depthstation.evaluate.scan.study import ChunkResult, StudyConfig, evaluate_chunk, frame_images

UNMEASURED_PIXELS = 0.01  # of the pixels within the grid's range on unmeasured surface: worth a warning

if TYPE_CHECKING:
    from depthstation.evaluate.scan.run import ScanJob


def _stamp_s(source: Any, index: int) -> float:
    """Time stamp (s) of frame `index` of the sequence."""
    return next(fs.timestamp_ns for fs in source.frames(limit=1, start=index)) * 1e-9


def write_scan(job: ScanJob, result: ChunkResult) -> dict[str, Any]:
    """Grid, figures (Fig. 8, 9, 10), summary.json and result.json of a finished study; the summary."""
    opt, out, source = job.options, job.out, job.source
    t0 = time.perf_counter()
    grid = result.grid
    reference_u_into(grid, result.reference_u)  # a cloud's own uncertainty into each cell's u95
    grid.save(out / GRID_FILE)
    figures: dict[str, str] = {}
    fig_index = (opt.figure_frame if opt.figure_frame is not None
                 else sorted(result.used)[len(result.used) // 2])
    intr = source.info.depth_intrinsics
    stream = f"depth {intr.width}x{intr.height}"
    caster = renderer_for(job.mesh_path, source.info.depth_intrinsics, job.config)
    images = frame_images(caster, source, job.posed, fig_index, opt.tolerance_s)
    if images is None:
        warn(f"frame {fig_index} (--figure-frame) has no pose within {opt.tolerance_s} s or no depth: "
             "Fig. 8 and 9 are left out", str(job.sequence), "figure-frame")
    else:
        frame_cfg = StudyConfig(opt.distance_bin_m, opt.inclination_bin_deg, opt.distance_max_m, 90.0,
                                tolerance_s=opt.tolerance_s, renderer=opt.renderer)
        one = evaluate_chunk(caster, source, job.posed, frame_cfg, fig_index, 1)
        look = job.mesh_info.get("appearance")
        pose = job.posed.match(_stamp_s(source, fig_index), opt.tolerance_s) if look else None
        shown = None
        if pose is not None:
            mesh = open3d().io.read_triangle_mesh(str(job.mesh_path))
            shown = appearance_image(mesh, source.info.depth_intrinsics, pose)
        figures["frame"] = frame_figure(images, out / "fig8_frame.png",
                                        f"Fig. 8: frame {fig_index} of {source.name} ({stream}): "
                                        "measured vs reference", shown, look or "").name
        figures["frame_grid"] = grid_figure(one.grid, out / "fig9_frame_grid.png", opt.min_count_frame,
                                            f"Fig. 9: frame {fig_index} of {source.name} ({stream})").name
    figures["sequence_grid"] = grid_figure(grid, out / "fig10_sequence_grid.png", opt.min_count_sequence,
                                           f"Fig. 10: {source.name} ({stream}, {len(result.used)} frames); "
                                           f"{job.registration.caption()}").name
    unmeasured, in_range = int(result.stats[5]), int(result.stats[4] + result.stats[5])
    if in_range and unmeasured > UNMEASURED_PIXELS * in_range and job.config.point_fits is not None:
        split = ", ".join(f"{r.replace('_', ' ')} {int(result.stats[6 + i])}" for i, r in enumerate(REASONS))
        warn(f"{100 * unmeasured / in_range:.1f} % of the pixels within the grid's range ({unmeasured} of "
             f"{in_range}) saw reference surface the scanned points do not support ({split}; "
             f"summary: pixels.{', pixels.'.join(PIXEL_NAMES)}): left out of the grid, so its cells miss "
             "those distances and inclinations", str(job.reference), "unmeasured-surface")
    elif in_range and unmeasured > UNMEASURED_PIXELS * in_range:
        warn(f"{100 * unmeasured / in_range:.1f} % of the pixels within the grid's range ({unmeasured} of "
             f"{in_range}) saw reference triangles with a vertex more than {1000 * opt.surface_gap_m:.0f} mm "
             "off the scanned surface (surface Poisson made up, and its borders): left out of the grid, so "
             "its cells miss those distances and inclinations (--surface-gap-m 0 keeps them, with the "
             "meshing's error)", str(job.reference), "unmeasured-surface")
    if grid.total == 0:
        warn(f"no pixel was gridded: {result.stats[3]} pixels had depth and a reference hit, of "
             f"{result.stats[0]} in {len(result.used)} frames; check the depth units, the trajectory's "
             "frame and units, and --distance-max-m", str(job.sequence), "no-samples")
    elif not (grid.count >= opt.min_count_sequence).any():
        warn(f"no cell of the grid holds {opt.min_count_sequence} samples (--min-count-sequence): too few "
             "frames for these bins; Fig. 10 draws coarser display cells", str(job.sequence), "sparse-grid")
    job.seconds["figures"] = time.perf_counter() - t0
    reg = job.registration
    summary = {
        "inputs": {"sequence": str(job.sequence), "poses": str(job.poses), "reference": str(job.reference),
                   "similarity": opt.similarity, "pass_points": opt.pass_points},
        "sequence": {"name": source.name, "frame_count": source.frame_count,
                     "intrinsics": source.info.depth_intrinsics.to_dict(),
                     "depth_units_m": source.info.depth_units_m},
        "trajectory": {"poses": len(job.trajectory), "tolerance_s": opt.tolerance_s},
        "reference_mesh": {"path": inside(job.mesh_path, out), **job.mesh_info},
        "registration": reg.to_dict(),
        "registration_caption": reg.caption(),
        "fit_check": None if job.fit is None else job.fit.to_dict(),
        "poses_camera": job.camera,
        "local_shift": (reg.local.to_dict() if reg.local is not None
                        else {"reference_m": [0.0, 0.0, 0.0], "trajectory_m": [0.0, 0.0, 0.0]}),
        "frames": {"used": len(result.used), "skipped_no_pose": len(result.no_pose),
                   "skipped_no_depth": len(result.no_depth), "every": opt.every,
                   "figure_frame": fig_index, "no_pose_indices": result.no_pose[:1000]},
        "pixels": result.summary()["pixels"],
        "grid": {**grid.summary(), "file": GRID_FILE, "shape": list(grid.shape),
                 "distance_bin_m": opt.distance_bin_m, "inclination_bin_deg": opt.inclination_bin_deg,
                 "min_count_frame": opt.min_count_frame, "min_count_sequence": opt.min_count_sequence},
        "figures": figures,
        "chunks": {"count": len(job.chunks), "frames_each": opt.chunk_frames},
        "reference_depth": caster.describe(),
        "timing_s": {**job.seconds, "total": sum(job.seconds.values())},
    }
    write_json(out / SUMMARY_FILE, summary)
    write_result_info(out, "scan", [str(job.sequence), str(job.poses), str(job.reference)], opt.to_dict(),
                      device=dict(source.info.device),
                      extra={"summary": SUMMARY_FILE, "grid": GRID_FILE,
                             "files": [GRID_FILE, SUMMARY_FILE, *figures.values()],
                             "registration": {"scale": reg.scale, "mean_c2c_m": reg.mean_c2c_m}})
    return summary
