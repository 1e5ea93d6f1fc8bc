"""What the automatic local shift costs the scan study (run by hand, not by pytest).

    .venv/bin/python benchmarks/bench_scan_shift.py [--frames 120] [--width 640] [--repeat 3]

The same synthetic walk round the table (analytic depth with a known error model) and the same
room mesh, once in room coordinates and once moved into survey coordinates (412345.6, 5523456.7,
110.0) m, trajectory moved with it. Both run the whole study (`run_scan`: reference, registration
with ICP, casting, grid, figures); runs alternate so that the shared machine's load hits both
alike; the best of each is compared. Goal: the shift adds < 2 %. Also prints how far the two grids
are apart (cells with >= 200 samples).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.grid import Grid
from depthstation.core.lazy_open3d import open3d
from depthstation.evaluate.scan.run import ScanOptions, run_scan
from depthstation.evaluate.scan.synthetic import Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum

SURVEY = np.array([412345.6, 5523456.7, 110.0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=None)
    args = ap.parse_args()
    o3d = open3d()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        seq = make_sequence(frames=args.frames, width=args.width, height=args.width * 3 // 4, seed=3)
        write_mcap(root / "seq.mcap", seq.info, seq.frames())
        t = np.asarray(seq.timestamps_ns) * 1e-9
        mesh = Room().mesh(segments=2048, subdivide_walls=8)  # ~0.8 M triangles, as a TLS mesh
        o3d.io.write_triangle_mesh(str(root / "room.ply"), mesh)
        far = o3d.geometry.TriangleMesh(mesh)
        far.translate(SURVEY)
        o3d.io.write_triangle_mesh(str(root / "room_survey.ply"), far)
        write_tum(root / "poses.txt", t, seq.poses)
        moved = seq.poses.copy()
        moved[:, :3, 3] += SURVEY
        write_tum(root / "poses_survey.txt", t, moved)
        np.savetxt(root / "identity.txt", np.eye(4))
        cases = {"room": ("room.ply", "poses.txt"), "survey": ("room_survey.ply", "poses_survey.txt")}
        times: dict[str, list[float]] = {k: [] for k in cases}
        stages: dict[str, list[dict[str, float]]] = {k: [] for k in cases}
        grids: dict[str, Grid] = {}
        for k in range(args.repeat):
            for name, (ref, poses) in cases.items():
                out = root / f"{name}_{k}"
                t0 = time.perf_counter()
                s = run_scan(root / "seq.mcap", root / poses, root / ref, out,
                             ScanOptions(similarity=root / "identity.txt", icp=True))
                times[name].append(time.perf_counter() - t0)
                stages[name].append(s["timing_s"])
                grids[name] = Grid.load(out / "grid.npz")
                if k == 0:
                    print(f"{name}: local shift {s['local_shift']}, {len(mesh.triangles)} triangles, "
                          f"{s['frames']['used']} frames of {args.width}x{args.width * 3 // 4}")
        best = {k: min(v) for k, v in times.items()}
        for name in cases:
            k = int(np.argmin(times[name]))
            print(f"  {name} stages of its best run (s):",
                  {a: round(b, 3) for a, b in stages[name][k].items()})
        print("whole study, best of", args.repeat, "(s):", {k: round(v, 3) for k, v in best.items()},
              "all:", {k: [round(x, 2) for x in v] for k, v in times.items()})
        print(f"shift cost: survey / room = {best['survey'] / best['room']:.4f} "
              f"({100 * (best['survey'] / best['room'] - 1):+.2f} %); goal < +2 %")
        a, b = grids["room"], grids["survey"]
        both = (a.count >= 200) & (b.count >= 200)
        d = np.abs(a.mean - b.mean)[both]
        print(f"grids: {int(both.sum())} cells with >= 200 samples, |mean difference| max "
              f"{1e3 * d.max():.4f} mm, mean {1e3 * d.mean():.5f} mm; counts {int(a.count.sum())} vs "
              f"{int(b.count.sum())}")


if __name__ == "__main__":
    main()
