"""The reference-scan study as a pure pipeline: frames in, one grid (and optional per-frame grids)
out. `evaluate_chunk` does frames [start, start + limit); `chunks.py` runs chunks on a ChunkRunner
and merges them (Chan) to the same result.

Why processes: the renderers hold one core each (the rasteriser is one thread, Open3D's ray
casting holds the GIL), so chunks run in processes; partial grids are merged once per chunk, in
chunk order, never per frame. Within a chunk each frame is merged into a cell-major accumulator
(`CellAccumulator`, one Chan merge per cell the frame touches), turned into the chunk's Grid at
its end, or, in one process, drained straight into the running grid (`ChunkCells`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import EvaluationError
from depthstation.core.frames import FrameSource
from depthstation.core.grid import FrameMoments, Grid
from depthstation.evaluate.scan.point_reference import PIXEL_NAMES, ReferenceCells
from depthstation.evaluate.scan.raycast import STAT_NAMES, CellAccumulator, FrameImages, FrameRenderer
from depthstation.evaluate.scan.trajectory import Trajectory

PER_FRAME_DIR = "frame_grids"
PIXEL_STATS = STAT_NAMES + PIXEL_NAMES  # the pass's counts, then a cloud's pixels left out by reason


@dataclass(frozen=True)
class StudyConfig:
    """Grid bins, frame selection and pose matching; the renderer ('raster' or 'raycast'),
    Open3D's ray-casting threads per process, and the mesh's unmeasured triangles (a file, so that
    worker processes read it as they read the mesh)."""

    distance_bin_m: float = 0.005
    inclination_bin_deg: float = 0.1
    distance_max_m: float = 6.0
    inclination_max_deg: float = 90.0
    every: int = 1
    max_frames: int | None = None
    tolerance_s: float = 0.01
    nthreads: int = 0
    per_frame_dir: Path | None = None
    renderer: str = "raster"
    unmeasured: Path | None = None  # per-triangle mask of reference surface nobody scanned (.npy)
    point_fits: Path | None = None  # a cloud's per-triangle planes fitted to its points (point_reference)

    def empty_grid(self) -> Grid:
        return Grid.empty(self.distance_bin_m, self.inclination_bin_deg, self.distance_max_m,
                          self.inclination_max_deg)


@dataclass
class ChunkCells:
    """A thread's accumulators, reused chunk after chunk in one process: the cells and frame
    moments, and the grid the chunk's result is written to.

    Why: a chunk's fresh 60 MB of accumulators (page faults) and their strided copy into a Grid
    cost ~0.1 s per chunk. The merge itself stays `Grid.merge`, so a study gives the same floats
    however it is run (command, batch item, workers)."""

    cells: CellAccumulator
    moments: FrameMoments
    grid: Grid

    @classmethod
    def for_grid(cls, grid: Grid) -> ChunkCells:
        return cls(CellAccumulator.for_grid(grid), FrameMoments.zeros(grid.shape), grid.like())

    def clear_moments(self) -> None:
        """After the chunk's grid was merged: its frame moments back to zero (the cells already are)."""
        for a in (self.moments.frames, self.moments.n2, self.moments.n2_mean, self.moments.n2_mean2):
            a.fill(0)


@dataclass
class ChunkResult:
    """A partial result: grid, pixel counts, and which frames were used or skipped why. A chunk run
    on reused `ChunkCells` keeps them in `cells` (its grid lives there) until merged."""

    grid: Grid
    stats: NDArray[np.int64] = field(default_factory=lambda: np.zeros(len(PIXEL_STATS), np.int64))
    used: list[int] = field(default_factory=list)
    no_pose: list[int] = field(default_factory=list)
    no_depth: list[int] = field(default_factory=list)
    cells: ChunkCells | None = None
    reference_u: ReferenceCells | None = None  # a cloud's reference sigma per cell (points mode)

    def merge(self, other: ChunkResult) -> ChunkResult:
        self.grid.merge(other.grid)
        if other.reference_u is not None:
            if self.reference_u is None:
                self.reference_u = ReferenceCells.zeros(other.reference_u.shape)
            self.reference_u.merge(other.reference_u)
        self.stats += other.stats
        self.used += other.used
        self.no_pose += other.no_pose
        self.no_depth += other.no_depth
        return self

    def summary(self) -> dict[str, Any]:
        return {"frames_used": len(self.used), "frames_skipped_no_pose": len(self.no_pose),
                "frames_skipped_no_depth": len(self.no_depth),
                "pixels": {k: int(v) for k, v in zip(PIXEL_STATS, self.stats, strict=True)},
                "grid": self.grid.summary()}


FrameCallback = Callable[[int, NDArray[np.int64]], None]  # (frame index, its pixel counts)


def evaluate_chunk(caster: FrameRenderer, source: FrameSource, trajectory: Trajectory, config: StudyConfig,
                   start: int = 0, limit: int | None = None,
                   on_frame: FrameCallback | None = None, reuse: ChunkCells | None = None) -> ChunkResult:
    """Frames [start, start+limit) of the source (positions in the sequence, 0-based), posed by
    `trajectory` (camera-to-reference); `used`, `no_pose`, `no_depth` hold positions.

    `reuse`: zeroed accumulators to add into; the result's grid and moments are theirs (merge it,
    then `reuse.clear_moments()`, before they serve another chunk)."""
    res = ChunkResult(config.empty_grid(), cells=reuse)
    units = source.info.depth_units_m
    intr = caster.intr
    acc = reuse if reuse is not None else ChunkCells.for_grid(res.grid)
    cells = acc.cells
    frame_cells = CellAccumulator.for_grid(res.grid) if config.per_frame_dir is not None else None
    moments = acc.moments  # frames as clusters: the honest SE of a cell mean
    # frames are counted by their position in the sequence (0-based), never by `fs.index`: a
    # RealSense recording numbers its frames from the device's counter (any start, with gaps), so
    # --frames, --every, the figure frame and the indices in summary.json would miss their frames
    for pos, fs in enumerate(source.frames(limit=limit, start=start), start):
        if pos % config.every:
            continue
        if config.max_frames is not None and pos >= config.max_frames * config.every:
            break
        if fs.depth is None:
            res.no_depth.append(pos)
            continue
        if fs.depth.shape != (intr.height, intr.width):
            raise EvaluationError(f"frame {pos} (device number {fs.index}): depth {fs.depth.shape} does not "
                                  f"match the intrinsics {intr.width}x{intr.height}")
        pose = trajectory.match(fs.timestamp_ns * 1e-9, config.tolerance_s)
        if pose is None:
            res.no_pose.append(pos)
            continue
        before = res.stats.copy()
        caster.bin_frame(pose, fs.depth, units, cells, res.stats, frame_cells, moments)
        res.used.append(pos)
        if frame_cells is not None and config.per_frame_dir is not None:
            path = Path(config.per_frame_dir) / f"frame_{pos:06d}.npz"
            frame_cells.to_grid().save(path, compressed=True)
            frame_cells.reset()
        if on_frame is not None:
            on_frame(pos, res.stats - before)
    res.grid = cells.to_grid() if reuse is None else cells.take_grid(reuse.grid)
    res.grid.moments = moments
    take = getattr(caster, "take_reference_cells", None)
    res.reference_u = take() if take is not None else None
    return res


def frame_images(caster: FrameRenderer, source: FrameSource, trajectory: Trajectory, index: int,
                 tolerance_s: float = 0.01) -> FrameImages | None:
    """Measured depth, reference depth and inclination maps of one frame (paper Fig. 8)."""
    for fs in source.frames(limit=1, start=index):
        pose = trajectory.match(fs.timestamp_ns * 1e-9, tolerance_s)
        if fs.depth is None or pose is None:
            return None
        return caster.images(pose, fs.depth, source.info.depth_units_m)
    return None


# a posed frame fits the reference when its depth agrees along the rays: a pixel is off when its
# error exceeds FIT_LIMIT_M or 4x Intel's expected noise (z^2 * 0.08 px / (f B)) at its distance
# (the nearer of measured and reference depth: a reference kilometres away must not widen it), and
# when most pixels with depth see no reference surface at all (axes or units of another frame)
FIT_LIMIT_M = 0.02
FIT_SHARE = 0.15
FIT_MISS_SHARE = 0.5
SUBPIXEL_PX = 0.08


@dataclass(frozen=True)
class FitCheck:
    """How well the posed depth lies on the reference along the rays (the study's own measure)."""

    frames: int
    pixels: int
    off_share: float         # share of pixels whose |error| exceeds their limit
    median_abs_error_m: float
    miss_share: float = 0.0  # share of the pixels with depth whose ray meets no reference surface

    @property
    def fits(self) -> bool:
        return self.off_share <= FIT_SHARE and self.miss_share <= FIT_MISS_SHARE

    def to_dict(self) -> dict[str, Any]:
        return {"frames": self.frames, "pixels": self.pixels, "off_share": self.off_share,
                "miss_share": self.miss_share, "median_abs_error_m": self.median_abs_error_m,
                "fits": self.fits,
                "rule": f"a pixel is off when |measured - reference| > max({FIT_LIMIT_M} m, 4 z^2 "
                        f"{SUBPIXEL_PX} px / (f B)), z the nearer of measured and reference depth; the "
                        f"trajectory fits when at most {FIT_SHARE:.0%} are and at most "
                        f"{FIT_MISS_SHARE:.0%} of the pixels with depth miss the reference"}


@dataclass(frozen=True)
class FitSample:
    """The frames a fit check looks at (time stamp and depth), read in one pass over the sequence,
    so that checking another reading of the poses costs renders, not passes over the file."""

    timestamps_s: tuple[float, ...]
    depths: tuple[NDArray[Any], ...]


def fit_sample(source: FrameSource, frames: int = 10) -> FitSample:
    """`frames` frames spread over the sequence (positions by linspace), with depth."""
    n = source.frame_count or 0
    picks = sorted({round(i) for i in np.linspace(0, max(n - 1, 0), frames)}) if n else list(range(frames))
    want = set(picks)
    stamps: list[float] = []
    depths: list[NDArray[Any]] = []
    for pos, fs in enumerate(source.frames(limit=max(picks) + 1 if picks else 0)):
        if pos in want and fs.depth is not None:
            stamps.append(fs.timestamp_ns * 1e-9)
            depths.append(np.array(fs.depth, copy=True))
    return FitSample(tuple(stamps), tuple(depths))


def fit_check(caster: FrameRenderer, source: FrameSource, trajectory: Trajectory, *, frames: int = 10,
              tolerance_s: float = 0.01, sample: FitSample | None = None) -> FitCheck | None:
    """Cast `frames` frames spread over the sequence (or the `sample` given) and count the pixels
    that miss the reference by more than the depth noise explains; None when no frame has a pose."""
    sample = sample if sample is not None else fit_sample(source, frames)
    intr = caster.intr
    fb = intr.fx * (source.info.baseline_m or 0.05)
    units = source.info.depth_units_m
    off = total = used = measured = missed = 0
    errors: list[NDArray[np.float32]] = []
    for t_s, depth in zip(sample.timestamps_s, sample.depths, strict=True):
        pose = trajectory.match(t_s, tolerance_s)
        if pose is None:
            continue
        images = caster.images(pose, depth, units)
        has_depth = np.isfinite(images.measured_m) & ~images.unmeasured  # the grid's pixels only
        ok = has_depth & np.isfinite(images.reference_m)
        measured += int(np.count_nonzero(has_depth))
        missed += int(np.count_nonzero(has_depth & ~ok))
        z = np.minimum(images.reference_m[ok], images.measured_m[ok])
        err = np.abs(images.error_m[ok])
        limit = np.maximum(FIT_LIMIT_M, 4 * z * z * SUBPIXEL_PX / fb)
        off += int(np.count_nonzero(err > limit))
        total += int(err.size)
        errors.append(err[:: max(1, err.size // 20000)])
        used += 1
    if used == 0 or measured == 0:
        return None
    if total == 0:  # depth everywhere, a reference nowhere
        return FitCheck(used, 0, 0.0, float("nan"), 1.0)
    return FitCheck(used, total, off / total, float(np.median(np.concatenate(errors))), missed / measured)
