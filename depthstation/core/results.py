"""Self-describing result folders: every evaluation writes `result.json` next to its tables, and any
later command reads a folder back by its files (see docs/results.md).

A result folder is recognised by its files, not only by `result.json`'s kind, so folders written by
any version of a stage (or by hand, in the documented formats) can be compared.
"""

from __future__ import annotations

import csv
import errno
import fcntl
import glob
import hashlib
import json
import os
import platform
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from contextvars import ContextVar
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from depthstation.core.errors import DepthstationError, InputError
from depthstation.core.grid import GRID_FILE
from depthstation.core.run_warnings import current as current_warnings
from depthstation.core.run_warnings import ensure_collecting

# every writer's --force (result_folder(force=...)): one declaration, one meaning
ForceOption = Annotated[bool, typer.Option("--force", help="Replace a non-empty --out and an existing "
                                                          "--rrd, only once the new result is complete.")]

RESULT_FILE = "result.json"
RESULT_MARKER = ".depthstation-result"  # in every folder result_folder finished: --force may replace it
# the files a result folder is recognised by (docs/results.md)
STANDPOINTS_FILE = "standpoints.csv"
FRAMES_FILE = "frames.csv"
SUMMARY_FILE = "summary.json"
EXPLAIN_FILE = "explain.json"
_PACKAGES = ("depthstation", "numpy", "opencv-python-headless", "open3d", "pyrealsense2",
             "rerun-sdk", "mcap", "rosbags", "scipy", "numba")


def software_versions() -> dict[str, str]:
    """Versions of Python and the packages that shape the numbers."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())  # a numpy NaN is a float NaN after .item(): null as well
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_json(path: Path, data: Any) -> None:
    """JSON with numpy values turned into plain ones and NaN/inf into null; written atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    tmp.replace(path)


# the command line of this process when it is the console script (set by depthstation.app.cli)
COMMAND_LINE: ContextVar[list[str] | None] = ContextVar("depthstation_command_line", default=None)
_HEAD_TAIL = 1 << 20  # bytes of a file's head and tail that go into its fingerprint


def fingerprint(path: str | Path) -> dict[str, Any]:
    """Enough to tell later whether an input changed: size, modification time and a SHA-256 of
    the file's first and last MiB (a folder: of its files' names, sizes and times, at most 10,000)."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return {"path": str(p), "exists": False}
    h = hashlib.sha256()
    if p.is_dir():
        files = sorted(x for x in p.rglob("*") if x.is_file())[:10_000]
        for f in files:
            s = f.stat()
            h.update(f"{f.relative_to(p)}|{s.st_size}|{s.st_mtime_ns}\n".encode())
        return {"path": str(p), "files": len(files), "sha256_listing": h.hexdigest()}
    with p.open("rb") as fh:
        h.update(fh.read(_HEAD_TAIL))
        if st.st_size > 2 * _HEAD_TAIL:
            fh.seek(-_HEAD_TAIL, os.SEEK_END)
            h.update(fh.read(_HEAD_TAIL))
    return {"path": str(p), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns,
            "sha256_head_tail": h.hexdigest()}


def write_result_info(out_dir: Path, kind: str, inputs: Sequence[str | Path], parameters: dict[str, Any],
                      device: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> Path:
    """`result.json`: what this folder holds, made from what (with fingerprints), by which software
    and command line, when, and every warning of the run (truncated inputs among them)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    warnings = current_warnings()
    info = {
        "kind": kind,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command_line": COMMAND_LINE.get(),
        "inputs": [str(i) for i in inputs],
        "input_fingerprints": [fingerprint(i) for i in inputs],
        "parameters": parameters,
        "device": device or {},
        "software": software_versions(),
        "warnings": [w.to_dict() for w in warnings],
        "truncated_inputs": sorted({w.where for w in warnings if w.code == "truncated-input" and w.where}),
    }
    if extra:
        info.update(extra)
    path = out_dir / RESULT_FILE
    write_json(path, info)
    return path


def inside(path: Path, folder: Path) -> str:
    """`path` as a name relative to a result folder when it lies in it (folders move: they are
    written under a temporary name), else as given."""
    try:
        return str(Path(path).resolve().relative_to(Path(folder).resolve()))
    except ValueError:
        return str(path)


def _non_empty(path: Path) -> bool:
    return path.is_dir() and any(path.iterdir())


class _FolderLock:
    """An exclusive, non-blocking lock on `.<name>.lock` beside a result folder (one run per folder)."""

    def __init__(self, out: Path) -> None:
        self.path = out.parent / f".{out.name}.lock"
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                holder = ""
                with suppress(OSError):
                    holder = f" (pid {self.path.read_text().strip()})"
                raise InputError(out, f"another depthstation run is writing this folder{holder}; "
                                      "wait for it or choose another --out") from exc
            try:  # the file we locked must still be the one at the path (a finished run unlinks it)
                same = os.fstat(fd).st_ino == self.path.stat().st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self.fd = fd
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())

    def release(self) -> None:
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self.fd)


DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


def _written_by_us(folder: Path) -> bool:
    """Whether a folder is one that `result_folder` wrote (its marker, or result.json of a result
    written before the marker existed)."""
    return (folder / RESULT_MARKER).is_file() or (folder / RESULT_FILE).is_file()


MARKER_FILES_MAX = 100_000  # a result with more files lists none (then nothing is checked)
LATER_FILES = ("view.rrd", ".view.rrd.partial-")  # what `view` adds to a finished result


def _listing(folder: Path) -> list[str] | None:
    """The files of a finished result folder (relative, sorted), for its marker; None if too many."""
    out = []
    for f in folder.rglob("*"):
        if f.is_file() and f.name != RESULT_MARKER:
            out.append(f.relative_to(folder).as_posix())
            if len(out) > MARKER_FILES_MAX:
                return None
    return sorted(out)


def files_added(folder: Path) -> list[str]:
    """Files in an earlier result that it did not write (the user's notes, another run's output):
    what `--force` must not delete. Empty where the marker lists no files (results before it did)."""
    with suppress(OSError, ValueError):
        written = json.loads((folder / RESULT_MARKER).read_text()).get("files")
        if isinstance(written, list):
            known = set(written)
            return sorted(rel for f in folder.rglob("*") if f.is_file() and f.name != RESULT_MARKER
                          and (rel := f.relative_to(folder).as_posix()) not in known
                          and not rel.startswith(LATER_FILES))
    return []


def _kind_of(folder: Path) -> str | None:
    """What kind of result a folder of ours holds (its marker's, else result.json's kind)."""
    for name in (RESULT_MARKER, RESULT_FILE):
        with suppress(OSError, ValueError):
            kind = json.loads((folder / name).read_text()).get("kind")
            if isinstance(kind, str):
                return kind
    return None


def check_replaceable(out: Path, inputs: Sequence[str | Path] = (), kind: str | None = None) -> None:
    """What `--force` may replace: an earlier result, never a folder of the user's own files (a
    recording, a capture session, notes) and never one that holds an input of this run.

    Why: `--force` removes the old folder once the new result is complete; pointed at the input
    folder, or at a folder that merely exists, it deleted what the user brought."""
    if not _non_empty(out):
        return
    here = out.resolve()
    for given in inputs:
        path = Path(given)
        if not path.exists():  # a preset name ('room', 'd455'), not a file
            continue
        p = path.resolve()
        if p == here or here in p.parents:
            raise InputError(out, f"holds the input {given}; --force would delete it with the old result: "
                                  "choose another --out")
    if not _written_by_us(out):
        raise InputError(out, f"holds files depthstation did not write (no {RESULT_MARKER} or "
                              f"{RESULT_FILE}); --force replaces only an earlier result: choose another "
                              "--out")
    added = files_added(out)
    if added:
        shown = ", ".join(added[:3]) + (f" and {len(added) - 3} more" if len(added) > 3 else "")
        raise InputError(out, f"holds files the earlier result did not write ({shown}); --force would "
                              "delete them with it: move them, or choose another --out")
    theirs = _kind_of(out)
    if kind is not None and theirs is not None and theirs != kind:
        raise InputError(out, f"holds an earlier '{theirs}' result; --force replaces only an earlier "
                              f"'{kind}' result (a simulated session is a capture, not a result to "
                              "overwrite): choose another --out")


def check_out_path(out: Path, what: str = "") -> None:
    """An output folder that can be made: not a file, not below one (mkdir would fail with "File
    exists", exit 1, the file unnamed). `what` says whose folder it is in the message."""
    if out.exists() and not out.is_dir():
        raise InputError(out, f"{what}is a file, not a folder (it names the result folder)")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise InputError(out, f"cannot be made: {blocking} is a file, not a folder")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


def remove_stale_partials(out: Path) -> list[Path]:
    """Remove the hidden `.<name>.partial-PID` folders an earlier run on `out` left when it was
    killed (its pid no longer runs); said on stderr. Called with `out`'s lock held, so no live run is
    writing them. Why: a killed run's partial folder stayed forever, unnamed, beside the result."""
    removed = []
    for p in out.parent.glob(f".{glob.escape(out.name)}.partial-*"):
        pid = p.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or int(pid) == os.getpid() or _pid_alive(int(pid)) or not p.is_dir():
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
        typer.echo(f"depthstation: removed {p}, the unfinished folder of an earlier run on {out} "
                   f"(pid {pid}, no longer running: killed before it finished)", err=True)
    return removed


@contextmanager
def folder_written_whole(out: Path, *, what: str = "the new result",
                         replaceable: Callable[[], str | None] | None = None) -> Iterator[Path]:
    """Yield a hidden `.<name>.partial-PID` folder to write; renamed to `out` once complete.

    Why: one way to write a folder that is never torn nor written over (a result, a corrected
    recording). An error or a full disk removes the hidden folder (a kill leaves at most it);
    where `out` holds something when the folder is complete, it is replaced only when
    `replaceable` (asked then) returns None, else the finished folder is kept under the visible
    name `NAME.new-PID` that the error gives (`what` names it there), with the reason
    `replaceable` returned or "appeared while this run was writing". An empty folder at `out`
    is replaced. The caller checks `out` before the work and holds any lock."""
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        yield tmp
        problem = None
        if not (out.is_dir() and not out.is_symlink() and not any(out.iterdir())) and \
                (out.exists() or out.is_symlink()):
            problem = "appeared while this run was writing" if replaceable is None else replaceable()
        if problem is not None:  # the finished folder is kept beside `out` under a visible name
            kept = out.parent / f"{out.name}.new-{os.getpid()}"
            tmp.rename(kept)
            raise InputError(out, f"{problem}; {what} is left in {kept}")
        old = out.parent / f".{out.name}.replaced-{os.getpid()}"
        if out.exists() or out.is_symlink():
            out.rename(old)
        tmp.rename(out)
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise disk_error(exc, out) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def result_folder(out: Path, *, force: bool = False, inputs: Sequence[str | Path] = (),
                  kind: str | None = None) -> Iterator[Path]:
    """Write a result folder under a temporary name and rename it into place when complete
    (`folder_written_whole`).

    Why: results are never overwritten or torn. A non-empty `out` is refused unless `force`
    (then it is replaced only once the new folder is complete, and only when it is an earlier
    result that holds none of `inputs`: `check_replaceable`); a lock keeps a second run out of
    the same folder; a kill, an error or a full disk leaves at most a hidden `.<name>.partial-PID`
    folder, never one that `view` or `compare` would take for a finished result. The finished
    folder carries a marker (`.depthstation-result`, with `kind`) so that a later `--force` knows
    it for ours, and replaces it only by a result of the same kind. Where no command
    collects the run's warnings (a notebook, a script), this does, so that `result.json` lists
    them too (`ensure_collecting`).
    """
    out = Path(out)
    check_out_path(out)
    if _non_empty(out) and not force:
        raise InputError(out, "is not empty; depthstation never overwrites results (--force replaces "
                              "it once the new result is complete)")
    if force:
        check_replaceable(out, inputs, kind)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise disk_error(exc, out.parent) from exc
    lock = _FolderLock(out)

    def replaceable() -> str | None:
        """Why what is now at `out` may not be replaced (None: it may)."""
        if not force or not out.is_dir():
            return "appeared while this run was writing"
        try:
            check_replaceable(out, inputs, kind)
        except InputError as exc:
            return exc.problem
        return None

    try:
        with folder_written_whole(out, replaceable=replaceable) as tmp:
            remove_stale_partials(out)
            with ensure_collecting():
                yield tmp
            (tmp / RESULT_MARKER).write_text(json.dumps({"kind": kind or _kind_of(tmp),
                                                         "command_line": COMMAND_LINE.get(),
                                                         "files": _listing(tmp)}) + "\n")
    finally:
        lock.release()


def disk_error(exc: OSError, where: Path) -> DepthstationError | OSError:
    """A full, read-only or forbidden disk as one line naming the path (exit 1); others unchanged."""
    if exc.errno not in DISK_ERRORS:
        return exc
    path = exc.filename or where
    what = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
            errno.EROFS: "the file system is read-only"}.get(exc.errno, "permission denied")
    return DepthstationError(f"{path}: cannot write ({what}); nothing was kept in {where}")


def is_recording_rrd(path: Path) -> bool:
    """An earlier rerun recording: what `new_file` (the only writer of .rrd files) may replace."""
    try:
        with path.open("rb") as fh:
            return path.is_file() and fh.read(3) == b"RRF"
    except OSError:
        return False


def check_new_file(path: Path, *, force: bool = False) -> None:
    """Refuse a file `new_file` would refuse, before any work (a run must not compute for minutes
    and then fail on its output name)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder; give a file name for the recording (e.g. run.rrd)")
    if path.exists() and not force:
        raise InputError(path, "exists; depthstation never overwrites a file (--force replaces it)")
    if path.exists() and not is_recording_rrd(path):
        raise InputError(path, "is not a rerun recording (.rrd); --force replaces only an earlier one, never "
                               "another file (a capture given as --rrd by mistake): choose another name")


def new_file(path: Path, *, force: bool = False) -> Path:
    """The temporary name to write `path` under (rename it with `finish_file`); refuses an existing
    `path` unless `force`."""
    path = Path(path)
    check_new_file(path, force=force)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(f".{path.name}.partial-{os.getpid()}")


def finish_file(tmp: Path, path: Path) -> Path:
    """Move a completely written temporary file into place."""
    Path(tmp).replace(path)
    return Path(path)


def read_result_info(out_dir: Path) -> dict[str, Any]:

    path = Path(out_dir) / RESULT_FILE
    if not path.is_file():
        raise InputError(out_dir, f"not a result folder (no {RESULT_FILE})")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"broken JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(path, "broken result.json (expected an object)")
    return data


@dataclass
class ResultFolder:
    path: Path
    kind: str                       # 'checkerboard' | 'scan' | 'explain'
    info: dict[str, Any] = field(default_factory=dict)   # result.json ({} if the folder has none)

    @property
    def label(self) -> str:
        return self.path.name


def _number(text: str) -> Any:
    if text == "":
        return float("nan")
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def read_standpoints(path: Path) -> list[dict[str, Any]]:
    """Rows of a `standpoints.csv`, numbers parsed (empty cells become NaN)."""
    try:
        with Path(path).open(newline="") as fh:
            rows = [{k: (_number(v) if k != "standpoint" else v) for k, v in row.items()}
                    for row in csv.DictReader(fh)]
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc})") from exc
    if rows and not {"standpoint", "distance_m", "inclination_deg"} <= set(rows[0]):
        raise InputError(path, "needs the columns standpoint, distance_m, inclination_deg")
    for row in rows:  # a figure's cell that is no number was read as NaN: the standpoint went unmatched
        for k, v in row.items():
            if isinstance(v, str) and k is not None and _numeric_column(k):
                raise InputError(path, f"{row.get('standpoint')}: {k} {v!r} is not a number")
    return rows


_NUMERIC_SUFFIXES = ("_m", "_m2", "_deg", "_px", "_pct", "_mm", "_p", "_ratio", "_std", "_u95")


def _numeric_column(name: str) -> bool:
    """Whether a standpoints.csv column holds a figure (its unit's suffix, or a count)."""
    return name.endswith(_NUMERIC_SUFFIXES) or name in ("frames", "frames_read", "fill_rate")


def open_result(path: Path) -> ResultFolder:
    """Recognise a result folder by its files; result.json is read when present."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "not a folder")
    info: dict[str, Any] = {}
    if (path / RESULT_FILE).is_file():
        try:
            loaded = json.loads((path / RESULT_FILE).read_text())
        except json.JSONDecodeError as exc:
            raise InputError(path / RESULT_FILE, f"broken JSON ({exc})") from exc
        info = loaded if isinstance(loaded, dict) else {}
    if (path / STANDPOINTS_FILE).is_file():
        kind = "checkerboard"
    elif (path / GRID_FILE).is_file():
        kind = "scan"
    elif (path / EXPLAIN_FILE).is_file():
        kind = "explain"
    else:
        raise InputError(path, f"not a result folder (no {STANDPOINTS_FILE}, {GRID_FILE} or {EXPLAIN_FILE})")
    return ResultFolder(path=path, kind=kind, info=info)


def unique_labels(folders: list[ResultFolder]) -> list[str]:
    """Short labels for tables: folder names, made unique with their parent's name when they clash."""
    labels = [f.label for f in folders]
    for i, lab in enumerate(labels):
        if labels.count(lab) > 1:
            labels[i] = f"{folders[i].path.parent.name}/{lab}"
    seen: dict[str, int] = {}
    out = []
    for lab in labels:
        seen[lab] = seen.get(lab, 0) + 1
        out.append(lab if seen[lab] == 1 else f"{lab}#{seen[lab]}")
    return out
