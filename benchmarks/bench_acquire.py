"""Recording at full size: 1280x720 depth + colour at 30 fps from the simulated camera at real-time
rate, through the guided loop into the session writer. The camera keeps its frame schedule and,
like a device, drops the frames a late reader missed beyond a 2-frame queue, so gaps in the frame
numbers of the MCAP are real drops.

Prints the achieved frame rate, writer drops, the longest queue, and whether the frame numbers in
the MCAP are contiguous. Run: .venv/bin/python benchmarks/bench_acquire.py [frames]
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from depthstation.acquire.guided_capture import GuidedCapture, LiveState
from depthstation.core.capture.session import Session
from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances
from depthstation.simulate.poses import standpoint_pose
from depthstation.simulate.simulated_camera import SimulatedCamera


def main() -> None:
    frames = int(sys.argv[1]) if len(sys.argv) > 1 else 150
    proto = Protocol("bench", streams=Streams(width=1280, height=720, fps=30),
                     plan=Plan(frames_per_standpoint=frames, start_distance_m=1.4, max_distance_m=1.4,
                               inclinations_deg=(0.0,)),
                     tolerances=Tolerances(still_seconds=0.2))
    cam = SimulatedCamera("d455", board=proto.board, real_time=True, drop_late_frames=True,
                          pose=standpoint_pose(proto.board, 1.4, 0.0))
    with tempfile.TemporaryDirectory() as tmp:
        session = Session.create(Path(tmp) / "s", protocol=proto)
        stamps: list[float] = []
        cpu: list[tuple[float, float]] = []  # (process CPU, main-thread CPU) per recorded frame

        def on_state(st: LiveState) -> None:
            if st.phase == "recording":
                stamps.append(time.perf_counter())
                cpu.append((time.process_time(), time.thread_time()))

        cap = GuidedCapture(cam, proto, session, max_guidance_s=20, on_state=on_state)
        t0 = time.perf_counter()
        cap.run()
        wall = time.perf_counter() - t0
        s = Session.open(Path(tmp) / "s")
        e = s.standpoints[0]
        idx = np.array([f.index for f in s.recordings()[0].frames()])
        rec_s = stamps[-1] - stamps[0] if len(stamps) > 1 else float("nan")
        print(f"frames recorded        {idx.size} of {frames}")
        print(f"recording fps          {(len(stamps) - 1) / rec_s:.1f} (target 30)")
        n = len(cpu) - 1
        proc_ms = (cpu[-1][0] - cpu[0][0]) / n * 1e3
        main_ms = (cpu[-1][1] - cpu[0][1]) / n * 1e3
        print(f"CPU per recorded frame {proc_ms:.1f} ms all threads, {main_ms:.1f} ms loop thread "
              f"(frame period 33.3 ms; {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
        print(f"writer drops           {e['dropped_frames']}")
        print(f"camera drops (late)    {cam.dropped_frames} (whole run, guidance included)")
        print(f"frame numbers          {'contiguous' if np.all(np.diff(idx) == 1) else 'GAPS'}")
        print(f"mcap size              {(Path(tmp) / 's' / e['file']).stat().st_size / 1e6:.0f} MB")
        print(f"wall (guide + record)  {wall:.1f} s")


if __name__ == "__main__":
    main()
