"""Capture writer and reader throughput at full size (run by hand, not by pytest).

    .venv/bin/python benchmarks/bench_capture.py [--frames 150] [--compression lz4|none|zstd]

Writer: 1280x720 z16 depth + 1280x720 rgb8 colour fed at a real-time 30 fps into a session's
background writer; reports the longest `write()` call, queue high-water mark, dropped frames and
whether the frame numbers read back are contiguous. Reader: depth frame sets per second.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.sample_recordings import sample_info
from depthstation.core.capture.session import Session
from depthstation.core.frames import FrameSet


def scene_frames(n_distinct: int, width: int, height: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Tilted plane with D455-like noise and holes, textured colour: compresses like real data."""
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    out = []
    for k in range(n_distinct):
        z_mm = 1500.0 + 0.6 * (u - width / 2) + 0.2 * v + rng.normal(0, 4.0, (height, width))
        depth = np.clip(z_mm, 0, 65535).astype(np.uint16)
        depth[rng.random((height, width)) < 0.03] = 0
        color = np.empty((height, width, 3), np.uint8)
        color[..., 0] = ((u // 40 + v // 40 + k) % 2 * 200 + rng.integers(0, 20, (height, width))).astype(
            np.uint8
        )
        color[..., 1] = color[..., 0]
        color[..., 2] = (v / height * 255).astype(np.uint8)
        out.append((depth, color))
    return out


def bench_writer(root: Path, n: int, fps: float, compression: str) -> Path:
    info = sample_info(1280, 720, fps=fps)
    frames = scene_frames(8, 1280, 720)
    session = Session.create(root / f"session-{compression}", device=info.device)
    period = 1.0 / fps
    t0 = time.perf_counter()
    t_start_ns = time.time_ns()
    put_times = []
    late = 0
    with session.standpoint_writer("standpoint_01", info, {"distance_m": 1.5}, compression=compression) as w:
        for i in range(n):
            due = t0 + i * period
            now = time.perf_counter()
            if now < due:
                time.sleep(due - now)
            elif now - due > period:
                late += 1
            depth, color = frames[i % len(frames)]
            fs = FrameSet(
                index=1000 + i, timestamp_ns=t_start_ns + int(i * period * 1e9), depth=depth, color=color
            )
            t = time.perf_counter()
            w.write(fs)
            put_times.append(time.perf_counter() - t)
            if i % 30 == 0:
                w.write_temperature(fs.timestamp_ns, {"asic": 40.0 + i / 100, "projector": 38.0})
        feed_s = time.perf_counter() - t0
        max_queue = w.max_queue
        t_close = time.perf_counter()
    close_s = time.perf_counter() - t_close
    path = session.dir / "standpoint_01.mcap"
    size_mb = path.stat().st_size / 1e6
    raw_mb = n * (1280 * 720 * 2 + 1280 * 720 * 3) / 1e6
    rec = open_recording(path)
    indices = [fs.index for fs in rec.frames()]
    contiguous = indices == list(range(1000, 1000 + n))
    print(
        f"writer [{compression}]: {n} frame sets 1280x720 z16 + rgb8 fed at {fps:.0f} fps in {feed_s:.2f} s "
        f"(producer late by > 1 period: {late})"
    )
    print(
        f"  write() call: max {max(put_times) * 1e3:.3f} ms, median {np.median(put_times) * 1e6:.1f} us; "
        f"queue high-water {max_queue}/64; dropped {w.dropped}; drain after last frame {close_s:.2f} s"
    )
    print(
        f"  file {size_mb:.0f} MB for {raw_mb:.0f} MB raw (ratio {raw_mb / size_mb:.2f}); "
        f"read back {len(indices)} frames, contiguous: {contiguous}"
    )
    print(f"  KEEPS UP: {w.dropped == 0 and contiguous and close_s < 2.0}")
    return path


def bench_reader(path: Path) -> None:
    rec = open_recording(path)
    t = time.perf_counter()
    n = sum(1 for _ in rec.frames())
    dt = time.perf_counter() - t
    print(
        f"reader: {n} frame sets (depth + colour) in {dt:.2f} s = {n / dt:.0f} frame sets/s "
        f"({n * (1280 * 720 * 5) / dt / 1e9:.2f} GB/s); target >= 300 depth frames/s: {n / dt >= 300}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--compression", default="none", choices=["lz4", "none", "zstd"])
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: a temporary folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        path = bench_writer(Path(tmp), args.frames, args.fps, args.compression)
        bench_reader(path)


if __name__ == "__main__":
    main()
