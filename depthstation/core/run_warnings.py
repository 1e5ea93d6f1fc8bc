"""Warnings of a run: what the station noticed that a user must see before trusting a number.

Why a collector and not `logging`: a warning that only sits in a log or a summary file is a warning
nobody reads. Every command runs inside `collecting()`; the console script prints what was
collected on stderr (one line each, naming the standpoint or file), `result.json` lists it, and
`--strict` turns any warning into exit code 3. Code that runs outside a command (a notebook, a
test) gets each warning at once through the `depthstation.warnings` logger (stderr by default).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class RunWarning:
    """One warning: what happened, where (standpoint, file), and a stable code to filter on."""

    message: str
    where: str | None = None
    code: str = "general"

    def line(self) -> str:
        return f"{self.where}: {self.message}" if self.where else self.message

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


log = logging.getLogger("depthstation.warnings")
_COLLECTED: ContextVar[list[RunWarning] | None] = ContextVar("depthstation_warnings", default=None)
# the main thread's collectors, innermost last, for threads that did not inherit the context (a
# thread pool's workers start with an empty one): their warnings reached stderr but not result.json
# or --strict (a truncated recording read by a standpoint worker went unrecorded). The innermost:
# a batch item collects its own, so that its result.json lists what its workers warned
_MAIN: list[list[RunWarning]] = []


@contextmanager
def collecting(*, forward: bool = False) -> Iterator[list[RunWarning]]:
    """Collect the warnings of the code inside; nested collectors pass theirs to the outer one.
    `forward`: with no outer collector, log them at the end as uncollected warnings are (a part of
    a run that keeps its own list, e.g. a batch item, called outside any command)."""
    outer = _COLLECTED.get()
    mine: list[RunWarning] = []
    token = _COLLECTED.set(mine)
    main = threading.current_thread() is threading.main_thread()
    if main:
        _MAIN.append(mine)
    try:
        yield mine
    finally:
        _COLLECTED.reset(token)
        if main:  # by identity: lists compare by value, and an empty one would match another's
            _MAIN[:] = [c for c in _MAIN if c is not mine]
        if outer is not None:
            outer.extend(w for w in mine if w not in outer)
        elif forward:
            for w in mine:
                log.warning(w.line())


@contextmanager
def ensure_collecting() -> Iterator[list[RunWarning]]:
    """The running collector, or a new one (logged at its end) where none runs: for a study called
    from Python, so that its result.json lists its warnings as a command's does (a nested
    collector here would hide the ones raised before it from that result.json)."""
    bucket = _COLLECTED.get()
    if bucket is not None:
        yield bucket
        return
    with collecting(forward=True) as mine:
        yield mine


def warn(message: str, where: str | None = None, code: str = "general") -> RunWarning:
    """Record a warning (once: the same message for the same place is not repeated). In a thread
    outside any collector of its own, the main thread's running command collects it."""
    w = RunWarning(message, None if where is None else str(where), code)
    bucket = _COLLECTED.get()
    if bucket is None and _MAIN and threading.current_thread() is not threading.main_thread():
        bucket = _MAIN[-1]
    if bucket is None:
        log.warning(w.line())
    elif w not in bucket:
        bucket.append(w)
    return w


def current() -> list[RunWarning]:
    """The warnings collected so far in this run (empty outside a collector)."""
    return list(_COLLECTED.get() or [])
