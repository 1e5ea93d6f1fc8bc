"""The checkerboard study in chunks on a ChunkRunner: one standpoint per task.

Why a standpoint per task: its frames must be averaged into one pose before accuracy, so a
standpoint is the smallest independent piece. Only the recording's path and the options travel;
the worker reads the frames. In one process the recordings already open are used, with a callback
per frame (progress, the live rerun view).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from depthstation.core.board import Board
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.frames import FrameSet
from depthstation.core.parallel import ChunkRunner, ProgressFn
from depthstation.evaluate.checkerboard.frame import FrameResult
from depthstation.evaluate.checkerboard.study import DEFAULT_FRAMES, StandpointResult, evaluate_recording

REFERENCES = ("auto", "average", "frame")


@dataclass(frozen=True)
class StandpointOptions:
    """How each standpoint is evaluated (the keyword options of `evaluate_recording`)."""

    frames: int | None = None  # asked for (short standpoints warned); None: up to `up_to`, not warned
    up_to: int = DEFAULT_FRAMES  # frames read when none were asked for
    reference: str = "auto"
    collect_samples: bool = False
    sample_stride: int = 1
    refine: bool = True
    margin_m: float = 0.01
    topics: TopicChoice | None = None  # which topics of a ROS recording (None: found automatically)
    roi: float | None = None           # the Depth Quality Tool's centred ROI, fraction of each side


@dataclass(frozen=True)
class CheckerboardChunk:
    """One standpoint: the recording's path (opened and read by the worker) and the study options."""

    path: str
    board: Board
    options: StandpointOptions = field(default_factory=StandpointOptions)


def evaluate(rec: Recording, board: Board, options: StandpointOptions,
             on_frame: Callable[[FrameSet, FrameResult], None] | None = None) -> StandpointResult:
    o = options
    return evaluate_recording(rec, board, frames=o.frames, up_to=o.up_to, reference=o.reference,
                              collect_samples=o.collect_samples, sample_stride=o.sample_stride,
                              refine=o.refine, margin_m=o.margin_m, on_frame=on_frame, roi=o.roi)


def checkerboard_chunk(chunk: CheckerboardChunk) -> StandpointResult:
    """StandpointResult of one standpoint, evaluated where it is read."""
    return evaluate(open_recording(Path(chunk.path), topics=chunk.options.topics), chunk.board, chunk.options)


StandpointCallback = Callable[[int, StandpointResult], None]
FrameHook = Callable[[Recording], Callable[[FrameSet, FrameResult], None] | None]


def run_standpoints(recordings: Sequence[Recording], board: Board, options: StandpointOptions,
                    runner: ChunkRunner, *, on_frame: FrameHook | None = None,
                    on_standpoint: StandpointCallback | None = None,
                    progress: ProgressFn | None = None, threads: int | None = None) -> list[StandpointResult]:
    """Every standpoint in input order: here on the open recordings (`on_frame(rec)` gives each
    one's per-frame callback), or one task per standpoint on the runner's workers.

    Here, standpoints run on `threads` threads (default: the cores this process may use, at most
    one per standpoint): decoding, OpenCV and the numba kernels release the GIL, so a second
    thread adds ~1.4x on two cores without starting processes. Standpoints are independent, so
    the results are the same for any thread count; callbacks come from the worker threads.
    """
    results: list[StandpointResult] = []
    if runner.in_process:
        n = threads if threads is not None else min(len(os.sched_getaffinity(0)), len(recordings))
        if n <= 1:
            for i, rec in enumerate(recordings):
                results.append(evaluate(rec, board, options, on_frame(rec) if on_frame else None))
                if on_standpoint is not None:
                    on_standpoint(i, results[-1])
                if progress is not None:
                    progress(i + 1, len(recordings))
            return results
        with ThreadPoolExecutor(n) as pool:
            futures = [pool.submit(evaluate, rec, board, options, on_frame(rec) if on_frame else None)
                       for rec in recordings]
            for i, fut in enumerate(futures):
                results.append(fut.result())
                if on_standpoint is not None:
                    on_standpoint(i, results[-1])
                if progress is not None:
                    progress(i + 1, len(recordings))
        return results
    chunks = [CheckerboardChunk(str(r.path), board, options) for r in recordings]
    results = runner.map(checkerboard_chunk, chunks, progress=progress or _quiet)
    for i, r in enumerate(results):
        if on_standpoint is not None:
            on_standpoint(i, r)
    return results


def _quiet(done: int, total: int) -> None:
    return None
