"""Which reader opens a path: a registry from file suffix or folder layout to reader (the way rosbags
maps storage plugins), and the expansion of user inputs (sessions, dataset roots) into standpoints."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from depthstation.core.capture.mcap_reader import MCAP_MAGIC, open_mcap
from depthstation.core.capture.png_folder import is_png_folder, open_png
from depthstation.core.capture.realsense_bag import is_rosbag2_folder, open_realsense
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.session import SESSION_FILE, Session
from depthstation.core.capture.tum_folder import is_tum_folder, open_tum_folder
from depthstation.core.errors import InputError


@dataclass(frozen=True)
class Format:
    """One recording format: the file suffixes or the folder test that pick it, and its reader."""

    name: str
    suffixes: tuple[str, ...]
    is_folder: Callable[[Path], bool] | None
    open: Callable[[Path], Recording]


FORMATS: tuple[Format, ...] = (
    Format("mcap", (".mcap", ".mcap.partial"), None, open_mcap),
    Format("realsense", (".bag", ".db3"), is_rosbag2_folder, open_realsense),
    Format("png", (), is_png_folder, open_png),
)
RECORDING_SUFFIXES = tuple(s for f in FORMATS for s in f.suffixes if not s.endswith(".partial"))


def recording_format(path: Path) -> Format | None:
    """The format that reads `path` (by suffix, folder layout, or an MCAP's magic bytes)."""
    if path.is_dir():
        return next((f for f in FORMATS if f.is_folder is not None and f.is_folder(path)), None)
    name = path.name.lower()
    for f in FORMATS:
        if any(name.endswith(s) for s in f.suffixes):
            return f
    with path.open("rb") as fh:
        if fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
            return FORMATS[0]
    return None


def open_recording(path: Path, *, intrinsics: Path | None = None) -> Recording:
    """Open one standpoint or sequence: `.mcap`, `.bag`, `.db3` (file or rosbag2 folder), a PNG
    standpoint folder, or a TUM RGB-D folder (whose intrinsics file `intrinsics` may name)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "does not exist")
    if is_tum_folder(path):
        return open_tum_folder(path, intrinsics)
    if intrinsics is not None:
        raise InputError(intrinsics, "an intrinsics file applies to TUM RGB-D folders only; "
                                     f"{path} carries its own")
    fmt = recording_format(path)
    if fmt is None:
        what = "folder is no recording (no frameK_depth.png, no rosbag2 metadata.yaml, no depth.txt)" \
            if path.is_dir() else "is no recording (expected .mcap, .bag, .db3 or a PNG folder)"
        raise InputError(path, what)
    return fmt.open(path)


def open_inputs(paths: Sequence[Path]) -> list[Recording]:
    """Expand session dirs, PNG dataset roots and folders of recordings into standpoints."""
    out: list[Recording] = []
    for p in map(Path, paths):
        if not p.exists():
            raise InputError(p, "does not exist")
        if p.is_dir() and (p / SESSION_FILE).is_file():
            out.extend(Session.open(p, read_only=True).recordings())
        elif p.is_dir() and recording_format(p) is None and not is_tum_folder(p):
            subs = sorted(d for d in p.iterdir() if is_png_folder(d))
            files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in RECORDING_SUFFIXES)
            bags = sorted(d for d in p.iterdir() if is_rosbag2_folder(d))
            if not (subs or files or bags):
                raise InputError(
                    p, "holds no recordings (session.json, PNG standpoint folders, .mcap/.bag/.db3)"
                )
            out.extend(open_recording(x) for x in [*subs, *files, *bags])
        else:
            out.append(open_recording(p))
    return out
