"""What the Depth Quality Tool metrics cost the checkerboard study per frame (run by hand).

    .venv/bin/python benchmarks/bench_dqt.py

At 1280x720, a still board rendered exactly (tests/checkerboard_render.py), for a near head-on and
a far inclined standpoint: the whole per-frame evaluation (detection, pose, mask, moments, DQT)
and the DQT part alone (board mask; then with the centred 40 % ROI), best of 40 frames each, so
that the shared machine's load spikes drop out.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.evaluate.checkerboard.frame import FrameEvaluator
from depthstation.evaluate.checkerboard.mask import board_mask

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from checkerboard_render import pose_for, still_frames


def main() -> None:
    intr = Intrinsics(1280, 720, 640.0, 640.0, 639.5, 359.5)
    info = StreamInfo(intr, intr, depth_units_m=0.001, depth_aligned_to_color=True, baseline_m=0.095)
    board = Board()
    for dist, inc in ((1.0, 0.0), (2.0, 30.0), (4.0, 45.0)):
        frames = list(still_frames(board, pose_for(board, dist, inc, 20.0), info, 8, noise_rel=0.002))
        for roi in (None, 0.4):
            ev = FrameEvaluator(info, board, roi=roi)
            first, _ = ev.evaluate(frames[0])
            assert first.pose_depth is not None
            mask = board_mask(first.pose_depth, intr, board, 0.01)
            assert mask is not None
            whole, part = [], []
            for k in range(40):
                fs = frames[k % len(frames)]
                assert fs.depth is not None
                t = time.perf_counter()
                res, _ = ev.evaluate(fs)
                whole.append(time.perf_counter() - t)
                t = time.perf_counter()
                ev._dqt(res, fs.depth, mask)
                part.append(time.perf_counter() - t)
            w, p = min(whole), min(part)
            print(f"{dist:.1f} m / {inc:4.1f} deg, {first.board_pixels:6d} board px, roi={roi}: frame "
                  f"{w * 1e3:5.2f} ms with DQT, DQT {p * 1e3:5.2f} ms = +{100 * p / (w - p):3.0f} % "
                  f"on the rest")


if __name__ == "__main__":
    main()
