"""The reference-scan study in chunks of frames on a ChunkRunner: what travels, what comes back.

Why chunks: a sequence is read and ray cast where it is evaluated, frames [start, start + limit)
per task; only paths, poses and options travel, and a partial grid comes back as its non-empty
cells. Chunks merge (Chan) in frame order, so one process, local processes and a Dask cluster give
the same grid. In one process the chunks run on the recording that is already open, with a
callback per frame (progress, the live rerun view).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from itertools import islice
from pathlib import Path
from queue import Empty, Queue

import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet, FrameSource
from depthstation.core.grid import PackedGrid, pack_grid, unpack_grid
from depthstation.core.parallel import ChunkRunner, ProgressFn
from depthstation.evaluate.scan.point_reference import PointFitRenderer, ReferenceCells, with_point_fits
from depthstation.evaluate.scan.rasterise import MeshRasteriser, make_renderer
from depthstation.evaluate.scan.raycast import FrameRenderer
from depthstation.evaluate.scan.reference import load_unmeasured
from depthstation.evaluate.scan.study import (
    ChunkCells,
    ChunkResult,
    FrameCallback,
    StudyConfig,
    evaluate_chunk,
)
from depthstation.evaluate.scan.trajectory import Trajectory


@dataclass(frozen=True)
class ScanChunk:
    """Frames [start, start+limit) of a sequence: a path (or a small picklable source) and the
    camera-to-reference poses travel; the pixels are read by the worker."""

    sequence: str | FrameSource
    mesh: str
    trajectory: Trajectory  # camera-to-reference (registration applied)
    config: StudyConfig
    start: int
    limit: int | None  # None: to the end (a sequence that does not say its length)
    intrinsics: str | None = None
    topics: TopicChoice | None = None  # ROS recordings: the topics it was opened with


@dataclass
class _WorkerCache:
    """One open sequence and one renderer per worker process, reused by its following chunks:
    the mesh is loaded once per worker, not per chunk; only one of each is kept (bounded memory)."""

    source_key: object = None
    source: FrameSource | None = None
    mesh_key: object = None
    caster: FrameRenderer | None = None


_CACHE = _WorkerCache()


def clear_cache() -> None:
    """Forget the kept sequence and renderer, so that the next study of this process opens its
    sequence and reads and prepares its mesh again, as a command does (benchmarks time that)."""
    _CACHE.source_key = _CACHE.source = _CACHE.mesh_key = _CACHE.caster = None


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".pgm", ".ppm")


def _file_key(path: str | Path) -> object:
    """A path with its size and modification time: a file rewritten in place is not the one kept.
    A folder (TUM, PNG sequence) by its entries' too: its own time does not move when a list or
    camera file in it is rewritten in place."""
    p = Path(path)
    try:
        st = p.stat()
        if p.is_dir():
            # lists and camera files, not the frames' images (read afresh each time; thousands of them)
            stats = {e.name: e.stat() for e in os.scandir(p) if not e.name.lower().endswith(IMAGE_SUFFIXES)}
            entries = tuple(sorted((name, s.st_size, s.st_mtime_ns) for name, s in stats.items()))
            return (str(path), st.st_mtime_ns, entries)
    except OSError:
        return str(path)
    return (str(path), st.st_size, st.st_mtime_ns)


def renderer_for(mesh: str | Path, intr: Intrinsics, config: StudyConfig) -> FrameRenderer:
    """The renderer of `config` over `mesh` for frames of `intr`, kept for the next chunks (and the
    report's figure frame) of this process: the mesh is loaded and prepared once (again when the
    file changed)."""
    key = (_file_key(mesh), intr, config.nthreads, config.renderer,
           None if config.unmeasured is None else _file_key(config.unmeasured),
           None if config.point_fits is None else _file_key(config.point_fits))
    if _CACHE.caster is None or _CACHE.mesh_key != key:
        _CACHE.caster = None
        _CACHE.caster = new_renderer(mesh, intr, config)
        _CACHE.mesh_key = key
    return _CACHE.caster


def new_renderer(mesh: str | Path, intr: Intrinsics, config: StudyConfig) -> FrameRenderer:
    """A fresh renderer of `config` over `mesh`, with the mesh's unmeasured triangles marked."""
    renderer = make_renderer(config.renderer, Path(mesh), intr, config.nthreads)
    if config.unmeasured is not None:
        renderer.mark_unmeasured(load_unmeasured(Path(config.unmeasured), renderer.n_triangles))
    if config.point_fits is not None:  # a cloud measured against its points (point_reference)
        return with_point_fits(renderer, Path(config.point_fits))
    return renderer


def _context(chunk: ScanChunk) -> tuple[FrameRenderer, FrameSource]:
    source: FrameSource
    if isinstance(chunk.sequence, str):
        key: object = (_file_key(chunk.sequence), chunk.intrinsics, chunk.topics)
        if _CACHE.source is None or _CACHE.source_key != key:
            intr = Path(chunk.intrinsics) if chunk.intrinsics else None
            _CACHE.source = open_recording(Path(chunk.sequence), intrinsics=intr, topics=chunk.topics)
            _CACHE.source_key = key
        source = _CACHE.source
    else:
        source = chunk.sequence
    return renderer_for(chunk.mesh, source.info.depth_intrinsics, chunk.config), source


def scan_chunk(chunk: ScanChunk) -> ChunkResult:
    """Partial scan result (grid + pixel counts + frames used) of one chunk, on the worker."""
    caster, source = _context(chunk)
    return evaluate_chunk(caster, source, chunk.trajectory, chunk.config, chunk.start, chunk.limit)


@dataclass
class PackedScanResult:
    grid: PackedGrid
    stats: NDArray[np.int64]
    used: list[int]
    no_pose: list[int]
    no_depth: list[int]
    reference_u: ReferenceCells | None = None


def pack_scan_result(res: ChunkResult) -> PackedScanResult:
    return PackedScanResult(pack_grid(res.grid), res.stats, res.used, res.no_pose, res.no_depth,
                            res.reference_u)


def unpack_scan_result(p: PackedScanResult) -> ChunkResult:
    return ChunkResult(unpack_grid(p.grid), p.stats, p.used, p.no_pose, p.no_depth,
                       reference_u=p.reference_u)


def merge_scan_results(a: ChunkResult, b: ChunkResult) -> ChunkResult:
    return a.merge(b)


def chunk_ranges(frame_count: int, chunk_frames: int) -> list[tuple[int, int]]:
    """(start, limit) of consecutive chunks of `chunk_frames` frames."""
    if chunk_frames < 1:
        raise InputError(None, f"chunk size must be at least 1 frame, got {chunk_frames}")
    return [(s, min(chunk_frames, frame_count - s)) for s in range(0, frame_count, chunk_frames)]


def frames_to_read(source: FrameSource, config: StudyConfig) -> int | None:
    """How many frames of the source the study reads (None when the source does not say)."""
    n = source.frame_count
    if config.max_frames is not None:
        cap = config.max_frames * config.every
        n = cap if n is None else min(n, cap)
    return n


def scan_chunks(sequence: Path | FrameSource, mesh: Path, trajectory: Trajectory, config: StudyConfig, *,
                chunk_frames: int = 64, intrinsics: Path | None = None,
                source: FrameSource | None = None, topics: TopicChoice | None = None) -> list[ScanChunk]:
    """The chunks of a scan evaluation (the frame count comes from the sequence's index only).

    `source`: the sequence already opened (so it is not opened again here).
    """
    if source is None:
        source = (open_recording(sequence, intrinsics=intrinsics, topics=topics) if isinstance(sequence, Path)
                  else sequence)
    n = frames_to_read(source, config)
    ranges: list[tuple[int, int | None]] = [(0, None)] if n is None else list(chunk_ranges(n, chunk_frames))
    spec: str | FrameSource = str(sequence) if isinstance(sequence, Path) else sequence
    return [ScanChunk(spec, str(mesh), trajectory, config, s, lim,
                      None if intrinsics is None else str(intrinsics), topics) for s, lim in ranges]


ChunkCallback = Callable[[int, int, ChunkResult], None]


def run_scan_chunks(sequence: Path | FrameSource, mesh: Path, trajectory: Trajectory, config: StudyConfig,
                    runner: ChunkRunner, *, chunk_frames: int = 64, intrinsics: Path | None = None,
                    topics: TopicChoice | None = None, source: FrameSource | None = None,
                    on_frame: FrameCallback | None = None,
                    on_chunk: ChunkCallback | None = None, progress: ProgressFn | None = None) -> ChunkResult:
    """The study over the whole sequence, chunk by chunk on `runner`, merged in frame order.

    In one process the chunks read the open `source` (or `sequence` when it is a frame source)
    and call `on_frame` after every frame; on workers each chunk is read where it runs and only
    `progress(done, total)` reports. `on_chunk(k, n, merged so far)` follows every merge.
    """
    if config.per_frame_dir is not None:
        Path(config.per_frame_dir).mkdir(parents=True, exist_ok=True)
    chunks = scan_chunks(sequence, mesh, trajectory, config, chunk_frames=chunk_frames,
                         intrinsics=intrinsics, source=source, topics=topics)
    chunks = split_last(chunks)
    merges = [0]

    def merge(a: ChunkResult, b: ChunkResult) -> ChunkResult:
        if merges[0] == 0 and on_chunk is not None:
            on_chunk(0, len(chunks), a)
        merges[0] += 1
        out = a.merge(b)
        if on_chunk is not None:
            on_chunk(merges[0], len(chunks), out)
        return out

    if runner.in_process:
        open_source = source if source is not None else (
            sequence if not isinstance(sequence, Path)
            else open_recording(sequence, intrinsics=intrinsics, topics=topics))
        result = _run_here(open_source, mesh, chunks, config, merge, on_frame, progress or _quiet)
    else:
        if chunks[0].limit is None:
            raise InputError(sequence if isinstance(sequence, Path) else None,
                             "the sequence does not say how many frames it holds (cut short?); "
                             "cannot split it for workers: evaluate it with one worker")
        result = runner.reduce(scan_chunk, chunks, merge, progress=progress or _quiet,
                               encode=pack_scan_result, decode=unpack_scan_result)
    if merges[0] == 0 and on_chunk is not None:  # one chunk: nothing was merged
        on_chunk(0, len(chunks), result)
    return result


def _quiet(done: int, total: int) -> None:
    return None


TAPER_FRAMES = 8  # the smallest piece `split_last` cuts


def taper(frames: int, smallest: int = TAPER_FRAMES) -> list[int]:
    """A chunk of `frames` cut into halving pieces down to `smallest` (64 -> 32, 16, 8, 8)."""
    pieces = []
    rest = frames
    while rest > smallest:
        piece = (rest + 1) // 2
        pieces.append(piece)
        rest -= piece
    if rest:
        pieces.append(rest)
    return pieces


def split_last(chunks: list[ScanChunk]) -> list[ScanChunk]:
    """The study's chunks: the frames of the last two cut into halving pieces (`taper`).

    Why: chunks run a thread (or process) each, taken as each frees, and the cores finish together
    only if the last pieces are short. With whole chunks to the end one core ran the last chunk
    while the other idled; halves of the last chunk still left 0.65 s of a 29 s study to one core
    (1334 frames in chunks of 64 on 2 cores). The cores reach the tail up to a chunk apart, so the
    taper starts a chunk earlier (118 frames -> 59, 30, 15, 7, 7): three more merges. The rule does
    not depend on threads or processes, so every way of running a study (command, batch item,
    workers) merges the same chunks in the same order: the same floats."""
    if not chunks or any(c.limit is None for c in chunks[-2:]):
        return chunks
    tail = chunks[-2:]
    frames = sum(c.limit or 0 for c in tail)
    out = chunks[:-2]
    start = tail[0].start
    for piece in taper(frames):
        out.append(replace(tail[0], start=start, limit=piece))
        start += piece
    return out


@dataclass
class _ChunkFrames:
    """The frame sets of one chunk, taken from the one pass over the open sequence (a FrameSource):
    the sequence's frames [offset, offset + len(items)), addressed by their positions in it."""

    name: str
    info: StreamInfo
    items: list[FrameSet]
    offset: int = 0

    @property
    def frame_count(self) -> int:
        return self.offset + len(self.items)

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        if start < self.offset:
            raise ValueError(f"frames before {self.offset} are not in this chunk")
        items = self.items[start - self.offset:]
        return iter(items if limit is None else items[:limit])


def _threads(config: StudyConfig, chunks: int) -> int:
    """Chunks evaluated side by side in this process: the rasteriser is one thread, so up to the
    cores it may use (`nthreads`, 0 = all); Open3D's ray casting uses its own threads."""
    if config.renderer != "raster":
        return 1
    n = config.nthreads or len(os.sched_getaffinity(0))
    return max(1, min(n, chunks))


def _run_here(source: FrameSource, mesh: str | Path, chunks: list[ScanChunk], config: StudyConfig,
              merge: Callable[[ChunkResult, ChunkResult], ChunkResult], on_frame: FrameCallback | None,
              progress: ProgressFn) -> ChunkResult:
    """The chunks in this process: the sequence is read once, in order (a chunk's frames are
    taken where the previous chunk stopped, not re-read from the start), and the chunks are
    evaluated on `_threads` threads, each with its own renderer (the kernels release the GIL);
    results are merged in chunk order, so the grid is the same for any thread count."""
    n = _threads(config, len(chunks))
    intr = source.info.depth_intrinsics
    renderers: Queue[FrameRenderer] = Queue()
    base = renderer_for(mesh, intr, config)
    renderers.put(base)
    for _ in range(n - 1):
        renderers.put(base.sibling() if isinstance(base, MeshRasteriser) or (
            isinstance(base, PointFitRenderer) and isinstance(base.inner, MeshRasteriser))
                      else new_renderer(mesh, intr, config))
    frames = iter(source.frames())
    spare: Queue[ChunkCells] = Queue()  # accumulators drained by `fold`, for the next chunks

    def evaluate(c: ScanChunk, items: list[FrameSet]) -> ChunkResult:
        r = renderers.get()
        try:  # never wait: the drained ones come back only as the main thread folds in order
            cells = spare.get_nowait()
        except Empty:
            cells = ChunkCells.for_grid(config.empty_grid())
        try:
            return evaluate_chunk(r, _ChunkFrames(source.name, source.info, items, c.start), c.trajectory,
                                  c.config, c.start, None, on_frame, reuse=cells)
        finally:
            renderers.put(r)

    acc: list[ChunkResult] = []
    done = [0]

    def fold(res: ChunkResult) -> None:
        if not acc:  # the first chunk becomes the running result (a grid of its own)
            acc.append(ChunkResult(config.empty_grid().with_frame_moments()).merge(res))
        else:
            merge(acc[0], res)
        if res.cells is not None:  # merged: its accumulators serve the next chunk
            res.cells.clear_moments()
            spare.put(res.cells)
            res.cells = None
        done[0] += 1
        progress(done[0], len(chunks))

    progress(0, len(chunks))
    with ThreadPoolExecutor(n) as pool:
        pending: deque[Future[ChunkResult]] = deque()
        for c in chunks:
            items = list(frames) if c.limit is None else list(islice(frames, c.limit))
            pending.append(pool.submit(evaluate, c, items))
            while len(pending) > n:
                fold(pending.popleft().result())
        while pending:
            fold(pending.popleft().result())
    return acc[0]
