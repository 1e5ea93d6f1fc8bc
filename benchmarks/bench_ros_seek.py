"""Reading one frame from the end of a ROS bag (a figure frame, a fit sample): peak memory and time,
for a rosbag2 MCAP, a rosbag2 sqlite3 and a ROS 1 bag written with rosbags' writers.

Why: the frames before `start` are skipped, but their colour images were all kept until the start
frame came (nothing to pair them with yet). Each read runs in a fresh process (peak RSS).

Run by hand: .venv/bin/python benchmarks/bench_ros_seek.py [--frames 300]
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
READ = """
import resource, sys, time
from pathlib import Path
from depthstation.core.capture.registry import open_recording
rec = open_recording(Path(sys.argv[1]))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
t = time.perf_counter()
f = next(iter(rec.frames(start=rec.frame_count - 1, limit=1)))
assert f.color is not None
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
print(f"{before:.0f} {after:.0f} {time.perf_counter() - t:.2f}")
"""


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench_ros_seek_") as tmp:
        run(Path(tmp))


def run(root: Path) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    sys.path.insert(0, str(HERE.parent / "tests"))
    from ros_bags import write_bag  # rosbags' writers, realsense-ros layout

    from depthstation.core.capture.sample_recordings import sample_frames, sample_info

    info = sample_info(640, 480)
    rng = np.random.default_rng(0)  # colour as incompressible as a camera's
    frames = [dataclasses.replace(f, color=rng.integers(0, 255, f.color.shape, dtype=np.uint8))
              for f in sample_frames(info, args.frames, seed=1) if f.color is not None]
    for name, kw in (("rosbag2 mcap", {}), ("rosbag2 sqlite3", {"storage": "sqlite3"}),
                     ("ROS 1 bag", {"ros": 1})):
        path = root / (name.replace(" ", "_") + (".bag" if "ROS 1" in name else ""))
        write_bag(path, info, frames, **kw)
        out = subprocess.run([sys.executable, "-c", READ, str(path)], capture_output=True, text=True,
                             check=True).stdout.split()
        before, after, secs = float(out[0]), float(out[1]), float(out[2])
        print(f"{name:16s} frame {args.frames - 1} of {args.frames}: peak RSS {before:.0f} MB after opening, "
              f"{after:.0f} MB after the read, {secs:.2f} s")


if __name__ == "__main__":
    main()
