"""The reference-scan study as a pure pipeline: frames in, one grid (and optional per-frame grids)
out, in chunks of frames that can run in separate processes and merge (Chan) to the same result.

Why processes: Open3D's ray casting holds the GIL, so threads do not add; two processes with one
ray-casting thread each beat one process with two on a two-core machine (PERF-NOTES). Partial
grids are merged once per chunk, in chunk order, never per frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.errors import EvaluationError
from evaluate.grid import Grid
from evaluate.scan.raycast import STAT_NAMES, FrameImages, MeshCaster
from evaluate.scan.sequence import FrameSource, open_sequence
from evaluate.scan.trajectory import Trajectory

PER_FRAME_DIR = "frame_grids"


@dataclass(frozen=True)
class StudyConfig:
    """Grid bins, frame selection and pose matching; ray-casting threads per process."""

    distance_bin_m: float = 0.005
    inclination_bin_deg: float = 0.1
    distance_max_m: float = 6.0
    inclination_max_deg: float = 90.0
    every: int = 1
    max_frames: int | None = None
    tolerance_s: float = 0.01
    nthreads: int = 0
    per_frame_dir: Path | None = None

    def empty_grid(self) -> Grid:
        return Grid.empty(self.distance_bin_m, self.inclination_bin_deg, self.distance_max_m,
                          self.inclination_max_deg)


@dataclass
class ChunkResult:
    """A partial result: grid, pixel counts, and which frames were used or skipped why."""

    grid: Grid
    stats: NDArray[np.int64] = field(default_factory=lambda: np.zeros(len(STAT_NAMES), np.int64))
    used: list[int] = field(default_factory=list)
    no_pose: list[int] = field(default_factory=list)
    no_depth: list[int] = field(default_factory=list)

    def merge(self, other: ChunkResult) -> ChunkResult:
        self.grid.merge(other.grid)
        self.stats += other.stats
        self.used += other.used
        self.no_pose += other.no_pose
        self.no_depth += other.no_depth
        return self

    def summary(self) -> dict[str, Any]:
        return {"frames_used": len(self.used), "frames_skipped_no_pose": len(self.no_pose),
                "frames_skipped_no_depth": len(self.no_depth),
                "pixels": {k: int(v) for k, v in zip(STAT_NAMES, self.stats, strict=True)},
                "grid": self.grid.summary()}


FrameCallback = Callable[[int, Grid, NDArray[np.int64]], None]


def evaluate_chunk(caster: MeshCaster, source: FrameSource, trajectory: Trajectory, config: StudyConfig,
                   start: int = 0, limit: int | None = None,
                   on_frame: FrameCallback | None = None) -> ChunkResult:
    """Frames [start, start+limit) of the source, posed by `trajectory` (camera-to-reference)."""
    res = ChunkResult(config.empty_grid())
    units = source.info.depth_units_m
    intr = caster.intr
    frame_grid = res.grid.like() if config.per_frame_dir is not None else None
    for fs in source.frames(limit=limit, start=start):
        if fs.index % config.every:
            continue
        if config.max_frames is not None and fs.index >= config.max_frames * config.every:
            break
        if fs.depth is None:
            res.no_depth.append(fs.index)
            continue
        if fs.depth.shape != (intr.height, intr.width):
            raise EvaluationError(f"frame {fs.index}: depth {fs.depth.shape} does not match the "
                                  f"intrinsics {intr.width}x{intr.height}")
        pose = trajectory.match(fs.timestamp_ns * 1e-9, config.tolerance_s)
        if pose is None:
            res.no_pose.append(fs.index)
            continue
        if frame_grid is not None:
            frame_grid.count[:] = 0
            frame_grid.mean[:] = 0
            frame_grid.m2[:] = 0
        before = res.stats.copy()
        caster.bin_frame(pose, fs.depth, units, res.grid, res.stats, frame_grid)
        res.used.append(fs.index)
        if frame_grid is not None and config.per_frame_dir is not None:
            frame_grid.save(Path(config.per_frame_dir) / f"frame_{fs.index:06d}.npz", compressed=True)
        if on_frame is not None:
            on_frame(fs.index, res.grid, res.stats - before)
    return res


def frame_images(caster: MeshCaster, source: FrameSource, trajectory: Trajectory, index: int,
                 tolerance_s: float = 0.01) -> FrameImages | None:
    """Measured depth, reference depth and inclination maps of one frame (paper Fig. 8)."""
    for fs in source.frames(limit=1, start=index):
        pose = trajectory.match(fs.timestamp_ns * 1e-9, tolerance_s)
        if fs.depth is None or pose is None:
            return None
        return caster.images(pose, fs.depth, source.info.depth_units_m)
    return None


# -- processes -----------------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(source_spec: Path | FrameSource, mesh_path: Path, trajectory: Trajectory,
                 config: StudyConfig) -> None:
    source = open_sequence(source_spec) if isinstance(source_spec, (str, Path)) else source_spec
    _WORKER.update(source=source, trajectory=trajectory, config=config,
                   caster=MeshCaster(mesh_path, source.info.depth_intrinsics, config.nthreads))


def _run_chunk(start: int, limit: int) -> ChunkResult:
    w = _WORKER
    return evaluate_chunk(w["caster"], w["source"], w["trajectory"], w["config"], start, limit)


def chunk_ranges(frame_count: int, chunk_frames: int) -> list[tuple[int, int]]:
    return [(s, min(chunk_frames, frame_count - s)) for s in range(0, frame_count, chunk_frames)]


def run_study(source_spec: Path | FrameSource, mesh_path: Path, trajectory: Trajectory,
              config: StudyConfig, *, workers: int = 1, chunk_frames: int = 64,
              on_frame: FrameCallback | None = None,
              on_chunk: Callable[[int, int, ChunkResult], None] | None = None) -> ChunkResult:
    """The whole sequence: in-process for one worker, else chunks in `workers` processes.

    `source_spec` is a path (each worker opens it) or a picklable frame source; `trajectory`
    holds camera-to-reference poses (registration applied). Chunks merge in frame order, so the
    result does not depend on which worker finished first.
    """
    if config.per_frame_dir is not None:
        Path(config.per_frame_dir).mkdir(parents=True, exist_ok=True)
    source = open_sequence(source_spec) if isinstance(source_spec, (str, Path)) else source_spec
    n = source.frame_count
    if config.max_frames is not None:
        n = min(n, config.max_frames * config.every) if n is not None else config.max_frames * config.every
    if workers <= 1 or n is None:
        caster = MeshCaster(mesh_path, source.info.depth_intrinsics, config.nthreads)
        if on_frame is None and on_chunk is None:
            return evaluate_chunk(caster, source, trajectory, config, 0, n)
        total = ChunkResult(config.empty_grid())
        ranges = chunk_ranges(n, chunk_frames) if n is not None else [(0, None)]
        for k, (start, limit) in enumerate(ranges):
            part = evaluate_chunk(caster, source, trajectory, config, start, limit, on_frame)
            total.merge(part)
            if on_chunk is not None:
                on_chunk(k, len(ranges), total)
        return total

    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ranges = chunk_ranges(n, chunk_frames)
    total = ChunkResult(config.empty_grid())
    pending: dict[int, ChunkResult] = {}
    next_k = 0
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                             initializer=_init_worker,
                             initargs=(source_spec, Path(mesh_path), trajectory, config)) as pool:
        futures = {pool.submit(_run_chunk, s, lim): k for k, (s, lim) in enumerate(ranges)}
        for fut in as_completed(futures):
            pending[futures[fut]] = fut.result()
            while next_k in pending:
                total.merge(pending.pop(next_k))
                if on_chunk is not None:
                    on_chunk(next_k, len(ranges), total)
                next_k += 1
    return total
