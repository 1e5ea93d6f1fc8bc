"""Benchmark of `evaluate scan --budget` against the plain study, measured in one run.

The workload is the paper's (1334 frames of 640x480; `--frames` for fewer) on the synthetic room of
benchmarks/bench_scan.py (its mesh of >= 1 M triangles, frames cycling over `--distinct` rendered
depth images), written once as an MCAP sequence, a TUM trajectory and a PLY mesh, then run as the
command runs it (`run_scan`): the plain study, then the study with `--budget`, back to back, each
`--cycles` times, alternating. Goal: the run with `--budget` at most 3 x the plain one (the
refinement ray casts about 2500 pixels a frame per render, 4 renders; the sensor pass is a second
study). The ratio of runs seconds apart says more than either wall time on a shared box.
`--workers 1` (the command's default) runs everything in one process; more workers run the
study's chunks and the refinement's frames on local processes.

Run by hand:  .venv/bin/python benchmarks/bench_budget.py [--frames 1334] [--workers 1] [--cycles 1]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from bench_scan import build_mesh, make_workload


def write_inputs(folder: Path, frames: int, distinct: int, width: int, height: int, subdivide: int,
                 segments: int) -> tuple[Path, Path, Path]:
    from depthstation.core.capture.mcap_writer import write_mcap
    from depthstation.core.frames import FrameSet
    from depthstation.core.lazy_open3d import open3d
    from depthstation.evaluate.scan.trajectory import write_tum

    seq = make_workload(frames, distinct, width, height)
    sets = (FrameSet(k, int(t), d, None) for k, (t, d) in enumerate(zip(seq.timestamps_ns, seq.depth,
                                                                         strict=True)))
    write_mcap(folder / "sequence.mcap", seq.info, sets, {"device": dict(seq.info.device)}, compression="lz4")
    write_tum(folder / "trajectory.txt", [t * 1e-9 for t in seq.timestamps_ns], list(seq.poses))
    _, mesh = build_mesh(subdivide, segments)
    open3d().io.write_triangle_mesh(str(folder / "room.ply"), mesh)
    return folder / "sequence.mcap", folder / "trajectory.txt", folder / "room.ply"


def run_once(paths: tuple[Path, Path, Path], out: Path, workers: int, budget: bool) -> float:
    from depthstation.evaluate.scan.chunks import clear_cache
    from depthstation.evaluate.scan.run import ScanOptions, run_scan

    clear_cache()  # each run reads and prepares its mesh, as a command does
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    run_scan(*paths, out, ScanOptions(workers=workers, budget=budget))
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1334)
    ap.add_argument("--distinct", type=int, default=32)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--subdivide", type=int, default=8, help="wall subdivisions (12 * 4^n triangles)")
    ap.add_argument("--segments", type=int, default=100_000, help="table segments (3 triangles each)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--cycles", type=int, default=1)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_budget_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        paths = write_inputs(root, args.frames, args.distinct, args.width, args.height, args.subdivide,
                             args.segments)
        print(f"inputs: {args.frames} frames of {args.width}x{args.height} written in "
              f"{time.perf_counter() - t0:.1f} s")
        ratios = []
        for c in range(args.cycles):
            plain = run_once(paths, root / "plain", args.workers, False)
            with_budget = run_once(paths, root / "budget", args.workers, True)
            ratios.append(with_budget / plain)
            print(f"cycle {c + 1}: plain {plain:.1f} s, --budget {with_budget:.1f} s: "
                  f"{with_budget / plain:.2f} x (goal <= 3)")
        import json

        b = json.loads((root / "budget" / "budget.json").read_text())
        print("budget timing_s:", {k: round(v, 1) for k, v in b["timing_s"].items()})
        print(f"median ratio {float(np.median(ratios)):.2f} x over {len(ratios)} cycle(s)")


if __name__ == "__main__":
    main()
