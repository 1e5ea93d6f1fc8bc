"""Reading recordings: our MCAP, RealSense `.bag`/`.db3`, PNG folders, as one `Recording` model.

Every importer maps its source into StreamInfo + FrameSets here, so later stages never special-case
a file format.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.camera import Extrinsics, Intrinsics, StreamInfo
from depthstation.errors import InputError
from depthstation.frames import FrameSet

log = logging.getLogger("depthstation.capture")

RECORDING_SUFFIXES = (".mcap", ".bag", ".db3")


class Recording:
    """One standpoint or sequence: stream geometry, metadata and an iterator over its frame sets."""

    name: str
    path: Path
    info: StreamInfo
    metadata: dict[str, Any]
    frame_count: int | None
    stream_counts: dict[str, int]

    def __init__(
        self,
        name: str,
        path: Path,
        info: StreamInfo,
        metadata: dict[str, Any],
        frame_count: int | None,
        stream_counts: dict[str, int] | None = None,
    ) -> None:
        self.name = name
        self.path = Path(path)
        self.info = info
        self.metadata = metadata
        self.frame_count = frame_count
        self.stream_counts = dict(stream_counts or {})

    def _iter(self, start: int) -> Iterator[FrameSet]:
        raise NotImplementedError

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        """Frame sets in recording order, skipping `start` of them and yielding at most `limit`."""
        if limit is not None and limit <= 0:
            return
        for n, fs in enumerate(self._iter(start), start=1):
            yield fs
            if limit is not None and n >= limit:
                return

    def temperatures(self) -> dict[str, tuple[list[int], list[float]]]:
        """Device temperatures over time per sensor: name -> (timestamps ns, degrees C)."""
        return {}

    def summary(self) -> dict[str, Any]:
        """What `capture info` shows: streams, sizes, counts, geometry, device."""
        return {
            "name": self.name,
            "path": str(self.path),
            "frame_count": self.frame_count,
            "stream_counts": self.stream_counts,
            "info": self.info.to_dict(),
            "metadata": self.metadata,
        }

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {str(self.path)!r}, frames={self.frame_count})"


# ---------------------------------------------------------------------------------------------
# Our MCAP
# ---------------------------------------------------------------------------------------------
def _mcap_messages(f: Any, topics: dict[int, str]) -> Iterator[tuple[int, memoryview]]:
    """(channel id, message data) in file order, filling `topics` from Channel records.

    Chunks are parsed here with memoryviews instead of mcap's record objects: that saves two copies
    of every image and is what lifts the reader above 300 frame sets/s. Raises on a cut-off file.
    """
    import struct

    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader

    for r in StreamReader(f, emit_chunks=True, record_size_limit=None).records:
        if isinstance(r, Chunk):
            if r.compression == "":
                raw: bytes = r.data
            elif r.compression == "lz4":
                import lz4.frame

                raw = lz4.frame.decompress(r.data)
            elif r.compression == "zstd":
                import zstandard

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
                    (channel_id,) = struct.unpack_from("<H", body, 0)
                    yield channel_id, body[22:]
                elif op == 0x04:  # Channel: id u16, schema u16, topic (u32 length + utf-8)
                    cid, _, n = struct.unpack_from("<HHI", body, 0)
                    topics[cid] = bytes(body[8 : 8 + n]).decode()
        elif isinstance(r, Channel):
            topics[r.id] = r.topic
        elif isinstance(r, Message):
            yield r.channel_id, memoryview(r.data)


class McapRecording(Recording):
    """Our capture format (see docs/capture-format.md); tolerates files cut short by a crash.

    Frame arrays are read-only views of the file data (zero-copy for speed): copy to modify.
    """

    truncated: bool = False
    recovered_frames: int | None = None

    def _iter(self, start: int) -> Iterator[FrameSet]:
        from depthstation.capture import mcap_writer as mw
        from depthstation.capture import rosmsgs

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
            records = _mcap_messages(f, topics)
            while True:
                try:
                    channel_id, data = next(records)
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
            log.warning(
                "%s: recording is cut short; recovered %d frames from its complete chunks", self.path, count
            )

    def temperatures(self) -> dict[str, tuple[list[int], list[float]]]:

        from depthstation.capture import mcap_writer as mw
        from depthstation.capture import rosmsgs

        out: dict[str, tuple[list[int], list[float]]] = {}
        topics: dict[int, str] = {}
        with self.path.open("rb") as f:
            try:
                for channel_id, data in _mcap_messages(f, topics):
                    if topics.get(channel_id) == mw.TEMPERATURE_TOPIC:
                        m = rosmsgs.deserialize(data, rosmsgs.TEMPERATURE)
                        ts, vs = out.setdefault(str(m.header.frame_id), ([], []))
                        ts.append(rosmsgs.stamp_ns(m.header))
                        vs.append(float(m.temperature))
            except Exception:
                pass
        return out


def _open_mcap(path: Path) -> McapRecording:
    """Read metadata, channels and counts; from the summary when the file is complete."""
    from mcap.exceptions import McapError
    from mcap.reader import SeekingReader
    from mcap.records import Channel, Chunk, Message, Metadata
    from mcap.stream_reader import StreamReader

    from depthstation.capture import mcap_writer as mw

    meta: dict[str, Any] = {}
    topics: dict[int, str] = {}
    counts: dict[int, int] = {}
    summary = None
    try:
        with Path(path).open("rb") as f:
            head = f.read(8)
            if head != b"\x89MCAP0\r\n":
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
    return McapRecording(name, path, info, docs, frame_count, stream_counts)


# ---------------------------------------------------------------------------------------------
# PNG folders (layout of alr-d435-charuco)
# ---------------------------------------------------------------------------------------------
def _png_frames(folder: Path) -> list[tuple[int, Path, Path | None]]:
    import re

    out = []
    for p in folder.iterdir():
        m = re.fullmatch(r"frame(\d+)_depth\.png", p.name)
        if m:
            k = int(m.group(1))
            c = folder / f"frame{k}_color.png"
            out.append((k, p, c if c.is_file() else None))
    return sorted(out)


class PngRecording(Recording):
    """A folder of `frameK_depth.png` (16 bit, aligned to colour) and `frameK_color.png`."""

    def _iter(self, start: int) -> Iterator[FrameSet]:
        import cv2

        fps = self.info.fps or 30.0
        for k, dpath, cpath in _png_frames(self.path)[start:]:
            depth = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
                raise InputError(dpath, "is no 16-bit single-channel depth PNG")
            color = None
            if cpath is not None:
                bgr = cv2.imread(str(cpath), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise InputError(cpath, "is no readable colour image")
                color = np.ascontiguousarray(bgr[..., ::-1])
            yield FrameSet(
                index=k,
                timestamp_ns=round(k * 1e9 / fps),
                depth=depth.astype(np.uint16, copy=False),
                color=None if color is None else color.astype(np.uint8, copy=False),
                metadata={"source_file": dpath.name, "timestamp_source": "nominal fps"},
            )


def _png_camera_json(folder: Path) -> Path | None:
    for d in (folder, folder.parent):
        if (d / "camera.json").is_file():
            return d / "camera.json"
    return None


def _open_png(folder: Path) -> PngRecording:
    cam_path = _png_camera_json(folder)
    if cam_path is None:
        raise InputError(folder, "PNG folder without camera.json (here or one level up)")
    try:
        cam = json.loads(cam_path.read_text())
        color = Intrinsics.from_dict(cam["color"])
    except (ValueError, KeyError) as exc:
        raise InputError(cam_path, f"bad camera.json: {exc}") from exc
    aligned = bool(cam.get("depth_aligned_to_color", True))
    depth_intr = color if aligned else Intrinsics.from_dict(cam["depth"])
    frames = _png_frames(folder)
    if not frames:
        raise InputError(folder, "has no frameK_depth.png files")
    device = {"name": cam.get("sensor", "unknown")}
    baseline = cam.get("stereo_baseline_m", cam.get("stereo_baseline_m_nominal"))
    info = StreamInfo(
        depth_intrinsics=depth_intr,
        color_intrinsics=color,
        depth_to_color=Extrinsics(),
        depth_units_m=float(cam.get("depth_units_m", 0.001)),
        depth_aligned_to_color=aligned,
        baseline_m=None if baseline is None else float(baseline),
        fps=float(cam.get("fps", 30.0)),
        device=device,
        # aligned depth: disparity physics lives in the stereo imager's own pixels
        stereo_intrinsics=(Intrinsics.from_dict(cam["depth_unaligned"])
                           if aligned and isinstance(cam.get("depth_unaligned"), dict) else None),
    )
    meta: dict[str, Any] = {"device": device, "source": {"kind": "png", "camera_json": str(cam_path)}}
    if (cam_path.parent / "board.json").is_file():
        meta["board"] = json.loads((cam_path.parent / "board.json").read_text())
    if "depth_unaligned" in cam:
        meta["depth_unaligned_intrinsics"] = cam["depth_unaligned"]
    n_color = sum(1 for f in frames if f[2] is not None)
    return PngRecording(
        folder.name, folder, info, meta, len(frames), {"depth": len(frames), "color": n_color}
    )


# ---------------------------------------------------------------------------------------------
# Dispatch
# ---------------------------------------------------------------------------------------------
def _is_png_folder(path: Path) -> bool:
    return path.is_dir() and any(path.glob("frame*_depth.png"))


def open_recording(path: Path) -> Recording:
    """Open one standpoint: `.mcap`, `.bag`, `.db3` (file or rosbag2 directory) or a PNG folder."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "does not exist")
    if path.is_dir():
        if _is_png_folder(path):
            return _open_png(path)
        if (path / "metadata.yaml").is_file():
            from depthstation.capture.realsense import open_realsense

            return open_realsense(path)
        raise InputError(path, "folder is no recording (no frameK_depth.png, no rosbag2 metadata.yaml)")
    suffix = path.suffix.lower()
    name = path.name
    if name.endswith(".mcap.partial"):
        return _open_mcap(path)
    if suffix == ".mcap":
        return _open_mcap(path)
    if suffix in (".bag", ".db3"):
        from depthstation.capture.realsense import open_realsense

        return open_realsense(path)
    with Path(path).open("rb") as f:
        head = f.read(16)
    if head.startswith(b"\x89MCAP0"):
        return _open_mcap(path)
    raise InputError(path, "is no recording (expected .mcap, .bag, .db3 or a PNG folder)")


def open_inputs(paths: Sequence[Path]) -> list[Recording]:
    """Expand session dirs, PNG dataset roots and folders of recordings into standpoints."""
    out: list[Recording] = []
    for p in map(Path, paths):
        if not p.exists():
            raise InputError(p, "does not exist")
        if p.is_dir() and (p / "session.json").is_file():
            from depthstation.capture.session import Session

            out.extend(Session.open(p, read_only=True).recordings())
        elif p.is_dir() and not _is_png_folder(p) and not (p / "metadata.yaml").is_file():
            subs = sorted(d for d in p.iterdir() if _is_png_folder(d))
            files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in RECORDING_SUFFIXES)
            bags = sorted(d for d in p.iterdir() if d.is_dir() and (d / "metadata.yaml").is_file())
            if not (subs or files or bags):
                raise InputError(
                    p, "holds no recordings (session.json, PNG standpoint folders, .mcap/.bag/.db3)"
                )
            out.extend(open_recording(x) for x in [*subs, *files, *bags])
        else:
            out.append(open_recording(p))
    return out
