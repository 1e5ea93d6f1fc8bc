"""Simulate a checkerboard-study session: every standpoint of a protocol plan, rendered into captures."""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.rs_writer import write_realsense_recording
from depthstation.core.capture.session import Session
from depthstation.core.errors import InputError, SimulationError
from depthstation.core.frames import FrameSet
from depthstation.core.progress import progress
from depthstation.core.protocol import MAX_FRAMES_PER_STANDPOINT, Protocol, Standpoint, load_protocol
from depthstation.core.results import write_json
from depthstation.core.run_warnings import warn
from depthstation.simulate.model import SensorModel, check_seed, load_model
from depthstation.simulate.poses import standpoint_pose, standpoint_truth
from depthstation.simulate.scene import Scene, board_scene
from depthstation.simulate.view_renderer import ViewRenderer

FORMATS = ("mcap", "db3")
TRUTH_FILE = "truth.json"
START_NS = 1_700_000_000_000_000_000  # fixed epoch origin so simulations are reproducible
WARM_TEMPERATURE_C = 40.0


@dataclass
class DepthTally:
    """Counts simulated frames and those holding any depth, as they pass to the writer, standpoint
    by standpoint. Why: a model whose scale or depth units put every z out of range renders empty
    frames, and nothing downstream says the simulation, not the scene, is empty. Said once per run
    for all the standpoints it empties (one cause)."""

    frames: int = 0
    with_depth: int = 0
    empty: list[tuple[str, int]] = field(default_factory=list)

    def watch(self, frames: Iterable[FrameSet]) -> Iterator[FrameSet]:
        for fs in frames:
            self.frames += 1
            if not self.with_depth and fs.depth is not None and bool(np.any(fs.depth)):
                self.with_depth += 1  # one frame with depth is all that is asked: no scan after it
            yield fs

    def done(self, name: str) -> None:
        """The standpoint `name` is rendered: note it if none of its frames held depth."""
        if self.frames and not self.with_depth:
            self.empty.append((name, self.frames))
        self.frames = self.with_depth = 0

    def warn_if_empty(self, model: str) -> None:
        if not self.empty:
            return
        names = [n for n, _ in self.empty]
        where = names[0] if len(names) == 1 else f"{', '.join(names[:4])}{', ...' if len(names) > 4 else ''}"
        frames = f"its {self.empty[0][1]} frames" if len(names) == 1 else "their frames"
        warn(f"the simulation holds no depth in any of {frames}: model {model} renders nothing here (a "
             "depth scale, depth units or range that put every z out of range?)", where, "no-depth")


def model_label(given: SensorModel | str | Path, mdl: SensorModel) -> str:
    """How a warning names the model: the file or preset given, else its name."""
    return f"'{mdl.name}'" if isinstance(given, SensorModel) else f"'{given}'"


def stream_info_for(protocol: Protocol, model: SensorModel) -> StreamInfo:
    """The streams a protocol asks for, with the model's camera geometry."""
    st = protocol.streams
    return model.camera.stream_info(st.width, st.height, float(st.fps), infrared=st.infrared)


def render_frames(renderer: ViewRenderer, count: int, *, seed: int, start_ns: int, fps: float,
                  temperature_c: float = WARM_TEMPERATURE_C, workers: int = 2) -> Iterator[FrameSet]:
    """Frames of a static pose, in order; noise per frame from its own generator (seed, frame).

    Two threads sample frames concurrently (numpy releases the GIL on whole-image work); results
    stay identical to a serial run because every frame owns its random generator.
    """
    def one(i: int) -> FrameSet:
        rng = np.random.default_rng([seed, i])
        t_s = i / fps
        return renderer.frame(i, start_ns + round(t_s * 1e9), t_s, temperature_c, rng=rng)

    if workers <= 1:
        for i in range(count):
            yield one(i)
        return
    with ThreadPoolExecutor(workers) as pool:
        pending: deque[Future[FrameSet]] = deque()
        nxt = 0
        while nxt < count or pending:
            while nxt < count and len(pending) < 2 * workers:
                pending.append(pool.submit(one, nxt))
                nxt += 1
            yield pending.popleft().result()


def _select(protocol: Protocol, standpoints: Sequence[str | Standpoint] | None) -> list[Standpoint]:
    plan = protocol.plan.standpoints()
    if standpoints is None:
        return plan
    by_name = {s.name: s for s in plan}
    out = []
    names = [s if isinstance(s, str) else s.name for s in standpoints]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:   # one standpoint rendered twice would write its recording twice
        raise InputError(None, f"--standpoint {twice[0]} is given more than once")
    for s in standpoints:
        if isinstance(s, Standpoint):
            out.append(s)
        elif s in by_name:
            out.append(by_name[s])
        else:
            raise InputError(None, f"standpoint '{s}' is not in the plan of {protocol.name}")
    return out


def standpoint_record(board: Board, sp: Standpoint, pose: NDArray[Any], info: StreamInfo) -> dict[str, Any]:
    """The truth of one standpoint: poses of the depth and colour cameras, distance, inclination."""
    dist, inc = standpoint_truth(board, pose)
    color_pose = pose @ np.linalg.inv(info.depth_to_color.matrix)
    return {"name": sp.name, "trajectory": sp.trajectory, "side": sp.side,
            "target": {"distance_m": sp.distance_m, "inclination_deg": sp.inclination_deg},
            "distance_m": dist, "inclination_deg": inc,
            "depth_camera_to_board": pose.tolist(), "board_to_depth_camera": np.linalg.inv(pose).tolist(),
            "color_camera_to_board": color_pose.tolist()}


def simulate_checkerboard(protocol: Protocol | str | Path, model: SensorModel | str | Path, out_dir: Path, *,
                          fmt: str = "mcap", seed: int = 0, frames: int | None = None,
                          standpoints: Sequence[str | Standpoint] | None = None,
                          poses: dict[str, NDArray[Any]] | None = None, scene: Scene | None = None,
                          progress: bool = False, compression: str = "lz4") -> Path:
    """Render every (or the named) standpoint of a protocol into `out_dir`; returns out_dir.

    mcap: a capture session (session.json + <standpoint>.mcap, our format); db3: one RealSense
    recording per standpoint written by librealsense's recorder. Both get `truth.json`: the true
    depth- and colour-camera poses relative to the board, true distance and inclination, the
    model TOML and the seed. `poses` overrides the camera-to-board pose of named standpoints.
    """

    proto = protocol if isinstance(protocol, Protocol) else load_protocol(protocol)
    mdl = load_model(model)
    if fmt not in FORMATS:
        raise InputError(None, f"--format must be one of {', '.join(FORMATS)}, got '{fmt}'")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise InputError(out, "is not empty; simulations never overwrite captures")
    n_frames = frames if frames is not None else proto.plan.frames_per_standpoint
    if not 1 <= n_frames <= MAX_FRAMES_PER_STANDPOINT:  # a protocol's own bound: 1e8 filled the disk
        raise InputError(None, f"--frames must lie in 1..{MAX_FRAMES_PER_STANDPOINT} (an hour at 30 fps), "
                               f"got {n_frames}")
    check_seed(seed)
    try:
        info = stream_info_for(proto, mdl)
    except SimulationError as exc:   # a mode the camera lacks: say which file asked for it
        raise InputError(Path(proto.source) if proto.source else None,
                         f"[streams] width/height: {exc}") from exc
    sc = scene or board_scene(proto.board)
    renderer = ViewRenderer(sc, mdl, info, seed=seed, infrared=proto.streams.infrared,
                            color=proto.streams.color)
    chosen = _select(proto, standpoints)
    truth: dict[str, Any] = {"kind": "simulated-checkerboard", "protocol": proto.name, "seed": seed,
                             "frames_per_standpoint": n_frames, "format": fmt,
                             "board": proto.board.to_dict(), "stream_info": info.to_dict(),
                             "model_name": mdl.name, "model": mdl.to_toml(),
                             "scene": sc.meta, "standpoints": []}
    out.mkdir(parents=True, exist_ok=True)
    session = None
    if fmt == "mcap":

        session = Session.create(out, protocol=proto.to_dict(), device=info.device, simulated=True)
    fps = float(proto.streams.fps)
    bar = _bar(progress, len(chosen) * n_frames)
    tally = DepthTally()
    for k, sp in enumerate(chosen):
        pose = np.asarray((poses or {}).get(sp.name, standpoint_pose(proto.board, sp.distance_m,
                                                                     sp.inclination_deg, sp.side)))
        rec = standpoint_record(proto.board, sp, pose, info)
        renderer.set_pose(pose)
        start_ns = START_NS + k * 60_000_000_000
        frames_it = render_frames(renderer, n_frames, seed=seed * 100003 + k, start_ns=start_ns, fps=fps)
        frames_it = _ticking(frames_it, bar)
        frames_it = tally.watch(frames_it)
        meta = {"name": sp.name, "trajectory": sp.trajectory,
                "target": {"distance_m": sp.distance_m, "inclination_deg": sp.inclination_deg,
                           "side": sp.side},
                "truth": {"distance_m": rec["distance_m"], "inclination_deg": rec["inclination_deg"]}}
        if session is not None:
            with session.standpoint_writer(sp.name, info, meta, blocking=True, compression=compression,
                                           metadata={"simulation": {"seed": seed, "model": mdl.name}}) as w:
                w.write_temperature(start_ns, {"asic": WARM_TEMPERATURE_C, "projector": WARM_TEMPERATURE_C})
                for fs in frames_it:
                    w.write(fs)
            rec["file"] = f"{sp.name}.mcap"
        else:

            write_realsense_recording(out / f"{sp.name}.db3", info, frames_it)
            rec["file"] = f"{sp.name}.db3"
        tally.done(sp.name)
        truth["standpoints"].append(rec)
        write_json(out / TRUTH_FILE, truth)
    if bar is not None:
        bar[0].stop()
    tally.warn_if_empty(model_label(model, mdl))
    write_json(out / TRUTH_FILE, truth)
    return out


def _bar(enabled: bool, total: int) -> Any:
    if not enabled:
        return None

    p = progress()
    p.start()
    task = p.add_task("simulate", total=total, status="")
    return p, task


def _ticking(it: Iterator[FrameSet], bar: Any) -> Iterator[FrameSet]:
    for fs in it:
        if bar is not None:
            bar[0].advance(bar[1])
        yield fs


def load_truth(out_dir: Path) -> dict[str, Any]:
    """The truth.json of a simulated session or scan."""

    p = Path(out_dir) / TRUTH_FILE
    if not p.is_file():
        raise InputError(out_dir, f"no {TRUTH_FILE} (not a simulation output)")
    data: dict[str, Any] = json.loads(p.read_text())
    return data
