"""The consoles every command prints through, and progress on stderr: a rich bar in a terminal,
plain lines (count, percentage, rate, ETA) in a log, where a bar would show only at the end."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

from rich.console import Console, ConsoleDimensions
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

LOG_WIDTH = 1000
"""Columns of a console that is no terminal (a log, a pipe): wide enough that no table is cut."""


class StationConsole(Console):
    """A rich console that is as wide as its content when it writes to no terminal.

    rich falls back to 80 columns there and cuts table cells to `stand…`; a log has no width to
    keep to. In a terminal it is the terminal's width, as rich finds it.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        # a width the caller gives is kept; one rich took from $COLUMNS is not (a process that
        # exported COLUMNS=80 would cut a log's tables again)
        self._given_width = kwargs.get("width") is not None
        super().__init__(*args, **kwargs)

    @property
    def size(self) -> ConsoleDimensions:
        size = Console.size.fget(self)  # type: ignore[attr-defined]
        if not self._given_width and not self.is_terminal:
            return ConsoleDimensions(LOG_WIDTH, size.height)
        return size  # type: ignore[no-any-return]

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        self._given_width = True
        Console.size.fset(self, new_size)  # type: ignore[attr-defined]

    @property
    def width(self) -> int:
        return self.size.width

    @width.setter
    def width(self, width: int) -> None:
        self._given_width = True
        Console.width.fset(self, width)  # type: ignore[attr-defined]


stderr_console = StationConsole(stderr=True)
stdout_console = StationConsole()


def progress(transient: bool = False, console: Console | None = None,
             get_time: Callable[[], float] | None = None) -> Progress:
    """A progress display on stderr: description, bar, n/N, elapsed, remaining.

    When the console is no terminal (stderr to a log file or a pipe) it is a :class:`LogProgress`,
    which prints a line per step or percentage milestone instead of a bar drawn once at the end.
    """
    console = console or stderr_console
    if not console.is_terminal:
        return LogProgress(console=console, get_time=get_time)
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
        console=console,
        transient=transient,
        get_time=get_time,
    )


def _clock(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "-:--:--"
    s = round(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class LogProgress(Progress):
    """Progress as lines in a log: `name: 30/150 (20%), 12.5/s, elapsed 0:00:02, ETA 0:00:10, status`.

    A line at the start, at every step when there are at most `steps` of them, else at every
    `100 / steps` percent, and at the end; at most one line per `min_interval_s` per task (the
    last one always), and one at least every `heartbeat_s` while work goes on between milestones
    (a slow step, or no known total).
    """

    def __init__(self, console: Console, get_time: Callable[[], float] | None = None,
                 steps: int = 20, min_interval_s: float = 1.0, heartbeat_s: float = 30.0) -> None:
        super().__init__(console=console, disable=True, get_time=get_time)
        self.steps = steps
        self.min_interval_s = min_interval_s
        self.heartbeat_s = heartbeat_s
        self._said: dict[TaskID, tuple[float, int, float]] = {}  # time, milestone, completed
        self._said_lock = threading.Lock()

    def add_task(self, description: str, start: bool = True, total: float | None = 100.0,
                 completed: int = 0, visible: bool = True, **fields: Any) -> TaskID:
        fields.setdefault("status", "")
        task_id = super().add_task(description, start, total, completed, visible, **fields)
        self._say(task_id, force=True)
        return task_id

    def update(self, task_id: TaskID, *, total: float | None = None, completed: float | None = None,
               advance: float | None = None, description: str | None = None,
               visible: bool | None = None, refresh: bool = False, **fields: Any) -> None:
        super().update(task_id, total=total, completed=completed, advance=advance,
                       description=description, visible=visible, refresh=refresh, **fields)
        self._say(task_id)

    def advance(self, task_id: TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._say(task_id)

    def stop(self) -> None:
        for task_id in list(self._said):
            self._say(task_id, final=True)
        super().stop()

    def _milestone(self, completed: float, total: float | None) -> int:
        if not total:
            return -1
        if total <= self.steps:
            return int(completed)
        return math.floor(completed / total * self.steps + 1e-9)

    def _say(self, task_id: TaskID, force: bool = False, final: bool = False) -> None:
        with self._lock:
            task = self._tasks[task_id]
            now = self.get_time()
            completed, total = task.completed, task.total
            milestone = self._milestone(completed, total)
            with self._said_lock:
                last = self._said.get(task_id)
                if last is not None and not force:
                    t_last, m_last, c_last = last
                    since = now - t_last
                    if completed == c_last:
                        return
                    done = total is not None and completed >= total
                    # the end is always said (once: `completed == c_last` after it)
                    quiet = since < self.min_interval_s or (milestone == m_last and since < self.heartbeat_s)
                    if quiet and not (final or done):
                        return
                self._said[task_id] = (now, milestone, completed)
            line = self._line(task, now)
        self.console.print(line, markup=False, highlight=False, soft_wrap=True)

    def _line(self, task: Any, now: float) -> str:
        elapsed = (now - task.start_time) if task.start_time is not None else 0.0
        completed, total = task.completed, task.total
        # the mean since the start until rich's window of recent steps is filled (its first
        # samples, a few frames finished together, gave 53 frames/s where 4 was the pace)
        rate = task.speed if elapsed >= self.speed_estimate_period else None
        if rate is None and elapsed > 0 and completed > 0:
            rate = completed / elapsed
        count = f"{completed:g}" if total is None else f"{completed:g}/{total:g} ({completed / total:.0%})"
        parts = [f"{task.description}: {count}"]
        if rate:
            parts.append(f"{rate:.3g}/s")
        parts.append(f"elapsed {_clock(elapsed)}")
        if total is not None and completed < total:
            eta = (total - completed) / rate if rate else None
            parts.append(f"ETA {_clock(eta)}")
        status = str(task.fields.get("status") or "")
        if status:
            parts.append(status)
        return ", ".join(parts)
