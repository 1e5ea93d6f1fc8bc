"""Independent jobs split between this process and one forked child (figures after a study).

Why: a study's figures are drawn one after another by matplotlib, which holds the GIL for nearly
all of its work, so threads do not overlap them and the second core idles for seconds at the end
of every command. A forked child already holds the results, the imported matplotlib and the fonts:
it starts in milliseconds and needs nothing pickled in, only the jobs' small return values back.

Safety: a job must only write its own files and return a small picklable value (a run warning
it recorded would stay in the child). The child runs no other code (no atexit handlers, no
flushing of inherited buffers: `os._exit`) and writes nothing to the terminal: its stdout and
stderr are fresh objects on /dev/null, as a lock another thread held at the fork would stay held
in the child. Whatever goes wrong in it (an exception, a kill, a value that does not pickle, no
answer within `CHILD_PATIENCE` of this side's own jobs) makes this process run the child's jobs
itself, so the outcome (files and values) is the same as a serial run, errors included. Fork is
used only on Linux and when more than one core is ours; elsewhere the jobs run here, in order.
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

#: Set to "0" to run the jobs serially in this process (debugging, profiling).
ENV_SWITCH = "DEPTHSTATION_FORK_JOBS"
#: How long the child may take beyond this side's own jobs: max(seconds, factor x their time).
CHILD_PATIENCE = (30.0, 4.0)


def can_fork() -> bool:
    """Whether `run_split` forks here: Linux, two or more usable cores, not switched off."""
    if os.environ.get(ENV_SWITCH, "1") == "0" or not sys.platform.startswith("linux"):
        return False
    return hasattr(os, "fork") and len(os.sched_getaffinity(0)) > 1


def split_jobs(costs: Sequence[float]) -> tuple[list[int], list[int]]:
    """Job indices for (this process, the child): longest first onto the lighter side, each side
    kept in the given order."""
    here: list[int] = []
    child: list[int] = []
    load = [0.0, 0.0]
    for k in sorted(range(len(costs)), key=lambda i: -costs[i]):
        side = 0 if load[0] <= load[1] else 1
        (here if side == 0 else child).append(k)
        load[side] += costs[k]
    return sorted(here), sorted(child)


def run_split(jobs: Sequence[Callable[[], T]], costs: Sequence[float] | None = None) -> list[T]:
    """Every job's return value, in the order given; about half of the work (by `costs`, default
    equal) runs in a forked child while this process runs the rest."""
    if len(jobs) < 2 or not can_fork():
        return [job() for job in jobs]
    here, there = split_jobs(costs if costs is not None else [1.0] * len(jobs))
    read_fd, write_fd = os.pipe()
    with warnings.catch_warnings():  # Python >= 3.12 warns of fork in a threaded process: see above
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # the child: its jobs, their values down the pipe, and out without any clean-up
        code = 1
        try:
            os.close(read_fd)
            sys.stdout = sys.stderr = Path(os.devnull).open("w")  # noqa: SIM115 - closed by the exit
            warnings.simplefilter("ignore")
            payload = pickle.dumps([jobs[k]() for k in there])
            with os.fdopen(write_fd, "wb") as w:
                w.write(payload)
            code = 0
        finally:
            os._exit(code)
    os.close(write_fd)
    values: dict[int, T] = {}
    t0 = time.monotonic()
    try:
        for k in here:
            values[k] = jobs[k]()
    finally:
        patience = max(CHILD_PATIENCE[0], CHILD_PATIENCE[1] * (time.monotonic() - t0))
        got = _collect(read_fd, pid, patience)
    if got is not None and len(got) == len(there):
        values.update(zip(there, got, strict=True))
    else:  # the child failed: its jobs again here, so errors surface as they would serially
        for k in there:
            values[k] = jobs[k]()
    return [values[k] for k in range(len(jobs))]


def _collect(read_fd: int, pid: int, patience: float) -> list[Any] | None:
    """The child's values, or None if it did not finish cleanly within `patience` seconds (then
    it is killed); the child is always reaped."""
    deadline = time.monotonic() + patience
    parts: list[bytes] = []
    with os.fdopen(read_fd, "rb", buffering=0) as r:
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([r], [], [], left)[0]:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return None
            block = r.read(1 << 20)
            if not block:
                break
            parts.append(block)
    _, status = os.waitpid(pid, 0)
    if not os.WIFEXITED(status) or os.WEXITSTATUS(status) != 0:
        return None
    try:
        got = pickle.loads(b"".join(parts))
    except Exception:  # a torn payload: treat as a failed child
        return None
    return got if isinstance(got, list) else None
