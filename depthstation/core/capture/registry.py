"""Which reader opens a path: a registry from file suffix or folder layout to reader (the way rosbags
maps storage plugins), and the expansion of user inputs (sessions, dataset roots) into standpoints.

Several readers may claim one suffix (`.mcap`: ours, else any ROS 2 bag; `.bag`/`.db3`: the
RealSense SDK's layout, else any ROS bag): they are tried in order, a reader that finds its own
layout missing raising `NotThisFormat`. Topic choices (`--depth-topic` ...) go to the ROS reader.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from depthstation.core.camera_model import model_name
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture.mcap_reader import MCAP_MAGIC, open_mcap
from depthstation.core.capture.png_folder import is_png_folder, open_png
from depthstation.core.capture.realsense_bag import is_rosbag2_folder, open_realsense
from depthstation.core.capture.recording import NotThisFormat, Recording
from depthstation.core.capture.ros_bag import open_ros
from depthstation.core.capture.session import SESSION_FILE, Session
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.capture.tum_folder import is_tum_folder, open_tum_folder
from depthstation.core.errors import InputError
from depthstation.core.results import fingerprint
from depthstation.core.run_warnings import warn


@dataclass(frozen=True)
class Format:
    """One recording format: the file suffixes or the folder test that pick it, and its reader."""

    name: str
    suffixes: tuple[str, ...]
    is_folder: Callable[[Path], bool] | None
    open: Callable[[Path], Recording]
    takes_topics: bool = False  # reads any topic layout (`--depth-topic` ...)


def _open_ros(path: Path) -> Recording:
    return open_ros(path)


FORMATS: tuple[Format, ...] = (
    Format("mcap", (".mcap", ".mcap.partial"), None, open_mcap),
    Format("realsense", (".bag", ".db3"), is_rosbag2_folder, open_realsense),
    Format("ros", (".bag", ".db3", ".mcap"), is_rosbag2_folder, _open_ros, takes_topics=True),
    Format("png", (), is_png_folder, open_png),
)
RECORDING_SUFFIXES = tuple(dict.fromkeys(s for f in FORMATS for s in f.suffixes
                                         if not s.endswith(".partial")))


def recording_formats(path: Path) -> list[Format]:
    """The formats that may read `path`, in the order to try them (suffix, folder layout, or an
    MCAP's magic bytes)."""
    if path.is_dir():
        return [f for f in FORMATS if f.is_folder is not None and f.is_folder(path)]
    name = path.name.lower()
    found = [f for f in FORMATS if any(name.endswith(s) for s in f.suffixes)]
    if found:
        return found
    with path.open("rb") as fh:
        if fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
            return [f for f in FORMATS if ".mcap" in f.suffixes]
    return []


def recording_format(path: Path) -> Format | None:
    """The first format that may read `path` (None: no recording)."""
    found = recording_formats(path)
    return found[0] if found else None


def open_recording(path: Path, *, intrinsics: Path | None = None,
                   topics: TopicChoice | None = None) -> Recording:
    """Open one standpoint or sequence: `.mcap`, `.bag`, `.db3` (file or rosbag2 folder; ours, the
    RealSense SDK's or any ROS recording), a PNG standpoint folder, or a TUM RGB-D folder (whose
    intrinsics file `intrinsics` may name). `topics` picks the streams of a ROS recording."""
    return _open_recording(Path(path), intrinsics, topics)


def check_lenses(rec: Recording, streams: Sequence[str] = ("depth", "colour")) -> None:
    """A study's refusal of a lens it cannot invert, in the streams it uses (depth; colour for the
    board's pose): dropped, every pixel would sit on the wrong ray without a word. Reading,
    `capture info` and export keep working on such a file."""
    info = rec.info
    for stream in streams:
        intr = info.depth_intrinsics if stream == "depth" else info.color_intrinsics
        problem = None if intr is None else intr.lens_problem()
        if problem:
            raise InputError(rec.path, f"{stream} intrinsics: {problem}")
        if intr is not None and model_name(intr.model) == "none" and any(c != 0.0 for c in intr.coeffs):
            warn(f"{stream} intrinsics: lens model 'none' with non-zero coefficients "
                 f"({', '.join(f'{c:g}' for c in intr.coeffs)}): read as no lens, as the model says. If "
                 "the images are not rectified, every pixel sits on the wrong ray: give the model "
                 "(brown_conrady, plumb_bob, rational_polynomial)", str(rec.path), "lens-model-none")


def _open_recording(path: Path, intrinsics: Path | None, topics: TopicChoice | None) -> Recording:
    if not path.exists():
        raise InputError(path, "does not exist")
    if topics is not None and not topics.given:
        topics = None
    if is_tum_folder(path):
        if topics is not None:
            raise InputError(path, "--depth-topic / --color-topic / --infrared-topic apply to ROS recordings")
        return open_tum_folder(path, intrinsics)
    if intrinsics is not None:
        raise InputError(intrinsics, "an intrinsics file applies to TUM RGB-D folders only; "
                                     f"{path} carries its own")
    formats = recording_formats(path)
    if topics is not None:
        formats = [f for f in formats if f.takes_topics]
        if not formats:
            raise InputError(path, "--depth-topic / --color-topic / --infrared-topic apply to ROS "
                                   "recordings (.bag, .db3, .mcap, rosbag2 folders)")
    if not formats:
        if path.is_dir() and (path / SESSION_FILE).is_file():  # `simulate scan` writes one: name its file
            inside = sorted(p.name for p in path.glob("*.mcap")) or ["none"]
            listed = ", ".join(inside[:3]) + (", ..." if len(inside) > 3 else "")
            raise InputError(path, f"is a capture session, and this takes one recording: give one of its "
                                   f"recordings ({listed})")
        what = "folder is no recording (no frameK_depth.png, no rosbag2 metadata.yaml, no depth.txt)" \
            if path.is_dir() else "is no recording (expected .mcap, .bag, .db3 or a PNG folder)"
        raise InputError(path, what)
    for fmt in formats[:-1]:
        try:
            return fmt.open(path)
        except NotThisFormat:
            continue
    last = formats[-1]
    return open_ros(path, topics) if last.takes_topics else last.open(path)


def open_inputs(paths: Sequence[Path], topics: TopicChoice | None = None) -> list[Recording]:
    """Expand session dirs, PNG dataset roots and folders of recordings into standpoints."""
    out: list[Recording] = []
    for p in map(Path, paths):
        if not p.exists():
            raise InputError(p, "does not exist")
        if p.is_dir() and (p / SESSION_FILE).is_file():
            check_session_topics(p, topics)
            session = Session.open(p, read_only=True)
            found = session.recordings()
            if not found:  # import, export and info had nothing to work on, and said nothing or crashed
                held = ", ".join(f"{e.get('name')} {e.get('status')}" for e in session.standpoints) or "none"
                raise InputError(p, f"is a session with no complete standpoint to read (standpoints: {held})")
            out.extend(found)
        elif p.is_dir() and recording_format(p) is None and not is_tum_folder(p):
            subs = sorted(d for d in p.iterdir() if is_png_folder(d))
            files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in RECORDING_SUFFIXES)
            bags = sorted(d for d in p.iterdir() if is_rosbag2_folder(d))
            if not (subs or files or bags):
                raise InputError(
                    p, "holds no recordings (session.json, PNG standpoint folders, .mcap/.bag/.db3)"
                )
            out.extend(open_recording(x, topics=topics) for x in [*subs, *files, *bags])
        else:
            out.append(open_recording(p, topics=topics))
    return out


def check_session_topics(session: Path, topics: TopicChoice | None) -> None:
    """A session's standpoints are read from the topics our writer gives each stream; a topic
    option naming another is refused, not ignored (the study would read a stream not asked for)."""
    if topics is None:
        return
    ours = {"depth": mw.DEPTH_TOPIC, "color": mw.COLOR_TOPIC, "infrared": mw.INFRARED_TOPIC}
    other = [f"--{k}-topic {v}" for k, v in topics.to_dict().items() if v is not None and v != ours[k]]
    if other:
        held = ", ".join(f"{k} on {v}" for k, v in ours.items())
        raise InputError(session, f"is a depthstation session, whose standpoints hold {held}; "
                                  f"{' and '.join(other)} names another (give a ROS recording's own files "
                                  "to read its topics)")


def check_distinct_recordings(recs: Sequence[Recording]) -> None:
    """One recording twice (given twice, inside a folder also given, or a copy under another name)
    is bad input: its standpoint would count twice, and explain would take the copies for
    independent evidence. Files compare by size and a hash of their first and last MiB
    (`fingerprint`), folders (PNG sets, rosbag2) by their resolved path."""
    seen: dict[tuple[Any, ...], Path] = {}
    for r in recs:
        p = Path(r.path)
        if p.is_file():
            f = fingerprint(p)
            key: tuple[Any, ...] = ("file", f.get("bytes"), f.get("sha256_head_tail"))
        else:
            key = ("folder", p.resolve())
        if key in seen:
            raise InputError(p, f"is the same recording as {seen[key]} (given twice, or a copy): its "
                                "standpoint would count twice; give each recording once")
        seen[key] = p
