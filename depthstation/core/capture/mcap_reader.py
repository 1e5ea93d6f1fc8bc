"""Reading our MCAP capture format (see docs/capture-format.md); tolerates files cut short by a crash."""

from __future__ import annotations

import contextlib
import io
import json
import mmap
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata
from mcap.stream_reader import StreamReader

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture import rosmsgs
from depthstation.core.capture.recording import NotThisFormat, Recording
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.run_warnings import warn

MCAP_MAGIC = b"\x89MCAP0\r\n"


class MappedFile:
    """A file read through a read-only memory map: `read(n)` gives memoryview slices of it.

    Why: `read()` copies every chunk into a new 4 MiB buffer, and a process that imports once pays
    for fresh pages on each (the kernel zeroes them: up to 2-3x the CPU of the import itself); a
    map reads the page cache in place. Arrays made from the data keep the map alive (it is never
    closed explicitly), so frames stay valid after their file is closed.
    """

    def __init__(self, f: Any) -> None:
        self._map = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        with contextlib.suppress(AttributeError, OSError):  # not every platform has madvise
            self._map.madvise(mmap.MADV_SEQUENTIAL)
        self._view = memoryview(self._map)
        self._pos = 0

    def read(self, n: int = -1) -> memoryview:
        end = len(self._view) if n < 0 else min(self._pos + n, len(self._view))
        out = self._view[self._pos : end]
        self._pos = end
        return out


def _stream(f: Any) -> Any:
    """A map of `f` where it can be mapped (a regular, non-empty file), else `f` itself."""
    try:
        return MappedFile(f)
    except (ValueError, OSError, AttributeError, io.UnsupportedOperation):
        return f


def mcap_messages(f: Any, topics: dict[int, str]) -> Iterator[tuple[int, int, memoryview]]:
    """(channel id, log time, message data) in file order, filling `topics` from Channel records.

    Chunks are parsed here with memoryviews instead of mcap's record objects, over a memory map of
    the file: no copy of any image between the page cache and the arrays, which is what lifts the
    reader above 300 frame sets/s. Raises on a cut-off file.
    """

    for r in StreamReader(_stream(f), emit_chunks=True, record_size_limit=None).records:
        if isinstance(r, Chunk):
            if r.compression == "":
                raw: bytes = r.data
            elif r.compression == "lz4":

                raw = lz4.frame.decompress(r.data)
            elif r.compression == "zstd":

                raw = zstandard.ZstdDecompressor().decompress(r.data, max_output_size=r.uncompressed_size)
            else:
                raise ValueError(f"unknown chunk compression {r.compression!r}")
            mv = memoryview(raw)
            pos, end = 0, len(mv)
            while pos + 9 <= end:
                op = mv[pos]
                (length,) = struct.unpack_from("<Q", mv, pos + 1)
                body = mv[pos + 9 : pos + 9 + length]
                pos += 9 + length
                if op == 0x05:  # Message: channel u16, sequence u32, log u64, publish u64, data
                    channel_id, _, log_time = struct.unpack_from("<HIQ", body, 0)
                    yield channel_id, log_time, body[22:]
                elif op == 0x04:  # Channel: id u16, schema u16, topic (u32 length + utf-8)
                    cid, _, n = struct.unpack_from("<HHI", body, 0)
                    topics[cid] = bytes(body[8 : 8 + n]).decode()
        elif isinstance(r, Channel):
            topics[r.id] = r.topic
        elif isinstance(r, Message):
            yield r.channel_id, r.log_time, memoryview(r.data)


def cut_source(rec: Recording) -> dict[str, Any] | None:
    """The cut a recording carries: itself cut short (the frames recovered so far), or written from
    one that was (its metadata `source`, by import or compact); None when whole. Why: a copy of a
    cut recording is a complete file, and a study of it must still say it holds only part."""
    if getattr(rec, "truncated", False):
        return {"path": str(rec.path), "recovered_frames": getattr(rec, "recovered_frames", None)}
    earlier = rec.metadata.get("source")
    if isinstance(earlier, dict) and earlier.get("truncated"):
        return {"path": earlier.get("cut_path") or earlier.get("path"),
                "recovered_frames": earlier.get("recovered_frames")}
    return None


def say_cut_source(name: str, where: str, cut: dict[str, Any]) -> None:
    """The warning every study of a recording written from a cut one gives (once per place)."""
    warn(f"standpoint {name} was written from {cut.get('path')}, which is cut short: it holds only the "
         f"{cut.get('recovered_frames')} frames recovered from it", where, "truncated-input")


class McapRecording(Recording):
    """Our capture format (see docs/capture-format.md); tolerates files cut short by a crash.

    Frame arrays are read-only views of the file data (zero-copy for speed): copy to modify.
    """

    truncated: bool = False
    recovered_frames: int | None = None

    def _iter(self, start: int) -> Iterator[FrameSet]:

        topics: dict[int, str] = {}
        expect_topics = {mw.COLOR_TOPIC: "color", mw.INFRARED_TOPIC: "infrared"}
        group: dict[str, Any] | None = None
        count = 0
        seen = 0

        def complete(g: dict[str, Any]) -> bool:
            """All images the frame record announces have arrived (a cut may fall between them)."""
            return all(k in g for k in g["record"].get("streams", ["depth"]))

        def emit(g: dict[str, Any]) -> FrameSet:
            rec = g["record"]
            return FrameSet(
                index=int(rec["index"]),
                timestamp_ns=int(rec["timestamp_ns"]),
                depth=rosmsgs.image_array(rosmsgs.deserialize(g["depth"], rosmsgs.IMAGE)),
                color=(
                    rosmsgs.image_array(rosmsgs.deserialize(g["color"], rosmsgs.IMAGE))
                    if "color" in g
                    else None
                ),
                infrared=(
                    rosmsgs.image_array(rosmsgs.deserialize(g["infrared"], rosmsgs.IMAGE))
                    if "infrared" in g
                    else None
                ),
                metadata=dict(rec.get("metadata") or {}),
            )

        truncated = False
        with self.path.open("rb") as f:
            records = mcap_messages(f, topics)
            while True:
                try:
                    channel_id, _, data = next(records)
                except StopIteration:
                    break
                except Exception:  # mcap raises several kinds on a cut-off file
                    truncated = True
                    break
                topic = topics.get(channel_id)
                if topic == mw.FRAME_TOPIC:
                    if group is not None and complete(group):
                        if seen >= start:
                            yield emit(group)
                        seen += 1
                        count += 1
                    group = {"record": json.loads(rosmsgs.deserialize(data, rosmsgs.STRING).data)}
                elif group is not None and topic == mw.DEPTH_TOPIC:
                    group["depth"] = data
                elif group is not None and topic in expect_topics:
                    group[expect_topics[topic]] = data
        if group is not None and complete(group):
            if seen >= start:
                yield emit(group)
            count += 1
        if truncated:
            self.truncated = True
            self.recovered_frames = count
            if count == 0:  # not a short recording: nothing at all (it was imported as a 0-frame session)
                raise InputError(self.path, "is cut short before its first complete frame: it holds no frame "
                                            "to read")
            warn(f"recording is cut short; recovered {count} frames from its complete chunks", str(self.path),
                 "truncated-input")

    def temperatures(self) -> dict[str, tuple[list[int], list[float]]]:


        out: dict[str, tuple[list[int], list[float]]] = {}
        topics: dict[int, str] = {}
        with self.path.open("rb") as f:
            try:
                for channel_id, _, data in mcap_messages(f, topics):
                    if topics.get(channel_id) == mw.TEMPERATURE_TOPIC:
                        m = rosmsgs.deserialize(data, rosmsgs.TEMPERATURE)
                        ts, vs = out.setdefault(str(m.header.frame_id), ([], []))
                        ts.append(rosmsgs.stamp_ns(m.header))
                        vs.append(float(m.temperature))
            except Exception:
                pass
        return out


def open_mcap(path: Path) -> McapRecording:
    """Read metadata, channels and counts; from the summary when the file is complete."""


    meta: dict[str, Any] = {}
    topics: dict[int, str] = {}
    counts: dict[int, int] = {}
    summary = None
    try:
        with Path(path).open("rb") as f:
            head = f.read(8)
            if head != MCAP_MAGIC:
                raise InputError(path, "is no MCAP file (bad magic)")
            f.seek(0)
            reader = SeekingReader(f)
            try:
                summary = reader.get_summary()
            except Exception:
                summary = None
            if summary is not None:
                for md in reader.iter_metadata():
                    meta[md.name] = md.metadata
                topics = {c.id: c.topic for c in summary.channels.values()}
                if summary.statistics is not None:
                    counts = dict(summary.statistics.channel_message_counts)
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror}") from exc
    except McapError as exc:
        raise InputError(path, f"is no readable MCAP file ({exc})") from exc
    if summary is None:
        # Cut short: metadata records precede the chunks; channels sit in the first chunk.
        with Path(path).open("rb") as f:
            try:
                for r in StreamReader(f, record_size_limit=None).records:
                    if isinstance(r, Metadata):
                        meta[r.name] = r.metadata
                    elif isinstance(r, Channel):
                        topics[r.id] = r.topic
                    elif isinstance(r, (Message, Chunk)) and mw.DEPTH_TOPIC in topics.values():
                        break
            except Exception:
                pass
    if "streams" not in meta and summary is not None:
        raise NotThisFormat(path, "is no depthstation recording (no 'streams' metadata record)")
    if summary is None and "streams" not in meta:  # a cut rosbag2 MCAP: the ROS reader recovers its chunks
        raise NotThisFormat(path, "is cut short before its first complete chunk: no frame can be recovered")
    if summary is None and mw.DEPTH_TOPIC not in topics.values():
        raise InputError(path, "is cut short before its first complete chunk: no frame can be recovered")
    if "streams" not in meta:
        raise InputError(path, "is no depthstation recording (no 'streams' metadata record)")
    if mw.DEPTH_TOPIC not in topics.values():
        raise InputError(path, "has no depth stream")
    docs: dict[str, Any] = {}
    for name, record in meta.items():
        try:
            docs[name] = json.loads(record["json"])
        except (KeyError, ValueError) as exc:
            raise InputError(path, f"metadata record {name!r} is no JSON document") from exc
    info = StreamInfo.from_dict(docs.pop("streams"))
    by_topic = {topics[cid]: n for cid, n in counts.items() if cid in topics}
    stream_counts = {
        k: by_topic[t]
        for k, t in (
            ("depth", mw.DEPTH_TOPIC),
            ("color", mw.COLOR_TOPIC),
            ("infrared", mw.INFRARED_TOPIC),
            ("temperature", mw.TEMPERATURE_TOPIC),
        )
        if t in by_topic
    }
    frame_count = by_topic.get(mw.FRAME_TOPIC) if summary is not None else None
    name = path.name.split(".")[0]
    rec = McapRecording(name, path, info, docs, frame_count, stream_counts)
    rec.truncated = summary is None  # said with the frames recovered, once they are read
    cut = None if rec.truncated else cut_source(rec)
    if cut is not None:
        say_cut_source(name, str(path), cut)
    return rec
