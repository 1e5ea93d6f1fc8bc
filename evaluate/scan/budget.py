"""`evaluate scan --budget`: how much of the grid is the camera (paper 5.2's open question).

The study's grid holds the camera's error plus what the poses (per frame: SLAM drift), the
registration (global: one similarity, e.g. the paper's scale 0.98288) and the reference (a mesh
that is off the scanned surface) add. `pose_refine` estimates per-frame pose corrections jointly
with a smooth sensor field, on subsampled pixels rendered at small size; the corrections are split
into a global similarity (registration) and the rest (poses); surface patches whose error is the
same from every frame and distance are reference defects. The study is then run again with the
corrected poses and without the defect patches: `sensor_grid.npz`. `budget.json` gives, per
0.25 m x 5 deg cell and pooled, each part's mean and spread with a U95 (posterior draws of the
joint problem; frames as clusters), and says what the data could not separate.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.grid import Grid
from depthstation.core.lazy_open3d import open3d
from depthstation.core.parallel import ChunkRunner
from depthstation.core.progress import progress
from depthstation.core.results import write_json
from depthstation.core.run_warnings import warn
from depthstation.evaluate.scan import budget_frames as bf
from depthstation.evaluate.scan import pose_refine as pr
from depthstation.evaluate.scan.chunks import run_scan_chunks
from depthstation.evaluate.scan.reference import load_unmeasured
from depthstation.evaluate.scan.study import ChunkResult
from depthstation.evaluate.scan.trajectory import Trajectory, write_tum

if TYPE_CHECKING:
    from depthstation.evaluate.scan.run import ScanJob

F64 = NDArray[np.float64]
SENSOR_GRID_FILE = "sensor_grid.npz"
BUDGET_FILE = "budget.json"
POSE_CSV = "pose_corrections.csv"
POSE_TUM = "pose_corrections.tum"
BUDGET_FIGURE = "fig_budget.png"
DEFECT_MASK = "budget_excluded_triangles.npy"
COARSE_M = 0.25
COARSE_DEG = 5.0
ITERATIONS = 4         # Gauss-Newton renders: at the given poses, then three times at the corrected ones
DRAWS = 40             # posterior draws for the U95s of the parts
CONFUSION_LIMIT_M = 0.0015  # a cell whose sensor mean moves this much with the poses' uncertainty


class _Clusters:
    """Samples grouped by cell and by (cell, frame): the grouping sorted once, for every part."""

    def __init__(self, cell: NDArray[np.int64], frame: NDArray[np.int64], cells: int, frames: int) -> None:
        self.cell, self.cells = cell, cells
        self.n = np.bincount(cell, minlength=cells).astype(np.float64)
        uk, self.inv = np.unique(cell * frames + frame, return_inverse=True)
        self.nf = np.bincount(self.inv).astype(np.float64)
        self.c = uk // frames
        self.fcount = np.bincount(self.c, minlength=cells).astype(np.float64)

    def stats(self, values: F64) -> tuple[F64, F64, F64, F64]:
        """Per cell: count, mean, std and the frames-as-clusters U95 of the mean."""
        n, cell, cells = self.n, self.cell, self.cells
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.bincount(cell, values, minlength=cells) / n
            ss = np.bincount(cell, values * values, minlength=cells)
            std = np.sqrt(np.maximum(ss / n - mean * mean, 0.0) * n / np.maximum(n - 1, 1))
            mf = np.bincount(self.inv, values) / self.nf
            dev = self.nf * (mf - mean[self.c])
            var = (np.bincount(self.c, dev * dev, minlength=cells) / (n * n)
                   * self.fcount / np.maximum(self.fcount - 1, 1))
            u95 = 1.96 * np.sqrt(var)
        return n, mean, std, u95


def refine_chunks(job: ScanJob, used: list[int], runner: ChunkRunner, step: int) -> list[bf.RefineChunk]:
    """The refinement's frames in chunks of `--chunk-frames` (descriptors: positions, no pixels);
    the first step matches their poses from the trajectory on the worker."""
    opt = job.options
    size = max(1, opt.chunk_frames)
    unmeasured = None if job.config.unmeasured is None else str(job.config.unmeasured)
    return [bf.RefineChunk(str(job.sequence), str(job.mesh_path), unmeasured,
                           None if opt.intrinsics is None else str(opt.intrinsics), opt.topics,
                           tuple(used[s:s + size]), s, step, opt.distance_max_m, None, job.posed,
                           opt.tolerance_s, job.config.nthreads,
                           job.source if runner.in_process else None)
            for s in range(0, len(used), size)]


def refine(job: ScanJob, used: list[int], runner: ChunkRunner) -> dict[str, Any]:
    """The Gauss-Newton iterations of `pose_refine`: each step renders every frame's subsampled
    view at the current poses on the runner (`budget_frames`), then solves here."""
    intr = job.source.info.depth_intrinsics
    step = bf.sample_step(intr)
    chunks = refine_chunks(job, used, runner, step)
    frames = len(used)
    xi = np.zeros((frames, 6))
    given = np.zeros((frames, 4, 4))
    stamps = np.zeros(frames)
    patches = pr.Patches()
    first: list[pr.FrameData | None] = []
    lam = pr.LAMBDAS[len(pr.LAMBDAS) // 2]
    noise = 1.0
    cv: list[dict[str, float]] = []
    sol: pr.Solution | None = None
    steps: list[dict[str, float]] = []  # each Gauss-Newton step's size: the convergence, shown
    with progress() as bar:
        task = bar.add_task("budget: refine", total=ITERATIONS * len(chunks), status="")
        for it in range(ITERATIONS):
            if it == 0:
                todo = chunks
            else:
                current = pr.corrected(given, xi)
                todo = [replace(c, poses=current[c.first:c.first + len(c.positions)], trajectory=None)
                        for c in chunks]
            done = it * len(chunks)

            def advance(d: int, n: int, done: int = done, it: int = it) -> None:
                bar.update(task, completed=done + d, status=f"iteration {it + 1}")

            parts = runner.map(bf.refine_frames, todo, progress=advance)
            data: list[pr.FrameData | None] = [fd for part in parts for fd in part.data]
            if it == 0:
                stamps = np.concatenate([part.stamps for part in parts])
                given = np.concatenate([part.poses for part in parts])
                # the pixels' noise level from the data: then the prior weighs right against them
                noise = pr.solve(pr.trim(data, pr.solve(data, xi, lam)), xi, lam).s2
            data = [None if fd is None else replace(fd, w=fd.w / noise) for fd in data]
            if it == 0:
                first = data
                lam, cv = pr.cross_validate(data, xi)
            use = pr.without_patches(data, patches)
            sol = pr.solve(use, xi, lam)
            use = pr.trim(use, sol)
            sol = pr.solve(use, xi, lam)
            # the surface's own errors, from the errors as measured (gross ones out), at these poses:
            # left out of the next step, and found again at the last one's poses for the budget
            patches = pr.find_patches(data, sol)
            ms = np.mean(sol.dxi ** 2, axis=0)  # RMS over the frames of the vectors' norms
            steps.append({"rotation_rms_deg": float(np.degrees(np.sqrt(ms[:3].sum()))),
                          "translation_rms_m": float(np.sqrt(ms[3:].sum()))})
            if it < ITERATIONS - 1:
                xi = xi + sol.dxi
    assert sol is not None
    xdraws, adraws = pr.draws(sol, xi, count=DRAWS)
    # what the choice of sensor model moves the poses by: the last step with a smaller model
    reduced = pr.solve(use, xi, lam, pr.REDUCED_TERMS)
    xi_reduced = xi + reduced.dxi
    xi = xi + sol.dxi
    return {"step": step, "stamps": stamps, "positions": list(used), "given": given, "xi": xi,
            "a": sol.a, "solution": sol, "lambda": lam, "cv": cv, "first": first, "patches": patches,
            "xdraws": xdraws, "adraws": adraws, "samples": sol.samples,
            "xi_reduced": xi_reduced, "steps": steps}


def _defect_mask(job: ScanJob, patches: pr.Patches, out: Path) -> tuple[Path | None, int]:
    """Per triangle: unmeasured (the study's mask) or on a defect patch; written beside the mesh."""
    if not patches.defect.any():
        return job.config.unmeasured, 0
    mesh = open3d().io.read_triangle_mesh(str(job.mesh_path))
    v = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    cen = v[t].mean(axis=1)
    nrm = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    keys = pr.patch_keys(cen, nrm)
    on = np.isin(keys, patches.keys[patches.defect])
    base = load_unmeasured(job.config.unmeasured, len(t)) if job.config.unmeasured is not None else None
    mask = on if base is None else (on | base)
    path = out / DEFECT_MASK
    np.save(path, mask)
    return path, int(on.sum())


def run_budget(job: ScanJob, result: ChunkResult, runner: ChunkRunner) -> dict[str, Any]:
    """The budget files into the job's folder; returns budget.json's content."""
    t0 = time.perf_counter()
    out = job.out
    opt = job.options
    ref = refine(job, sorted(result.used), runner)
    t_ref = time.perf_counter()
    given, xi = ref["given"], ref["xi"]
    xreg, reg_params = pr.split_registration(given, xi)
    refined = Trajectory(ref["stamps"], pr.corrected(given, xi))
    mask_path, defect_tris = _defect_mask(job, ref["patches"], out)
    config = replace(job.config, unmeasured=mask_path, per_frame_dir=None)
    sensor = run_scan_chunks(job.sequence, job.mesh_path, refined, config, runner,
                             chunk_frames=opt.chunk_frames, intrinsics=opt.intrinsics, topics=opt.topics,
                             source=job.source)
    sensor.grid.save(out / SENSOR_GRID_FILE)
    t_sensor = time.perf_counter()
    parts = attribute(job, result.grid, sensor.grid, ref, xreg)
    poses_file = write_pose_corrections(job, ref, xreg, out)
    shift = np.asarray(job.mesh_info.get("local_shift_m", [0.0, 0.0, 0.0]), dtype=np.float64)
    write_tum(out / POSE_TUM, list(ref["stamps"]), list(refined.translated(shift).poses))
    sol: pr.Solution = ref["solution"]
    cov_a = sol.s2 * sol.s_inv
    cond = sol.s2 * sol.hss_inv
    vif = np.diag(cov_a) / np.diag(cond)
    terms = {name: {"value": float(ref["a"][i]), "u95": float(1.96 * math.sqrt(max(cov_a[i, i], 0.0))),
                    "meaning": pr.SENSOR_MEANING[name], "variance_inflation_by_poses": float(vif[i]),
                    "separated_from_poses": bool(vif[i] < pr.VIF_LIMIT)}
             for i, name in enumerate(pr.SENSOR_TERMS)}
    patches: pr.Patches = ref["patches"]
    limit = np.maximum(pr.DEFECT_MIN_M, pr.DEFECT_U95S * patches.u95_m)
    single = int(np.sum((np.abs(patches.offset_m) > limit) & (patches.z_span_m < pr.DEFECT_Z_SPAN_M)))
    surface = job.mesh_info.get("surface_to_points")
    not_separated = [f"sensor term '{n}' ({t['meaning']}): its variance grows "
                     f"{t['variance_inflation_by_poses']:.0f}x "
                     "once the poses are free (frames that see one surface cannot tell it from a pose "
                     "translation along its normal); its part stays in the poses' U95"
                     for n, t in terms.items() if not t["separated_from_poses"]]
    not_separated.append("a global rigid motion and scale of all poses is not separable from the "
                         "registration: the registration part is defined as the least-squares similarity "
                         "of the corrections (gauge), the poses' part as the rest")
    if single:
        not_separated.append(f"{single} surface patches hold a consistent offset seen only from within "
                             f"{pr.DEFECT_Z_SPAN_M} m of one distance: reference or sensor, the data cannot "
                             "say; left in the sensor grid")
    confused = parts.pop("confused_cells")
    if confused:
        not_separated.append(f"{confused} coarse cells: the sensor mean moves by more than "
                             f"{1000 * CONFUSION_LIMIT_M:g} mm (U95) with the poses' uncertainty "
                             "(cells[].sensor.pose_u95_m)")
    budget = {
        "what": "parts of the study's depth error (grid.npz, given poses) per coarse distance x "
                "inclination cell and pooled: sensor (sensor_grid.npz, corrected poses, defect patches "
                "left out), poses (per-frame corrections less the registration part), registration "
                "(global similarity of the corrections), reference (defect patches); mean_m and std_m "
                "each with u95_m; not_attributed = total - sum of the means",
        "cell_m": COARSE_M, "cell_deg": COARSE_DEG,
        **parts,
        "registration": {"mode": job.registration.mode, "given_scale": job.registration.scale,
                         "correction": reg_params,
                         "meaning": "the corrections' global similarity: the registration's error "
                                    "(rotation, translation, scale about the walk's centroid)"},
        "sensor_model": {"terms": terms, "residual_scale": math.sqrt(sol.s2),
                         "note": "the smooth field that keeps the poses from absorbing the camera's error; "
                                 "the sensor grid itself is measured, not this model"},
        "pose_refinement": {"pixels_per_frame_step": ref["step"], "frames": len(ref["positions"]),
                            "samples": ref["samples"], "iterations": ITERATIONS,
                            "step_rms": ref["steps"],
                            "second_difference_weight": ref["lambda"], "cross_validation": ref["cv"],
                            "prior": {"rotation_deg": math.degrees(pr.SIGMA_ROT_RAD),
                                      "translation_m": pr.SIGMA_TRANS_M, "ridge": pr.RIDGE},
                            "gauge": "registration = least-squares similarity of the corrections; a weak "
                                     "prior of SLAM size on each frame's correction fixes what its view "
                                     "does not; the sensor's constant offset is estimated jointly, its "
                                     "confusion with the poses in its U95",
                            "file": POSE_CSV, "trajectory": POSE_TUM},
        "reference": {"defect_patches": int(patches.defect.sum()), "patch_m": pr.PATCH_M,
                      "excluded_triangles": defect_tris,
                      "patches": defect_list(patches),
                      "mesh_to_cloud": surface,
                      "meaning": "patches whose point-to-plane error is the same from every frame and "
                                 "distance: the mesh is off there; left out of the sensor grid"},
        "not_separated": not_separated,
        "files": {"sensor_grid": SENSOR_GRID_FILE, "pose_corrections": [POSE_CSV, poses_file],
                  "figure": BUDGET_FIGURE},
        "timing_s": {"refine": t_ref - t0, "sensor_pass": t_sensor - t_ref},
    }
    budget_figure(budget, out / BUDGET_FIGURE, job)
    budget["timing_s"]["total"] = time.perf_counter() - t0
    budget = _plain(budget)
    write_json(out / BUDGET_FILE, budget)
    return budget


def _plain(obj: Any) -> Any:
    """Plain JSON values: numpy scalars as Python ones, NaN and inf (an empty part) as null."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def defect_list(patches: pr.Patches) -> list[dict[str, Any]]:
    """The defect patches: where (the patch's centre in the local reference frame, its normal's
    axis), the offset along the normal, its U95, the frames and the distance span it was seen over."""
    centres, axes = pr.patch_centres(patches.keys)
    return [{"centre_m": centres[i].tolist(), "normal_axis": "xyz"[int(axes[i])],
             "offset_m": float(patches.offset_m[i]), "u95_m": float(patches.u95_m[i]),
             "frames": int(patches.frames[i]), "z_span_m": float(patches.z_span_m[i])}
            for i in np.flatnonzero(patches.defect)]


def attribute(job: ScanJob, total_grid: Grid, sensor_grid: Grid, ref: dict[str, Any],
              xreg: F64) -> dict[str, Any]:
    """Per coarse cell and pooled: each part's mean, spread and U95 over the samples at the given
    poses (the grid's own binning), the sensor's from the sensor grid."""
    first: list[pr.FrameData | None] = ref["first"]
    xi, xdraws = ref["xi"], ref["xdraws"]
    patches: pr.Patches = ref["patches"]
    given = ref["given"]
    nd = math.ceil(job.options.distance_max_m / COARSE_M - 1e-9)
    ni = math.ceil(90.0 / COARSE_DEG - 1e-9)
    cols = ("e", "pose", "reg", "refr", "cell", "frame")
    parts: dict[str, list[F64]] = {k: [] for k in cols}
    frames_of: list[int] = []
    for f, fd in enumerate(first):
        if fd is None:
            continue
        frames_of.append(f)
        gx = fd.g.astype(np.float64)
        parts["e"].append(fd.e)
        parts["pose"].append(gx @ (xi[f] - xreg[f]))
        parts["reg"].append(gx @ xreg[f])
        parts["refr"].append(patches.lookup(fd.key) / fd.c)
        kz = np.minimum((fd.z / COARSE_M).astype(np.int64), nd - 1)
        jt = np.minimum((fd.theta / COARSE_DEG).astype(np.int64), ni - 1)
        parts["cell"].append((kz * ni + jt).astype(np.float64))
        parts["frame"].append(np.full(fd.n, float(f)))
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    cell = cat["cell"].astype(np.int64)
    frame = cat["frame"].astype(np.int64)
    frames = len(first)
    cells = nd * ni
    n_cell = np.bincount(cell, minlength=cells).astype(np.float64)
    # the parts are linear in the corrections: with the pixels' g summed per (cell, frame), a set of
    # corrections' cell means is one product, not a pass over every pixel (40 draws, two models)
    upair, pinv = np.unique(cell * frames + frame, return_inverse=True)
    gcat = np.concatenate([fd.g for fd in first if fd is not None])
    gsum = np.stack([np.bincount(pinv, gcat[:, j], minlength=upair.size) for j in range(6)], axis=1)
    del gcat
    pcell, pframe = upair // frames, upair % frames
    total_n = float(cell.size)

    def means(x: F64) -> F64:
        """Cell means (and the pooled one, last) of g . x_f over the refinement's pixels."""
        v = np.einsum("pj,pj->p", gsum, x[pframe])
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.append(np.bincount(pcell, v, minlength=cells) / n_cell, v.sum() / total_n)

    def pose_reg(x: F64, xr: F64) -> F64:
        """(pose, registration, both) x (cells + pooled) of corrections x with registration part xr."""
        mp, mr = means(x - xr), means(xr)
        return np.stack([mp, mr, mp + mr])

    # posterior draws: the pose and registration parts' cell means under each draw
    drawn = np.stack([pose_reg(xd, pr.split_registration(given, xd)[0]) for xd in xdraws])
    draw_pose, draw_reg, draw_both = drawn[:, 0], drawn[:, 1], drawn[:, 2]
    # the sensor model's share: the parts' cell means with the poses of the smaller model
    xi_red = ref["xi_reduced"]
    model = [pose_reg(xi, xreg), pose_reg(xi_red, pr.split_registration(given, xi_red)[0])]
    shift = np.abs(model[0] - model[1])  # (pose, registration, both) x (cells + pooled)
    # and the cell means' sampling (the refinement's pixels, frames as clusters)
    by_cell = _Clusters(cell, frame, cells, frames)
    by_all = _Clusters(np.zeros_like(cell), frame, 1, frames)
    samp = [np.append(by_cell.stats(v)[3], by_all.stats(v)[3]) for v in (cat["pose"], cat["reg"])]
    with np.errstate(invalid="ignore"):
        u_pose = np.sqrt((1.96 * np.std(draw_pose, axis=0)) ** 2 + shift[0] ** 2 + samp[0] ** 2)
        u_reg = np.sqrt((1.96 * np.std(draw_reg, axis=0)) ** 2 + shift[1] ** 2 + samp[1] ** 2)
        # what moves the sensor grid: the corrected poses' uncertainty, not the parts' sampling
        u_both = np.sqrt((1.96 * np.std(draw_both, axis=0)) ** 2 + shift[2] ** 2)

    rest = cat["e"] - cat["pose"] - cat["reg"] - cat["refr"]
    tot, pose, reg, refr, sens_res = (by_cell.stats(v) for v in (cat["e"], cat["pose"], cat["reg"],
                                                                   cat["refr"], rest))
    ptot, ppose, preg, prefr, psens = (by_all.stats(v) for v in (cat["e"], cat["pose"], cat["reg"],
                                                                   cat["refr"], rest))
    factors = _factors(total_grid)
    tg = total_grid.coarsened(*factors) if factors else None
    sg = sensor_grid.coarsened(*factors) if factors else None
    out_cells: list[dict[str, Any]] = []
    confused = 0
    empty = np.zeros((nd, ni))
    t_count, t_mean, t_std = ((tg.count, tg.mean_m, tg.std) if tg is not None and tg.shape == (nd, ni)
                              else (empty, empty, empty))
    s_count, s_mean, s_std = ((sg.count, sg.mean_m, sg.std) if sg is not None and sg.shape == (nd, ni)
                              else (empty, empty, empty))
    for k in range(nd):
        for j in range(ni):
            c = k * ni + j
            if tot[0][c] < 2:
                continue
            g_n, s_n = int(t_count[k, j]), int(s_count[k, j])
            total_mean = float(t_mean[k, j]) if g_n else float(tot[1][c])
            total_std = float(t_std[k, j]) if g_n > 1 else float(tot[2][c])
            sensor_mean = float(s_mean[k, j]) if s_n else float("nan")
            sensor_std = float(s_std[k, j]) if s_n > 1 else float("nan")
            su = math.hypot(float(sens_res[3][c]), float(u_both[c]))
            if u_both[c] > CONFUSION_LIMIT_M:
                confused += 1
            parts_mean = sensor_mean + pose[1][c] + reg[1][c] + refr[1][c]
            out_cells.append({
                "distance_m": [k * COARSE_M, (k + 1) * COARSE_M], "inclination_deg": [j * COARSE_DEG,
                                                                                     (j + 1) * COARSE_DEG],
                "samples_grid": g_n, "samples_sensor_grid": s_n, "samples_refinement": int(tot[0][c]),
                "total": {"mean_m": total_mean, "std_m": total_std, "u95_m": float(tot[3][c])},
                "sensor": {"mean_m": sensor_mean, "std_m": sensor_std, "u95_m": su,
                           "pose_u95_m": float(u_both[c])},
                "poses": {"mean_m": float(pose[1][c]), "std_m": float(pose[2][c]),
                          "u95_m": float(u_pose[c])},
                "registration": {"mean_m": float(reg[1][c]), "std_m": float(reg[2][c]),
                                 "u95_m": float(u_reg[c])},
                "reference": {"mean_m": float(refr[1][c]), "std_m": float(refr[2][c]),
                              "u95_m": float(refr[3][c])},
                "not_attributed": {"mean_m": total_mean - parts_mean,
                                   "u95_m": math.sqrt(float(tot[3][c]) ** 2 + su ** 2 + u_pose[c] ** 2
                                                      + u_reg[c] ** 2 + float(refr[3][c]) ** 2)},
            })
    t_sum, s_sum = total_grid.summary(), sensor_grid.summary()
    pooled = {
        "samples_refinement": int(ptot[0][0]),
        "total": {"mean_m": t_sum.get("mean_m"), "std_m": t_sum.get("std_m"), "u95_m": float(ptot[3][0])},
        "sensor": {"mean_m": s_sum.get("mean_m"), "std_m": s_sum.get("std_m"),
                   "u95_m": math.hypot(float(psens[3][0]), float(u_both[cells])),
                   "pose_u95_m": float(u_both[cells])},
        "poses": {"mean_m": float(ppose[1][0]), "std_m": float(ppose[2][0]), "u95_m": float(u_pose[cells])},
        "registration": {"mean_m": float(preg[1][0]), "std_m": float(preg[2][0]),
                         "u95_m": float(u_reg[cells])},
        "reference": {"mean_m": float(prefr[1][0]), "std_m": float(prefr[2][0]), "u95_m": float(prefr[3][0])},
    }
    return {"cells": out_cells, "pooled": pooled, "confused_cells": confused}


def _factors(grid: Grid) -> tuple[int, int] | None:
    """The coarsening factors from the grid's bins to COARSE_M x COARSE_DEG (None: they do not divide)."""
    d_step = float(grid.distance_edges_m[1] - grid.distance_edges_m[0])
    i_step = float(grid.inclination_edges_deg[1] - grid.inclination_edges_deg[0])
    fd, fi = round(COARSE_M / d_step), round(COARSE_DEG / i_step)
    nd, ni = grid.shape
    if abs(fd * d_step - COARSE_M) > 1e-9 or abs(fi * i_step - COARSE_DEG) > 1e-9 or nd % fd or ni % fi:
        return None
    return fd, fi


def write_pose_corrections(job: ScanJob, ref: dict[str, Any], xreg: F64, out: Path) -> str:
    """pose_corrections.csv: per frame the correction (camera frame: rotation deg, translation m),
    its registration and per-frame parts, the camera centre's shift in the reference frame, each
    with a U95 from the posterior draws."""
    xi, xd, given = ref["xi"], ref["xdraws"], ref["given"]
    u = 1.96 * xd.std(axis=0)
    shift = np.einsum("fij,fj->fi", given[:, :3, :3], xi[:, 3:])
    shift_d = np.einsum("fij,dfj->dfi", given[:, :3, :3], xd[:, :, 3:])
    us = 1.96 * shift_d.std(axis=0)
    head = ["frame", "t_s", "rx_deg", "ry_deg", "rz_deg", "tx_m", "ty_m", "tz_m",
            "rx_u95_deg", "ry_u95_deg", "rz_u95_deg", "tx_u95_m", "ty_u95_m", "tz_u95_m",
            "reg_rx_deg", "reg_ry_deg", "reg_rz_deg", "reg_tx_m", "reg_ty_m", "reg_tz_m",
            "centre_dx_m", "centre_dy_m", "centre_dz_m", "centre_u95_m"]
    lines = [",".join(head)]
    deg = np.degrees
    for f, pos in enumerate(ref["positions"]):
        row = [str(pos), f"{ref['stamps'][f]:.6f}",
               *(f"{v:.6g}" for v in deg(xi[f, :3])), *(f"{v:.6g}" for v in xi[f, 3:]),
               *(f"{v:.3g}" for v in deg(u[f, :3])), *(f"{v:.3g}" for v in u[f, 3:]),
               *(f"{v:.6g}" for v in deg(xreg[f, :3])), *(f"{v:.6g}" for v in xreg[f, 3:]),
               *(f"{v:.6g}" for v in shift[f]), f"{float(np.linalg.norm(us[f])):.3g}"]
        lines.append(",".join(row))
    (out / POSE_CSV).write_text("\n".join(lines) + "\n")
    return POSE_CSV


def budget_figure(budget: dict[str, Any], path: Path, job: ScanJob) -> Path:
    """Fig. 10's mean (grid.npz, coarse cells) beside the sensor's, the poses', the registration's
    and the reference's parts, and below each its U95 (mm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = budget["cells"]
    nd = math.ceil(job.options.distance_max_m / COARSE_M - 1e-9)
    ni = math.ceil(90.0 / COARSE_DEG - 1e-9)
    names = [("total", "Fig. 10: the study (grid.npz)"), ("sensor", "sensor (sensor_grid.npz)"),
             ("poses", "poses (per frame)"), ("registration", "registration (global)"),
             ("reference", "reference (mesh)")]
    mean = {n: np.full((nd, ni), np.nan) for n, _ in names}
    u95 = {n: np.full((nd, ni), np.nan) for n, _ in names}
    shown = job.options.min_count_sequence  # as Fig. 10: cells of fewer samples are not drawn
    for c in cells:
        if c["samples_grid"] < shown:
            continue
        k = round(c["distance_m"][0] / COARSE_M)
        j = round(c["inclination_deg"][0] / COARSE_DEG)
        for n, _ in names:
            mean[n][k, j] = 1000 * c[n]["mean_m"]
            u95[n][k, j] = 1000 * c[n]["u95_m"]
    finite = np.concatenate([m[np.isfinite(m)] for m in mean.values()])
    lim = float(np.percentile(np.abs(finite), 98)) if finite.size else 1.0
    lim = max(lim, 1.0)
    ulim = max(float(np.nanpercentile(np.concatenate([u.ravel() for u in u95.values()]), 98))
               if finite.size else 1.0, 0.5)
    used_d = [k for k in range(nd) if np.isfinite(mean["total"][k]).any()]
    used_i = [j for j in range(ni) if np.isfinite(mean["total"][:, j]).any()]
    d_hi = (max(used_d) + 1) * COARSE_M if used_d else job.options.distance_max_m
    i_hi = (max(used_i) + 1) * COARSE_DEG if used_i else 90.0
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 7.5), constrained_layout=True,
                             sharex=True, sharey=True)
    edges_d = np.arange(nd + 1) * COARSE_M
    edges_i = np.arange(ni + 1) * COARSE_DEG
    for col, (n, title) in enumerate(names):
        im = axes[0, col].pcolormesh(edges_d, edges_i, mean[n].T, cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[0, col].set_title(f"{title}\nmean (mm)", fontsize=10)
        iu = axes[1, col].pcolormesh(edges_d, edges_i, u95[n].T, cmap="viridis", vmin=0, vmax=ulim)
        axes[1, col].set_title(f"{n}: U95 of the mean (mm)", fontsize=10)
        for row in (0, 1):
            axes[row, col].set_xlim(0, d_hi)
            axes[row, col].set_ylim(0, i_hi)
            axes[1, col].set_xlabel("distance (m)")
        if col == 0:
            axes[0, 0].set_ylabel("inclination (deg)")
            axes[1, 0].set_ylabel("inclination (deg)")
    fig.colorbar(im, ax=axes[0, :], shrink=0.9, label="mean error (mm)")
    fig.colorbar(iu, ax=axes[1, :], shrink=0.9, label="U95 (mm)")
    reg = budget["registration"]["correction"]
    fig.suptitle(f"Error budget over distance x inclination ({COARSE_M:g} m x {COARSE_DEG:g} deg cells of "
                 f">= {shown} samples); "
                 f"registration correction: scale {reg['scale']:.5f}", fontsize=11)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    if not np.isfinite(mean["sensor"]).any():
        warn("the budget's sensor grid has no cell in common with the study's grid", str(path),
             "budget-empty")
    return path
