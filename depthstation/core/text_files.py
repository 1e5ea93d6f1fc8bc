"""Reading the text files users hand in (trajectories, board and camera JSON, protocols, models,
manifests): every way such a file can be unreadable becomes one line naming it (exit 2)."""

from __future__ import annotations

from pathlib import Path

from depthstation.core.errors import InputError


def read_text(path: str | Path, what: str) -> str:
    """The file's text (UTF-8); `what` says what the file should be, for the error line."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError as exc:
        raise InputError(p, f"{what} not found") from exc
    except IsADirectoryError as exc:
        raise InputError(p, f"is a folder, expected a {what} file") from exc
    except OSError as exc:
        raise InputError(p, f"cannot read the {what} ({exc.strerror})") from exc
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(p, f"is not UTF-8 text (byte {exc.start}); expected a {what}") from exc
