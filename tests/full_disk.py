"""A full disk without privileges: files opened for writing under one folder raise ENOSPC once a
byte budget is spent, after writing the part that still fits (what a real full disk does to a
buffered write). Python's `open`, `io.open` and `Path.open` are patched; the code under test is not."""

from __future__ import annotations

import builtins
import errno
import io
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest


class _Budget:
    def __init__(self, left: int) -> None:
        self.left = left
        self.refused = 0  # writes refused for lack of space


class _FullFile:
    """A writable file whose writes draw on a shared budget."""

    def __init__(self, f: Any, budget: _Budget) -> None:
        self._f = f
        self._budget = budget

    def write(self, data: Any) -> int:
        raw = data.encode() if isinstance(data, str) else bytes(memoryview(data).cast("B"))
        if len(raw) > self._budget.left:
            fits = self._budget.left
            if fits > 0:
                self._f.write(data[:fits] if isinstance(data, str) else raw[:fits])
                self._f.flush()
            self._budget.left = 0
            self._budget.refused += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._budget.left -= len(raw)
        return int(self._f.write(data))

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def __enter__(self) -> _FullFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._f.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


@contextmanager
def disk_full_after(monkeypatch: pytest.MonkeyPatch, folder: Path, budget_bytes: int) -> Iterator[_Budget]:
    """Under `folder`, writing beyond `budget_bytes` (all files together) raises ENOSPC."""
    real_open = io.open
    root = os.path.realpath(folder)
    budget = _Budget(budget_bytes)

    def full_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        f = real_open(file, mode, *args, **kwargs)
        if isinstance(file, (str, os.PathLike)) and any(c in mode for c in "wxa+"):
            path = os.path.realpath(os.fspath(file))
            if path == root or path.startswith(root + os.sep):
                return _FullFile(f, budget)
        return f

    monkeypatch.setattr(io, "open", full_open)
    monkeypatch.setattr(builtins, "open", full_open)
    try:
        yield budget
    finally:
        monkeypatch.setattr(io, "open", real_open)
        monkeypatch.setattr(builtins, "open", real_open)
