"""Checkerboard study speed: one standpoint of 150 frames at 1280x720 (target: >= 30 frames/s).

Run: .venv/bin/python benchmarks/bench_checkerboard.py [--frames 150] [--distance 2.0] [--inclination 30]
Frames are rendered first (not timed); the timed part is evaluate_frames (detection, pose, mask,
moments, aggregation) in one process.
`--e2e`: end to end, as a user runs it: `--standpoints` simulated standpoints (150 frames of
1280x720 depth + colour each, `simulate checkerboard`) are written to disk (not timed), then
`depthstation evaluate checkerboard SESSION --board ... --out ...` is timed as a whole process
(start-up, reading, the study, tables and figures): frames/s = frames / wall time, target >= 60.
`--corners`: instead, the corner error of each refinement (cornerSubPix, findChessboardCornersSB
with CALIB_CB_ACCURACY, the X-junction fit of corners.py) on the simulator's exact-coverage colour
(noise-free, i.e. the static error a still standpoint keeps), against the projected true corners.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from depthstation.core.board import Board
from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.evaluate.checkerboard.study import evaluate_frames

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from checkerboard_render import pose_for, still_frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--distance", type=float, default=2.0)
    ap.add_argument("--inclination", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--corners", action="store_true")
    ap.add_argument("--e2e", action="store_true", help="time the command on simulated standpoints on disk")
    ap.add_argument("--standpoints", default="standpoint_03,standpoint_07,standpoint_12",
                    help="--e2e: the protocol's standpoints to simulate (comma list)")
    ap.add_argument("--dir", type=Path, default=None,
                    help="--e2e: where to simulate (default: a temporary folder)")
    a = ap.parse_args()
    if a.corners:
        corner_errors()
        return
    if a.e2e:
        end_to_end(a.standpoints.split(","), a.frames, a.repeat, a.dir)
        return
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


def end_to_end(standpoints: list[str], frames: int, repeat: int, where: Path | None) -> None:
    """`depthstation evaluate checkerboard` as a whole process on simulated standpoints on disk."""
    import os
    import resource
    import subprocess
    import tempfile

    from depthstation.simulate.checkerboard_session import simulate_checkerboard

    root = Path(__file__).resolve().parents[1]
    board = root / "protocols" / "checkerboard-d455.toml"
    with tempfile.TemporaryDirectory(dir=where) as tmp:
        t = time.perf_counter()
        session = simulate_checkerboard("checkerboard-d455", "d455", Path(tmp) / "session", frames=frames,
                                        standpoints=standpoints)
        size = sum(p.stat().st_size for p in session.glob("*.mcap")) / 1e6
        n = frames * len(standpoints)
        print(f"{len(standpoints)} standpoints x {frames} frames of 1280x720 depth + colour simulated to "
              f"disk ({size:.0f} MB) in {time.perf_counter() - t:.0f} s (not timed)")
        cmd = [sys.executable, "-m", "depthstation.app.cli", "evaluate", "checkerboard", str(session),
               "--board", str(board)]
        imp = [sys.executable, "-c", "import depthstation.app.cli"]
        t = time.perf_counter()
        subprocess.run(imp, check=True)
        t_import = time.perf_counter() - t
        walls, cpus = [], []
        for k in range(repeat):
            out = Path(tmp) / f"out{k}"
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            subprocess.run([*cmd, "--out", str(out)], check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
            walls.append(time.perf_counter() - t)
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime)
        w = sorted(walls)[len(walls) // 2]
        c = sorted(cpus)[len(cpus) // 2]
        load = os.getloadavg()[0]
        print(f"the command (start-up, reading, study, tables, figures): median {w:.2f} s wall of {repeat} "
              f"= {n / w:.1f} frames/s; CPU {c:.2f} s ({n / c * 2:.0f} frames/s if spread over 2 cores); "
              f"importing the CLI alone {t_import:.2f} s")
        print(f"target 60 frames/s -> ratio {n / w / 60:.2f}; load average {load:.1f} on "
              f"{os.cpu_count()} cores (other work on the machine lowers the wall-time figure)")


def corner_errors() -> None:
    """RMS and max static corner error (px) per method over 1-5 m x 0-60 deg at 1280x720."""
    import cv2

    from depthstation.evaluate.checkerboard.corners import refine_xjunctions
    from depthstation.simulate.model import load_model
    from depthstation.simulate.poses import standpoint_pose
    from depthstation.simulate.scene import board_scene
    from depthstation.simulate.scene_render import encode_srgb, render_color_linear

    board = Board()
    model = load_model("d455")
    scene = board_scene(board)
    rc = scene.raycasting_scene()
    info = model.camera.stream_info(1280, 720, 30.0)
    ci = info.color_intrinsics
    assert ci is not None
    obj = board.corner_points()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    print("standpoint      square | cornerSubPix rms/max | SB+ACCURACY rms/max | X-junction rms/max  (px)")
    for dist, incl in [(1.0, 0), (2.6, 0), (4.0, 0), (5.0, 0), (1.0, 60), (3.0, 60), (5.0, 30), (5.0, 60)]:
        cam_to_board = standpoint_pose(board, dist, incl, "left")
        cpose = cam_to_board @ np.linalg.inv(info.depth_to_color.matrix)
        gray = encode_srgb(render_color_linear(scene, ci, cpose, rc))[..., 1]
        b2c = np.linalg.inv(cpose)
        truth, _ = cv2.projectPoints(obj @ b2c[:3, :3].T + b2c[:3, 3], np.zeros(3), np.zeros(3), ci.K,
                                     ci.opencv_distortion())
        truth = truth.reshape(-1, 2)
        found, c0 = cv2.findChessboardCorners(gray, board.inner_corners)
        if not found:
            print(f"{dist} m {incl} deg: not found")
            continue
        c0 = c0.reshape(-1, 2)
        if np.linalg.norm(c0[0] - truth[0]) > 5:
            c0 = c0[::-1].copy()
        half = int(np.clip(np.min(np.linalg.norm(np.diff(c0, axis=0), axis=1)) / 4, 2, 11))
        sub = cv2.cornerSubPix(gray, c0.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), crit).reshape(-1, 2)
        ok, sb = cv2.findChessboardCornersSB(gray, board.inner_corners, flags=cv2.CALIB_CB_ACCURACY)
        sbp = sb.reshape(-1, 2) if ok else None
        if sbp is not None and np.linalg.norm(sbp[0] - truth[0]) > 5:
            sbp = sbp[::-1]
        xj, _ = refine_xjunctions(gray, sub.astype(np.float64), obj)

        def fmt(p: np.ndarray | None, truth: np.ndarray = truth) -> str:
            if p is None:
                return "     not found     "
            e = p - truth
            return f"{np.sqrt(np.mean(np.sum(e**2, axis=1))):.3f} / {np.abs(e).max():.3f}"

        side = float(np.linalg.norm(truth[1] - truth[0]))
        print(f"{dist:.1f} m {incl:2d} deg {side:6.1f} px |  {fmt(sub)}   |  {fmt(sbp)}    | {fmt(xj)}")


if __name__ == "__main__":
    main()
