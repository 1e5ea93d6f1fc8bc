"""A capture session directory: `session.json` plus one MCAP per standpoint.

Each standpoint is written to `<name>.mcap.partial` by a background thread and renamed to
`<name>.mcap` only after a clean close, so a crash loses at most the standpoint in progress and the
camera loop never waits on the disk. `session.json` is replaced atomically on every change.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import queue
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.mcap_reader import McapRecording, cut_source, open_mcap, say_cut_source
from depthstation.core.capture.mcap_writer import CAPTURE_COMPRESSION, McapFileWriter
from depthstation.core.errors import CaptureError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import drop_none, protocol_from_dict
from depthstation.core.results import _jsonable
from depthstation.core.run_warnings import warn
from depthstation.core.text_files import read_text

log = logging.getLogger("depthstation.core.capture")

SESSION_FILE = "session.json"
SESSION_FORMAT = "depthstation-session"
SESSION_VERSION = 1
STATUSES = ("recording", "complete", "partial", "discarded")
IDENTITY_KEYS = ("name", "serial_number", "baseline_m", "depth_size", "color_size")


def camera_identity(info: StreamInfo) -> dict[str, Any]:
    """What makes the standpoints of one session comparable: the device (model name, serial,
    baseline) and the stream sizes. Stored at creation; a resume with another camera is refused."""

    def size(i: Any) -> list[int] | None:
        return None if i is None else [int(i.width), int(i.height)]

    dev = info.device or {}
    return {"name": dev.get("name"), "serial_number": dev.get("serial_number"),
            "baseline_m": None if info.baseline_m is None else round(float(info.baseline_m), 5),
            "depth_size": size(info.depth_intrinsics), "color_size": size(info.color_intrinsics)}


def identity_differences(stored: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """The identity keys on which two cameras differ, as 'key: stored vs now'."""
    return [f"{k} {stored.get(k)!r} vs {now.get(k)!r}" for k in IDENTITY_KEYS if stored.get(k) != now.get(k)]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _to_dict(obj: Any) -> Any:
    if obj is None or isinstance(obj, dict):
        return obj
    to_dict = getattr(obj, "to_dict", None)
    if callable(to_dict):
        return to_dict()
    raise TypeError(f"cannot store {type(obj).__name__} in session.json")


def _atomic_json(path: Path, data: dict[str, Any]) -> None:
    """Write, fsync, rename: a reader sees the old or the new file, never a torn one."""

    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("w") as f:
            f.write(json.dumps(_jsonable(data), indent=2) + "\n")
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)
    except OSError as exc:  # a full disk: no torn temporary left beside the kept session.json
        tmp.unlink(missing_ok=True)
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


class Session:
    """A session directory; create it once, open it again to resume or read."""

    def __init__(self, directory: Path, data: dict[str, Any], read_only: bool = False) -> None:
        self.dir = Path(directory)
        self.data = data
        self.read_only = read_only
        self._lock = threading.Lock()

    # -- life cycle ----------------------------------------------------------------------------
    @classmethod
    def create(
        cls, directory: Path, *, protocol: Any = None, device: dict[str, Any] | None = None, **extra: Any
    ) -> Session:
        """New session; refuses a directory that already holds a session or any other file."""
        d = Path(directory)
        if (d / SESSION_FILE).exists():
            raise InputError(d, "holds a session already; open it to resume, captures are never overwritten")
        if d.exists() and any(d.iterdir()):
            raise InputError(d, "is not empty; a new session needs an empty or new directory")
        d.mkdir(parents=True, exist_ok=True)
        data: dict[str, Any] = {
            "format": SESSION_FORMAT,
            "version": SESSION_VERSION,
            "created": _now(),
            "protocol": _to_dict(protocol),
            "device": dict(device or {}),
            "warmup": None,
            "calibration": None,
            "standpoints": [],
        }
        data.update(extra)
        s = cls(d, data)
        s._save()
        return s

    @classmethod
    def open(cls, directory: Path, *, read_only: bool = False) -> Session:
        """Open for resume; a stale `.mcap.partial` (a crash) is marked 'partial'."""
        d = Path(directory)
        path = d / SESSION_FILE
        if not path.is_file():
            raise InputError(d, "is no capture session (no session.json)")
        try:
            data = json.loads(read_text(path, "session JSON"))
        except ValueError as exc:
            raise InputError(path, f"is not valid JSON ({exc})") from exc
        if data.get("format") != SESSION_FORMAT:
            raise InputError(path, "is no depthstation session file")
        s = cls(d, data, read_only=read_only)
        if s._reconcile() and not read_only:
            s._save()
        return s

    def _reconcile(self) -> bool:
        """Make session.json agree with the files on disk after a crash at any step.

        A standpoint killed while recording or closing leaves `<name>.mcap.partial`: it is marked
        'partial' (re-recorded on resume, the file kept aside). One killed after its file was
        renamed to `<name>.mcap` but before session.json said so, or a finished MCAP the session
        never listed, is adopted as complete once it reads back whole: never lost, never blocking
        a resume.
        """
        d, data = self.dir, self.data
        changed = False
        entries = data.setdefault("standpoints", [])
        for e in entries:
            final = d / f"{e['name']}.mcap"
            if e.get("status") in ("recording", "partial") and str(e.get("file", "")).endswith(".partial") \
                    and not (d / e["file"]).exists() and final.is_file() and self._adopt(e, final):
                changed = True
            elif e.get("status") == "recording":
                e["status"] = "partial"
                e["note"] = "interrupted while recording"
                changed = True
        known = {e["file"] for e in entries}
        plan = self._plan_names()
        for p in sorted(d.glob("*.mcap.partial")):
            if p.name not in known:
                entries.append({"name": p.name.split(".")[0], "file": p.name, "status": "partial",
                                "note": "found without an entry (crash)"})
                changed = True
        for p in sorted(d.glob("*.mcap")):
            name = p.name[: -len(".mcap")]
            if p.name in known or "." in name:  # discarded-N / attempt files carry a dot
                continue
            if any(e["name"] == name and e.get("status") == "complete" for e in entries):
                continue
            entry: dict[str, Any] = {"name": name, "file": p.name, "status": "partial"}
            if plan is not None and name not in plan:
                self._refuse(p, "its name is no standpoint of the session's plan")
                continue
            if self._adopt(entry, p):
                entries.append(entry)
                changed = True
        return changed

    def _adopt(self, entry: dict[str, Any], path: Path) -> bool:
        """Take a finished MCAP into the session after a read check (summary and frames present)."""
        try:
            rec = open_mcap(path)
        except (InputError, OSError) as exc:
            log.warning("%s: not adopted (%s)", path, exc)
            return False
        if rec.frame_count is None or rec.frame_count < 1:
            return False
        stored = self.data.get("camera_identity")
        if isinstance(stored, dict) and (diff := identity_differences(stored, camera_identity(rec.info))):
            self._refuse(path, "it was recorded by another camera (" + "; ".join(diff) + ")")
            return False
        indices = [fs.index for fs in rec.frames()]
        entry.update(status="complete", file=path.name, frames=rec.frame_count,
                     first_index=indices[0] if indices else None,
                     last_index=indices[-1] if indices else None, adopted=_now(),
                     note="finished file adopted after a crash (session.json had not recorded it)")
        return True

    def _refuse(self, path: Path, why: str) -> None:
        """A finished MCAP in the folder that is not the session's: left alone, said on a resume."""
        if self.read_only:
            log.info("%s: not adopted (%s)", path, why)
        else:
            warn(f"{path.name} is not adopted into the session: {why}; it is left as it is",
                 str(self.dir), "foreign-recording")

    def _plan_names(self) -> set[str] | None:
        """The standpoint names of the stored protocol's plan (None: no usable protocol stored)."""
        stored = self.data.get("protocol")
        if not isinstance(stored, dict):
            return None
        try:
            proto = protocol_from_dict(drop_none(stored), self.dir / SESSION_FILE)
        except InputError:
            return None
        return {sp.name for sp in proto.plan.standpoints()}

    def verify_complete(self) -> list[str]:
        """Check the standpoints listed complete against the disk before a resume trusts them: a
        missing file or one cut short (a copy gone wrong, a full disk) is re-recorded, the damaged
        file kept aside (renamed, never deleted), each with a warning. The names to re-record."""
        redo = []
        for e in self.data.get("standpoints", []):
            if e.get("status") != "complete":
                continue
            path = self.dir / e["file"]
            if not path.is_file():
                e.update(status="discarded", reason="recording missing from the disk at resume",
                         discarded=_now())
                warn(f"standpoint {e['name']} is listed complete but {e['file']} is missing: it is recorded "
                     "again", str(self.dir), "missing-recording")
                redo.append(e["name"])
                continue
            try:
                rec = open_mcap(path)
                problem = ("it is cut short (no MCAP summary)" if rec.truncated
                           else None if rec.frame_count == e.get("frames", rec.frame_count)
                           else f"it holds {rec.frame_count} frames, {e.get('frames')} were recorded")
            except (InputError, OSError) as exc:
                problem = f"it cannot be read ({exc})"
            if problem is not None:
                self.discard(e["name"], f"damaged at resume: {problem}")
                warn(f"standpoint {e['name']}: {path.name} is damaged ({problem}): "
                     f"kept aside as {e['file']}, the standpoint is recorded again", str(self.dir),
                     "damaged-recording")
                redo.append(e["name"])
        if redo:
            self._save()
        return redo

    def _save(self) -> None:
        if self.read_only:
            raise CaptureError(f"{self.dir}: session opened read-only")
        with self._lock:
            _atomic_json(self.dir / SESSION_FILE, self.data)

    # -- contents ------------------------------------------------------------------------------
    @property
    def standpoints(self) -> list[dict[str, Any]]:
        """Entries with name, file, status (recording/complete/partial/discarded), frames, dropped."""
        return list(self.data.get("standpoints", []))

    def status(self, name: str) -> str | None:
        entries = [e for e in self.data.get("standpoints", []) if e["name"] == name]
        return entries[-1]["status"] if entries else None

    def set(self, key: str, value: Any) -> None:
        """Store a session-level document ('warmup', 'calibration', ...) atomically."""
        self.data[key] = _to_dict(value) if not isinstance(value, (str, int, float, list)) else value
        self._save()

    def recordings(self, statuses: tuple[str, ...] = ("complete",)) -> list[McapRecording]:
        """Readers for the standpoints of the given statuses, in capture order. A warm-up that
        never settled is said again (`warmup-unsettled`): every study of the session inherits it."""
        warm = self.data.get("warmup")
        if isinstance(warm, dict) and warm.get("has_temperature") and warm.get("settled") is False:
            slope = warm.get("final_slope_c_per_min")
            warn(f"the session's warm-up ended without the temperature settling ({warm.get('reason', '?')}"
                 f"{f'; final slope {slope:+.3f} °C/min' if isinstance(slope, (int, float)) else ''}): "
                 "depth may drift across its standpoints", str(self.dir), "warmup-unsettled")
        out = []
        for e in self.data.get("standpoints", []):
            if e.get("status") not in statuses:
                continue
            if (self.dir / e["file"]).is_file():
                rec = open_mcap(self.dir / e["file"])  # says a cut its metadata carries
                out.append(rec)
                cut = e.get("source_truncated")
                if cut and cut_source(rec) is None:  # an import older than that metadata: say it here
                    say_cut_source(e["name"], str(self.dir / e["file"]), cut)
            else:  # listed as recorded, gone from the disk: a standpoint the study must not drop silently
                warn(f"standpoint {e['name']} is listed as {e.get('status')} in {SESSION_FILE} but its "
                     f"recording {e['file']} is missing; it is left out", str(self.dir), "missing-recording")
        return out

    def discard(self, name: str, reason: str = "") -> None:
        """Mark a standpoint discarded; its file is renamed aside, never deleted."""
        for e in self.data.get("standpoints", []):
            if e["name"] == name and e["status"] in ("complete", "partial"):
                src = self.dir / e["file"]
                n = sum(1 for x in self.data["standpoints"] if x["status"] == "discarded") + 1
                dst = self.dir / f"{name}.discarded-{n}.mcap"
                if src.exists():
                    src.rename(dst)
                e.update(status="discarded", file=dst.name, reason=reason, discarded=_now())
        self._save()

    def _entry(self, name: str, file: str) -> dict[str, Any]:
        e = {"name": name, "file": file, "status": "recording", "started": _now()}
        self.data.setdefault("standpoints", []).append(e)
        return e

    def standpoint_writer(
        self,
        name: str,
        info: StreamInfo,
        standpoint: dict[str, Any] | None = None,
        *,
        compression: str = CAPTURE_COMPRESSION,
        queue_frames: int = 64,
        metadata: dict[str, Any] | None = None,
        blocking: bool = False,
        color_encoding: str = "rgb8",
    ) -> StandpointWriter:
        """A background writer for one standpoint; refuses a name that is complete already."""
        if self.read_only:
            raise CaptureError(f"{self.dir}: session opened read-only")
        final = self.dir / f"{name}.mcap"
        if final.exists() or self.status(name) == "complete":
            raise InputError(final, "exists already; captures are never overwritten (discard it first)")
        partial = self.dir / f"{name}.mcap.partial"
        if partial.exists():  # an earlier attempt that crashed: keep it aside
            n = 1
            while (self.dir / f"{name}.attempt-{n}.mcap.partial").exists():
                n += 1
            aside = self.dir / f"{name}.attempt-{n}.mcap.partial"
            partial.rename(aside)
            for e in self.data.get("standpoints", []):
                if e["file"] == partial.name:
                    e["file"] = aside.name
        meta: dict[str, Any] = {
            "device": self.data.get("device") or {},
            "protocol": self.data.get("protocol"),
            "standpoint": dict(standpoint or {}, name=name),
            "calibration": self.data.get("calibration"),
        }
        meta.update(metadata or {})
        entry = self._entry(name, partial.name)
        entry["standpoint"] = dict(standpoint or {})
        self._save()
        return StandpointWriter(self, entry, partial, final, info, meta, compression, queue_frames, blocking,
                                color_encoding)


_STOP = object()


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold SIGINT back while the block runs (main thread only) and raise it afterwards, also when
    the block fails: the Ctrl-C is not lost behind that error, which becomes its cause."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum: int, frame: Any) -> None:
        caught.append(signum)

    previous = signal.signal(signal.SIGINT, hold)
    try:
        yield
    except Exception as exc:
        if caught:
            raise KeyboardInterrupt from exc
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


class StandpointWriter:
    """Context manager: `write()` only enqueues (never blocks); a thread serialises to MCAP.

    When the bounded queue is full the frame set is dropped and counted (`dropped`), since blocking
    the camera loop would drop frames in the driver instead, silently.
    """

    def __init__(
        self,
        session: Session,
        entry: dict[str, Any],
        partial: Path,
        final: Path,
        info: StreamInfo,
        metadata: dict[str, Any],
        compression: str,
        queue_frames: int,
        blocking: bool = False,
        color_encoding: str = "rgb8",
    ) -> None:

        self.session = session
        self.entry = entry
        self.partial = partial
        self.final = final
        self.dropped = 0
        self.blocking = blocking  # imports wait instead of dropping; a live camera must not
        self.max_queue = 0
        self.max_put_s = 0.0
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_frames)
        self._error: BaseException | None = None
        self._writer = McapFileWriter(partial, info, metadata, compression=compression,
                                      color_encoding=color_encoding)
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"mcap-writer-{final.stem}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            if self._error is not None:
                continue  # drain so producers never block
            try:
                kind, payload = item
                if kind == "frame":
                    self._writer.write(payload)
                elif kind == "temp":
                    self._writer.write_temperature(*payload)
                else:
                    self._writer.add_metadata(*payload)
            except BaseException as exc:  # surfaced on the next write() / close()
                self._error = exc

    def _put(self, item: Any) -> bool:
        if self._closed:
            raise CaptureError(f"{self.final}: writer is closed")
        if self._error is not None:
            raise CaptureError(f"{self.partial}: writing failed: {self._error}") from self._error
        t0 = time.perf_counter()
        try:
            if self.blocking:
                self._queue.put(item)
            else:
                self._queue.put_nowait(item)
            ok = True
        except queue.Full:
            ok = False
        self.max_put_s = max(self.max_put_s, time.perf_counter() - t0)
        self.max_queue = max(self.max_queue, self._queue.qsize())
        return ok

    def write(self, fs: FrameSet) -> bool:
        """Enqueue a frame set; False (and `dropped` + 1) when the queue is full. Arrays must not be
        mutated by the caller afterwards."""
        ok = self._put(("frame", fs))
        if not ok:
            self.dropped += 1
            log.warning("%s: writer queue full, frame %d dropped", self.final.name, fs.index)
        return ok

    def write_temperature(self, t_ns: int, temperatures: dict[str, float]) -> None:
        if not self._put(("temp", (int(t_ns), dict(temperatures)))):
            self.dropped += 0  # temperatures are best effort
            log.warning("%s: writer queue full, temperature sample dropped", self.final.name)

    def set_metadata(self, name: str, value: Any) -> None:
        """Add/replace a metadata record (e.g. the measured standpoint); the last one wins."""
        self._queue.put(("meta", (name, value)))  # blocking: rare and must not be lost

    def update_standpoint(self, **values: Any) -> None:
        """Record measured values (distance_m, inclination_deg, ...) in the MCAP and session.json."""
        self.entry.setdefault("standpoint", {}).update(values)
        self.set_metadata("standpoint", dict(self.entry["standpoint"], name=self.final.name.split(".")[0]))

    def close(self, ok: bool = True) -> None:
        """Drain the queue, finish the MCAP, rename it into place, mark the standpoint complete.

        Ctrl-C during the close is held back until the file is finished (a half-written summary
        would make the whole standpoint unreadable), then raised.
        """
        if self._closed:
            return
        with _sigint_deferred():
            self._close(ok)

    def _close(self, ok: bool) -> None:
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join()
        w = self._writer
        self.entry.update(
            frames=w.frames_written,
            dropped_frames=self.dropped,
            finished=_now(),
            first_index=w.first_index,
            last_index=w.last_index,
        )
        if self._error is not None or not ok:
            w.abort() if self._error is not None else w.close()
            self.entry["status"] = "partial"
            if self._error is not None:
                self.entry["note"] = f"writer failed: {self._error}"
            self.session._save()
            if self._error is not None:
                raise CaptureError(f"{self.partial}: writing failed: {self._error}") from self._error
            return
        w.close()
        if self.final.exists():
            raise CaptureError(f"{self.final}: appeared while recording; left as {self.partial.name}")
        self.partial.replace(self.final)
        self.entry.update(status="complete", file=self.final.name)
        self.session._save()

    def __enter__(self) -> StandpointWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close(ok=exc_type is None)
