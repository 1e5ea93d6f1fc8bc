"""Simulate the reference-scan study: a camera walking round a table in a room, recorded as one sequence."""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.capture.mcap_writer import SIMULATION_COLOR_ENCODING, SIMULATION_COMPRESSION
from depthstation.core.capture.session import Session
from depthstation.core.errors import InputError, SimulationError
from depthstation.core.frames import FrameSet
from depthstation.core.progress import progress as make_progress
from depthstation.core.protocol import Streams
from depthstation.core.results import write_json
from depthstation.core.run_warnings import warn
from depthstation.simulate.checkerboard_session import (
    START_NS,
    TRUTH_FILE,
    WARM_TEMPERATURE_C,
    DepthTally,
    model_label,
)
from depthstation.simulate.model import SensorModel, check_seed, load_model
from depthstation.simulate.poses import read_tum, walk_around, write_tum
from depthstation.simulate.scene import Scene, load_scene
from depthstation.simulate.scene_render import SceneRaster
from depthstation.simulate.view_renderer import ViewRenderer

SEQUENCE_NAME = "sequence"
TRAJECTORY_FILE = "trajectory.txt"
MESH_FILE = "scene.ply"


def scan_trajectory(trajectory: str | Path, scene: Scene, fps: float,
                    frames: int | None = None) -> tuple[NDArray[np.float64], list[NDArray[np.float64]]]:
    """(time stamps s, depth-camera-to-world poses): 'walk' round the room's table or a TUM file."""
    if str(trajectory) == "walk":
        th = float(scene.meta.get("table_height_m", 0.75))
        poses = walk_around(np.array([0.0, -th, 0.0]), fps=fps, frames=frames)
        return np.arange(len(poses)) / fps, poses
    stamps, poses = read_tum(Path(trajectory))
    if frames is not None:
        stamps, poses = stamps[:frames], poses[:frames]
    dt = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    if dt > 0 and abs(1.0 / dt - fps) > 0.1 * fps:  # the frames are stamped at the trajectory's times
        warn(f"its poses are {dt:.4g} s apart ({1.0 / dt:.3g} per second) while --fps is {fps:g}: the "
             "frames are stamped at the trajectory's times (TUM times are seconds; times in "
             "milliseconds put frames 1000x too far apart)", str(trajectory), "trajectory-rate")
    return stamps - stamps[0], poses


def simulate_scan(scene: str | Path | Scene, trajectory: str | Path, model: SensorModel | str | Path,
                  out_dir: Path, *, seed: int = 0, frames: int | None = None, width: int = 640,
                  height: int = 480, fps: float = 30.0, color: bool = True, progress: bool = False,
                  compression: str = SIMULATION_COMPRESSION, threads: int | None = None,
                  color_encoding: str = SIMULATION_COLOR_ENCODING) -> Path:
    """Render a sequence along a trajectory into a capture session; returns out_dir.

    out_dir gets session.json + sequence.mcap (our format), trajectory.txt (true depth-camera
    poses, TUM, what ORB-SLAM3 would estimate), scene.ply (the reference mesh) and truth.json.
    `threads`: frames rendered side by side (default: up to 2, the cores this process may use).
    `color_encoding`: colour recorded as the camera sends it (YUYV 4:2:2) or as RGB8.
    """

    mdl = load_model(model)
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise InputError(out, "is not empty; simulations never overwrite captures")
    if frames is not None and frames < 1:
        raise InputError(None, "--frames must be at least 1")
    check_seed(seed)
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(None, f"--fps must be a positive number of frames per second, not {fps}")
    if width < 1 or height < 1:
        raise InputError(None, f"--width and --height must be positive pixel counts, not {width}x{height}")
    stamps, poses = scan_trajectory(trajectory, sc, fps, frames)
    try:
        info = mdl.camera.stream_info(width, height, fps)
    except SimulationError as exc:
        raise InputError(None, f"--width/--height: {exc}") from exc
    if not color:

        info = replace(info, color_intrinsics=None)
    session = Session.create(out, protocol=None, device=info.device, simulated=True,
                             scan={"scene": sc.meta, "trajectory": str(trajectory)})
    write_tum(out / TRAJECTORY_FILE, START_NS / 1e9 + stamps, poses)  # the frames' epoch time stamps
    sc.save_mesh(out / MESH_FILE)
    # the room is rasterised (the hits ray casting would give, several times faster); frames are
    # rendered by `threads` renderers side by side (the kernels release the GIL); every frame
    # depends only on its pose, index and the seed, so the sequence is the same for any count
    n_threads = max(1, threads if threads is not None else min(2, len(os.sched_getaffinity(0))))
    renderers = [ViewRenderer(sc, mdl, info, seed=seed, color=color, rc=SceneRaster(sc), vectors=False)
                 for _ in range(n_threads)]

    def render(i: int) -> FrameSet:
        r = renderers[i % n_threads]
        r.set_pose(poses[i])
        stamp = START_NS + round(float(stamps[i]) * 1e9)
        return r.frame(i, stamp, float(stamps[i]), WARM_TEMPERATURE_C, rng=np.random.default_rng([seed, i]))

    def gen() -> Iterator[FrameSet]:
        bar = None
        if progress:

            bar = make_progress()
            bar.start()
            task = bar.add_task("simulate scan", total=len(poses), status="")
        pools = [ThreadPoolExecutor(1) for _ in range(n_threads)]
        try:
            pending: deque[Future[FrameSet]] = deque()
            for i in range(len(poses)):
                pending.append(pools[i % n_threads].submit(render, i))
                if len(pending) >= 2 * n_threads:
                    yield pending.popleft().result()
                    if bar is not None:
                        bar.advance(task)
            while pending:
                yield pending.popleft().result()
                if bar is not None:
                    bar.advance(task)
        finally:
            for p in pools:
                p.shutdown(wait=True, cancel_futures=True)
            if bar is not None:
                bar.stop()

    meta: dict[str, Any] = {"name": SEQUENCE_NAME, "kind": "scan", "trajectory_file": TRAJECTORY_FILE,
                            "mesh_file": MESH_FILE}
    with session.standpoint_writer(SEQUENCE_NAME, info, meta, blocking=True, compression=compression,
                                   metadata={"simulation": {"seed": seed, "model": mdl.name}},
                                   color_encoding=color_encoding) as w:
        w.write_temperature(START_NS, {"asic": WARM_TEMPERATURE_C, "projector": WARM_TEMPERATURE_C})
        tally = DepthTally()
        for fs in tally.watch(gen()):
            w.write(fs)
    tally.done(SEQUENCE_NAME)
    tally.warn_if_empty(model_label(model, mdl))
    write_json(out / TRUTH_FILE, {
        "kind": "simulated-scan", "seed": seed, "frames": len(poses), "stream_info": info.to_dict(),
        "model_name": mdl.name, "model": mdl.to_toml(), "scene": sc.meta, "mesh_file": MESH_FILE,
        "trajectory_file": TRAJECTORY_FILE, "trajectory_source": str(trajectory),
        "pose_convention": "depth camera to world (scene mesh frame), OpenCV axes",
        "start_ns": START_NS})
    return out


def default_streams() -> Streams:
    """The paper's scan mode: 640x480 at 30 fps."""
    return Streams(width=640, height=480, fps=30)
