"""Coverage of the scan grid's cell uncertainty (u95_m, frames as clusters) against sqrt(var / n).

The same walk through the analytic room (24 frames) is rendered R times with fresh noise: white
pixel noise from the error model and, written here in this benchmark's own form, a depth offset
common to every pixel of a frame (a pose or exposure error, N(0, sigma_f)). The truth of a cell is
the mean of the model's bias over the very pixels the cell received. Printed: the share of cells
(with >= --min-count samples and >= 5 frames) whose truth lies within mean +- u95_m, the same for
1.96 sqrt(var / n), and the median over cells of u95_m / (1.96 x the actual spread of the cell mean
over the R runs) (1 = honest, < 2 = not inflated; goal: coverage >= 93 %).

    .venv/bin/python benchmarks/bench_grid_coverage.py --runs 200 --sigma-frame-mm 2
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from depthstation.core.grid import Grid
from depthstation.evaluate.scan.raycast import MeshCaster
from depthstation.evaluate.scan.study import StudyConfig, evaluate_chunk
from depthstation.evaluate.scan.synthetic import ErrorModel, Room, make_sequence, render_truth
from depthstation.evaluate.scan.trajectory import Trajectory

UNITS = 1e-4


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--sigma-frame-mm", type=float, default=2.0, help="frame-common depth offset")
    ap.add_argument("--min-count", type=int, default=200)
    args = ap.parse_args()

    model = ErrorModel(a_per_m=0.002, b_m=0.004, sigma_per_m=0.0015)
    room = Room()
    mesh = room.mesh()
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=2.0, nthreads=1)
    sigma_f = args.sigma_frame_mm * 1e-3
    means, truths, u95s, naives, wells = [], [], [], [], []
    t0 = time.perf_counter()
    caster = None
    for r in range(args.runs):
        seq = make_sequence(frames=args.frames, width=160, height=120, model=model, depth_units_m=UNITS,
                            seed=1000 + r)
        rng = np.random.default_rng(r)
        shifted = []
        for d in seq.depth:
            z = np.where(d > 0, d * UNITS + rng.normal(0.0, sigma_f), 0.0)
            shifted.append(np.round(z / UNITS).astype(np.uint16))
        seq = dataclasses.replace(seq, depth=shifted)
        caster = caster or MeshCaster(mesh, seq.info.depth_intrinsics, nthreads=1)
        traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
        grid = evaluate_chunk(caster, seq, traj, config).grid
        truth = Grid.empty(0.05, 2.0)
        for k in range(args.frames):
            z, inc = render_truth(room, seq.info.depth_intrinsics, seq.poses[k])
            ok = seq.depth[k] > 0
            truth.add(z[ok], inc[ok], model.bias_m(z[ok], inc[ok]))
        assert grid.moments is not None
        wells.append((grid.count >= args.min_count) & (grid.moments.frames >= 5))
        means.append(grid.mean_m)
        truths.append(truth.mean_m)
        u95s.append(grid.u95_m)
        naives.append(1.96 * grid.stderr)
    seconds = time.perf_counter() - t0
    well = np.all(wells, axis=0)  # cells filled in every run
    m, t, u, n = (np.stack(a)[:, well] for a in (means, truths, u95s, naives))
    err = m - t
    covered = float(np.mean(np.abs(err) <= u))
    covered_naive = float(np.mean(np.abs(err) <= n))
    spread = 1.96 * np.sqrt(np.mean(err**2, axis=0))
    ratio = float(np.median(np.median(u, axis=0) / spread))
    ratio_naive = float(np.median(np.median(n, axis=0) / spread))
    print(f"{args.runs} runs x {int(well.sum())} cells (>= {args.min_count} samples, >= 5 frames), "
          f"frame-common sigma {args.sigma_frame_mm} mm, {seconds:.0f} s")
    print(f"coverage: u95_m {covered:.1%}   1.96 sqrt(var/n) {covered_naive:.1%}   (goal >= 93 %)")
    print(f"median U95 / actual spread: u95_m {ratio:.2f}   sqrt(var/n) {ratio_naive:.2f}   "
          "(1 = honest, < 2 = not inflated)")


if __name__ == "__main__":
    main()
