"""Checkerboard study speed: one standpoint of 150 frames at 1280x720 (target: >= 30 frames/s).

Run: .venv/bin/python benchmarks/bench_checkerboard.py [--frames 150] [--distance 2.0] [--inclination 30]
Frames are rendered first (not timed); the timed part is evaluate_frames (detection, pose, mask,
moments, aggregation) in one process.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from depthstation.board import Board
from depthstation.camera import Intrinsics, StreamInfo
from evaluate.checkerboard.study import evaluate_frames

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from checkerboard_render import pose_for, still_frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--distance", type=float, default=2.0)
    ap.add_argument("--inclination", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    intr = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)
    info = StreamInfo(intr, intr, depth_units_m=0.001, depth_aligned_to_color=True)
    board = Board()
    frames = list(still_frames(board, pose_for(board, a.distance, a.inclination, 20.0), info, a.frames,
                               noise_rel=0.002))
    # colour sensor noise (2 grey levels RMS, as the simulator's) so that corner tracking works on
    # changing images; 8 noisy copies cycled keep memory low
    rng = np.random.default_rng(1)
    base = frames[0].color
    assert base is not None
    noisy = [np.clip(base + rng.normal(0.0, 2.0, base.shape[:2])[..., None], 0, 255).astype(np.uint8)
             for _ in range(8)]
    for k, fs in enumerate(frames):
        fs.color = noisy[k % len(noisy)]
    times = []
    r = None
    for _ in range(a.repeat):
        t = time.perf_counter()
        r = evaluate_frames("bench", frames, info, board, frames_requested=a.frames)
        times.append(time.perf_counter() - t)
    assert r is not None
    best, med = min(times), sorted(times)[len(times) // 2]
    print(f"{a.frames} frames 1280x720, board at {a.distance} m / {a.inclination} deg, "
          f"{r.figures['pixels_per_frame']:.0f} board pixels per frame, {r.frames_used} used")
    print(f"median {med:.2f} s = {a.frames / med:.1f} frames/s (best {a.frames / best:.1f}); "
          f"target 30 frames/s -> ratio {a.frames / med / 30:.2f}")


if __name__ == "__main__":
    main()
