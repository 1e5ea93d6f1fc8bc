"""Run chunks of an evaluation serially, in local processes, or on a Dask cluster, and merge.

Why three paths behind one call: the maths is the same whatever runs it, so the commands pass a
chunk function and a list of small chunk descriptors (recording path + frame range, never
pixels) and choose only *where* it runs:

- ``workers=1, cluster=None``: in this process, no pool, no pickling (tests, small jobs).
- ``workers=N, cluster=None``: N local processes through :class:`concurrent.futures.
  ProcessPoolExecutor`. Chosen over a Dask ``LocalCluster`` because it starts in milliseconds
  instead of seconds, needs no extra package (the single-machine path must not import Dask),
  and what a chunk returns (a partial grid) goes back over one pipe without a scheduler hop. A
  worker that dies (killed, out of memory) breaks the pool; the pool is rebuilt and the chunks
  that had not finished are submitted again.
- ``cluster="tcp://host:port"``: an existing Dask distributed scheduler. Dask is imported only
  here. Dask re-runs the task of a worker that dies (up to its ``allowed-failures``).

Each chunk is read and evaluated by the worker that receives it, so every frame is read once.
Memory stays bounded: at most ``2 x workers`` chunks are in flight locally, results are folded
into the running merge as they arrive when a ``merge`` is given, and a result that arrives out
of order waits only until its predecessors are in. Results are merged in chunk order whatever
order they finish in, so the outcome is the same float for float on every path.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Generic, TypeVar

from depthstation.core.errors import DepthstationError, InputError
from depthstation.core.progress import progress

C = TypeVar("C")
R = TypeVar("R")

#: How often the local path rebuilds a broken pool before it gives up on a chunk.
MAX_RETRIES = 3


class WorkerLost(DepthstationError):
    """A chunk kept killing the worker that ran it; retrying would not help."""


@dataclass(frozen=True)
class FrameChunk:
    """What travels to a worker: where to read and which frames, not the pixels themselves."""

    path: str
    start: int
    stop: int
    index: int = 0

    @property
    def frames(self) -> int:
        return self.stop - self.start


def frame_chunks(path: str | Path, frame_count: int, chunk_frames: int) -> list[FrameChunk]:
    """Split ``frame_count`` frames of one recording into consecutive ranges of ``chunk_frames``."""
    if chunk_frames < 1:
        raise InputError(None, f"chunk size must be at least 1 frame, got {chunk_frames}")
    return [FrameChunk(str(path), s, min(s + chunk_frames, frame_count), i)
            for i, s in enumerate(range(0, frame_count, chunk_frames))]


ProgressFn = Callable[[int, int], None]


def _no_progress(done: int, total: int) -> None:
    return None


@dataclass
class _Call(Generic[C, R]):
    """Picklable wrapper that runs ``fn`` then ``encode`` on the worker (e.g. a sparse grid)."""

    fn: Callable[[C], Any]
    encode: Callable[[Any], Any] | None

    def __call__(self, chunk: C) -> Any:
        out = self.fn(chunk)
        return out if self.encode is None else self.encode(out)


class _OrderedFold(Generic[R]):
    """Collect results by index; fold them in index order as soon as the prefix is complete."""

    def __init__(self, total: int, merge: Callable[[R, R], R] | None) -> None:
        self.total = total
        self.merge = merge
        self.pending: dict[int, R] = {}
        self.results: list[R] = []
        self.acc: R | None = None
        self.next = 0
        self.done = 0

    def add(self, index: int, value: R) -> None:
        self.pending[index] = value
        self.done += 1
        while self.next in self.pending:
            item = self.pending.pop(self.next)
            if self.merge is None:
                self.results.append(item)
            else:
                self.acc = item if self.next == 0 else self.merge(self.acc, item)  # type: ignore[arg-type]
            self.next += 1


def _mp_context() -> Any:
    """forkserver on Linux: no fork of a process that runs threads (rich, numba, Open3D)."""

    if sys.platform.startswith("linux"):
        return mp.get_context("forkserver")
    return mp.get_context("spawn")


_CLUSTER_ADDRESS = re.compile(r"^(?:(?:tcp|tls|ucx|ws|wss)://)?[A-Za-z0-9_.\-]+:\d{1,5}$"
                              r"|^(?:tcp|tls|ucx|ws|wss|inproc)://\S+$")


def check_cluster_address(address: str) -> None:
    """A Dask scheduler address is `[tcp://]host:port`: anything else is refused before any work (Dask
    took 'notanaddress' for a host, waited its timeout and failed with a traceback)."""
    if not _CLUSTER_ADDRESS.match(address):
        raise InputError(None, f"--cluster '{address}' is not a Dask scheduler address (tcp://host:port)")


class ChunkRunner(AbstractContextManager["ChunkRunner"]):
    """Holds a process pool or a Dask client open across several runs (a whole batch)."""

    def __init__(self, workers: int = 1, cluster: str | None = None) -> None:
        if workers < 1:
            raise InputError(None, f"--workers must be at least 1, got {workers}")
        if cluster is not None:
            check_cluster_address(cluster)
        self.workers = workers
        self.cluster = cluster
        self._pool: ProcessPoolExecutor | None = None
        self._client: Any = None

    # -- lifecycle -------------------------------------------------------------------------
    def __enter__(self) -> ChunkRunner:
        if self.cluster is not None:
            self._client = _dask_client(self.cluster)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None

    @property
    def in_process(self) -> bool:
        """Chunks run here, one after the other (callbacks may be closures, nothing is pickled)."""
        return self.cluster is None and self.workers == 1

    @property
    def kind(self) -> str:
        if self.cluster is not None:
            return f"dask {self.cluster}"
        return "serial" if self.workers == 1 else f"{self.workers} processes"

    # -- running ---------------------------------------------------------------------------
    def map(self, fn: Callable[[C], R], chunks: Sequence[C], *, progress: ProgressFn = _no_progress,
            encode: Callable[[R], Any] | None = None,
            decode: Callable[[Any], R] | None = None) -> list[R]:
        """Results of ``fn`` on every chunk, in chunk order."""
        fold: _OrderedFold[R] = _OrderedFold(len(chunks), None)
        self._run(fn, chunks, fold, progress, encode, decode)
        return fold.results

    def reduce(self, fn: Callable[[C], R], chunks: Sequence[C], merge: Callable[[R, R], R], *,
               progress: ProgressFn = _no_progress, encode: Callable[[R], Any] | None = None,
               decode: Callable[[Any], R] | None = None) -> R:
        """``merge(merge(r0, r1), r2) ...`` in chunk order, folded while chunks arrive."""
        if not chunks:
            raise InputError(None, "nothing to evaluate (no chunks)")
        fold: _OrderedFold[R] = _OrderedFold(len(chunks), merge)
        self._run(fn, chunks, fold, progress, encode, decode)
        return fold.acc  # type: ignore[return-value]

    def _run(self, fn: Callable[[C], R], chunks: Sequence[C], fold: _OrderedFold[R],
             progress: ProgressFn, encode: Callable[[R], Any] | None,
             decode: Callable[[Any], R] | None) -> None:
        progress(0, len(chunks))
        if not chunks:
            return
        if self.cluster is not None:
            self._run_dask(fn, chunks, fold, progress, encode, decode)
        elif self.workers == 1:
            for i, chunk in enumerate(chunks):
                fold.add(i, fn(chunk))
                progress(fold.done, len(chunks))
        else:
            self._run_local(fn, chunks, fold, progress, encode, decode)

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=_mp_context())
        return self._pool

    def _run_local(self, fn: Callable[[C], R], chunks: Sequence[C], fold: _OrderedFold[R],
                   progress: ProgressFn, encode: Callable[[R], Any] | None,
                   decode: Callable[[Any], R] | None) -> None:
        call: _Call[C, R] = _Call(fn, encode)
        todo: list[int] = list(range(len(chunks)))[::-1]  # a stack, next chunk at the end
        tries = [0] * len(chunks)
        window = 2 * self.workers  # bounded: chunks queued or running at once
        running: dict[Future[Any], int] = {}
        while todo or running:
            pool = self._ensure_pool()
            try:
                while todo and len(running) < window:
                    i = todo.pop()
                    tries[i] += 1
                    running[pool.submit(call, chunks[i])] = i
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    value = fut.result()  # raises BrokenProcessPool or the chunk's own error
                    i = running.pop(fut)
                    fold.add(i, value if decode is None else decode(value))
                    progress(fold.done, len(chunks))
            except BrokenProcessPool:
                # A worker died: every future of this pool is lost. Collect what did finish,
                # rebuild the pool and put the rest back on the stack in their original order.
                lost: list[int] = []
                for fut, i in running.items():
                    if fut.done() and fut.exception() is None:
                        value = fut.result()
                        fold.add(i, value if decode is None else decode(value))
                    else:
                        lost.append(i)
                running.clear()
                if self._pool is not None:
                    self._pool.shutdown(wait=False, cancel_futures=True)
                    self._pool = None
                bad = [i for i in lost if tries[i] > MAX_RETRIES]
                if bad:
                    msg = (f"chunk {bad[0]} lost its worker {tries[bad[0]]} times "
                           "(killed or out of memory); giving up")
                    raise WorkerLost(msg) from None
                todo.extend(sorted(lost, reverse=True))
                progress(fold.done, len(chunks))
            except BaseException:
                for fut in running:
                    fut.cancel()
                if self._pool is not None:
                    self._pool.shutdown(wait=False, cancel_futures=True)
                    self._pool = None
                raise

    def _run_dask(self, fn: Callable[[C], R], chunks: Sequence[C], fold: _OrderedFold[R],
                  progress: ProgressFn, encode: Callable[[R], Any] | None,
                  decode: Callable[[Any], R] | None) -> None:
        from distributed import as_completed

        client = self._client
        if client is None:
            client = self._client = _dask_client(self.cluster or "")
        call: _Call[C, R] = _Call(fn, encode)
        futures = client.map(call, list(chunks), pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures, loop=client.loop):
                value = fut.result()
                fold.add(index[fut.key], value if decode is None else decode(value))
                fut.release()  # the worker may forget the result now: bounded memory
                progress(fold.done, len(chunks))
        except BaseException:
            client.cancel(futures)
            raise


def _dask_client(address: str) -> Any:
    """Connect to an existing scheduler; a clear one-line error when Dask or the cluster is absent."""
    try:
        from distributed import Client
    except ImportError as exc:
        msg = "--cluster needs Dask distributed: pip install 'depthstation[cluster]'"
        raise InputError(None, msg) from exc
    try:
        return Client(address, timeout=int(os.environ.get("DEPTHSTATION_CLUSTER_TIMEOUT", "20")),
                      set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(None, f"cannot reach the Dask scheduler at {address} ({exc})") from exc


def run_chunks(fn: Callable[[C], R], chunks: Sequence[C], *, workers: int = 1,
               cluster: str | None = None, progress: ProgressFn | None = None,
               encode: Callable[[R], Any] | None = None,
               decode: Callable[[Any], R] | None = None) -> list[R]:
    """``[fn(c) for c in chunks]`` serially, in ``workers`` processes, or on the Dask ``cluster``.

    ``fn`` must be a module-level function (it is pickled by reference) and ``chunks`` small
    descriptors. ``encode`` runs on the worker after ``fn`` and ``decode`` here, to shrink what
    travels (e.g. only the non-empty cells of a grid). ``progress(done, total)`` is called as
    chunks finish.
    """
    with ChunkRunner(workers, cluster) as runner:
        return runner.map(fn, chunks, progress=progress or _no_progress, encode=encode, decode=decode)


def reduce_chunks(fn: Callable[[C], R], chunks: Sequence[C], merge: Callable[[R, R], R], *,
                  workers: int = 1, cluster: str | None = None, progress: ProgressFn | None = None,
                  encode: Callable[[R], Any] | None = None,
                  decode: Callable[[Any], R] | None = None) -> R:
    """Like :func:`run_chunks` but folds results with ``merge`` in chunk order as they arrive."""
    with ChunkRunner(workers, cluster) as runner:
        return runner.reduce(fn, chunks, merge, progress=progress or _no_progress, encode=encode,
                             decode=decode)


def progress_bar(description: str, enabled: bool = True) -> AbstractContextManager[ProgressFn]:
    """A rich bar of finished chunks as a ``progress(done, total)`` callback (context manager)."""
    if not enabled:
        return nullcontext(_no_progress)
    return _Bar(description)


class _Bar(AbstractContextManager[ProgressFn]):
    def __init__(self, description: str) -> None:

        self._progress = progress()
        self._task = self._progress.add_task(description, total=None, status="chunks")

    def __enter__(self) -> ProgressFn:
        self._progress.start()

        def update(done: int, total: int) -> None:
            self._progress.update(self._task, completed=done, total=total)

        return update

    def __exit__(self, *exc: object) -> None:
        self._progress.stop()


def chunked(seq: Sequence[C], size: int) -> Iterator[Sequence[C]]:
    """Consecutive slices of ``size`` items (e.g. standpoints per task)."""
    for s in range(0, len(seq), size):
        yield seq[s:s + size]


def flatten(parts: Iterable[Iterable[R]]) -> list[R]:
    """Concatenate per-chunk lists (rows of a table) in chunk order."""
    return [x for part in parts for x in part]
