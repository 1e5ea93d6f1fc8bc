"""RealSense recordings (`.bag` ROS 1, file version 3; `.db3` ROS 2, file version 4) via rosbags.

Parsing the `/device_0/sensor_N/...` topics directly (instead of pyrealsense2 playback) keeps every
frame (playback's syncer drops and repeats frames) and is bit-exact. Version 3 stores numbers in
typed messages; version 4 (SDK 2.59) stores most as `key=value;` strings, images PNG-compressed and
the precise geometry in per-frame CameraInfo and `/tf_static`.
"""

from __future__ import annotations

import contextlib
import re
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.capture import rosmsgs
from depthstation.core.capture.recording import NotThisFormat, Recording
from depthstation.core.capture.ros_bag import cut_mcap_files
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet

_STREAM_RE = re.compile(r"^/device_(\d+)/sensor_(\d+)/([A-Za-z]+)_(\d+)/(.*)$")
_KINDS = {"Depth": "depth", "Color": "color", "Infrared": "infrared"}


def _kv_string(text: str) -> dict[str, str]:
    """'a=1;b=2;' -> {'a': '1', 'b': '2'} (version 4 info strings)."""
    out = {}
    for part in str(text).split(";"):
        if "=" in part:
            k, v = part.split("=", 1)
            out[k.strip()] = v.strip()
    return out


def _snake(key: str) -> str:
    return re.sub(r"[^0-9a-z]+", "_", key.strip().lower()).strip("_")


def _scalar(msg: Any) -> float | str:
    """Option value; float32 values come back as their shortest decimal (0.001, not 0.0010000000475)."""
    data = msg.data
    try:
        return float(str(np.float32(float(data))))
    except (TypeError, ValueError):
        return str(data)


@dataclass
class _Stream:
    kind: str
    sensor: int
    prefix: str  # /device_0/sensor_N/Kind_I
    fps: float | None = None
    encoding: str | None = None
    intr: Intrinsics | None = None  # from CameraInfo (float32 exact)
    intr_str: Intrinsics | None = None  # from the version 4 info string (6 decimals)
    model_hint: str | None = None
    ref_to_stream: Extrinsics | None = None  # librealsense extrinsics reference -> this stream
    stream_to_ref: Extrinsics | None = None  # /tf_static (v4): pose of this stream in the reference
    frames: list[dict[str, Any]] = field(default_factory=list)  # per image: bag time, number, time


class RealsenseRecording(Recording):
    """A RealSense Viewer / rs.recorder file; one FrameSet per depth frame, others paired by time."""

    def __init__(
        self, *args: Any, streams: dict[str, _Stream], version: int, typestore: Any, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        self._streams = streams
        self.version = version
        self._typestore = typestore

    def _reader(self) -> Any:

        return AnyReader([self.path], default_typestore=self._typestore)

    def _pairing(self) -> dict[tuple[str, int], dict[str, int]]:
        """depth bag time -> {kind: bag time of the nearest frame of that stream within 1 period}."""
        depth = self._streams["depth"]
        out: dict[tuple[str, int], dict[str, int]] = {}
        for kind in ("color", "infrared"):
            s = self._streams.get(kind)
            if s is None or not s.frames:
                continue
            times = np.array([f["time_ms"] for f in s.frames])
            period_ms = 1000.0 / (s.fps or depth.fps or 30.0)
            for f in depth.frames:
                i = int(np.argmin(np.abs(times - f["time_ms"])))
                if abs(times[i] - f["time_ms"]) <= period_ms + 1e-6:
                    out.setdefault(("depth", f["bag_t"]), {})[kind] = s.frames[i]["bag_t"]
        return out

    def _iter(self, start: int) -> Iterator[FrameSet]:
        depth = self._streams["depth"]
        pairing = self._pairing()
        by_bag_t = {f["bag_t"]: f for f in depth.frames}
        depth_order = [f["bag_t"] for f in depth.frames][start:]
        if not depth_order:
            return
        image_topics = {s.prefix: k for k, s in self._streams.items()}
        with self._reader() as reader:
            conns = [c for c in reader.connections if _image_topic(c.topic) in image_topics]

            def messages() -> Iterator[tuple[str, int, Any]]:
                for conn, bag_t, raw in reader.messages(connections=conns):
                    yield (image_topics[_image_topic(conn.topic)], bag_t,
                           lambda raw=raw, conn=conn: _decode_image(reader.deserialize(raw, conn.msgtype),
                                                                    conn.msgtype))

            for bag_t, parts in assemble(messages(), pairing, depth_order):
                yield self._frameset(bag_t, parts, by_bag_t)

    def _frameset(self, bag_t: int, parts: dict[str, NDArray[Any]],
                  by_bag_t: dict[int, dict[str, Any]]) -> FrameSet:
        f = by_bag_t[bag_t]
        color, infra, d = parts.get("color"), parts.get("infrared"), parts["depth"]
        if d.dtype != np.uint16:
            raise InputError(self.path, f"depth frame {f['number']} is not 16 bit")
        if infra is not None and infra.ndim == 3:
            infra = infra[..., 0]
        meta = dict(f["metadata"])
        meta["frame_number"] = f["number"]
        meta["device_timestamp_ms"] = f["time_ms"]
        return FrameSet(
            index=int(f["number"]),
            timestamp_ns=int(f["epoch_ns"]),
            depth=d,
            color=color,
            infrared=None if infra is None else infra.astype(np.uint8, copy=False),
            metadata=meta,
        )


def assemble(messages: Iterable[tuple[str, int, Callable[[], Any]]],
             pairing: dict[tuple[str, int], dict[str, int]],
             depth_order: Sequence[int]) -> Iterator[tuple[int, dict[str, Any]]]:
    """Depth frames of `depth_order` (bag times), in that order, each with the images `pairing`
    gives it, from the file's messages (kind, bag time, loader) in file order.

    A colour or infrared frame that two depth frames share (a slower colour stream, a dropped frame)
    is kept until its last depth frame has it: taken away by the first, it left the second without
    colour and held every later frame in memory until the end of the file. Only images some depth
    frame wants are loaded.
    """
    wanted = set(depth_order)
    uses: Counter[tuple[str, int]] = Counter(
        key for t in depth_order for key in pairing.get(("depth", t), {}).items())
    first = depth_order[0] if len(depth_order) else 0
    images: dict[tuple[str, int], Any] = {}
    pending: deque[int] = deque()

    def take(t: int) -> tuple[int, dict[str, Any]]:
        parts: dict[str, Any] = {"depth": images.pop(("depth", t))}
        for key in pairing.get(("depth", t), {}).items():
            uses[key] -= 1
            img: Any = images.pop(key, None) if uses[key] <= 0 else images.get(key)
            # a frame set may be changed in place by its user: the later ones get their own copy
            parts[key[0]] = img.copy() if uses[key] > 0 and img is not None else img
        return t, parts

    for kind, t, load in messages:
        if kind == "depth":
            if t < first or t not in wanted:
                continue
            pending.append(t)
        elif uses[(kind, t)] <= 0:
            continue
        images[(kind, t)] = load()
        while pending and all(key in images for key in pairing.get(("depth", pending[0]), {}).items()):
            yield take(pending.popleft())
    while pending:
        yield take(pending.popleft())


def _image_topic(topic: str) -> str:
    """'/device_0/sensor_0/Depth_0/image/data[/compressed...]' -> '/device_0/sensor_0/Depth_0'."""
    i = topic.find("/image/data")
    return topic[:i] if i >= 0 else ""


def _decode_image(msg: Any, msgtype: str) -> NDArray[Any]:
    """Raw Image or the version 4 CompressedImage ('16UC1; compressedDepth png', 'rgb8; png ...')."""
    if msgtype.endswith("CompressedImage"):
        return rosmsgs.compressed_image_array(msg)
    return rosmsgs.image_array(msg)


def _typestore_for(path: Path) -> Any:

    ts = get_typestore(Stores.ROS2_HUMBLE)
    # realsense_msgs/StreamInfo appears in version 3 bags; they carry their own definitions, but
    # register it so a .db3 with it also decodes.

    with contextlib.suppress(Exception):
        ts.register(
            get_types_from_msg(
                "uint32 fps\nstring encoding\nbool is_recommended", "realsense_msgs/msg/StreamInfo"
            )
        )
    return ts


def is_rosbag2_folder(path: Path) -> bool:
    """A rosbag2 folder: `metadata.yaml` beside its storage files."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def open_realsense(path: Path) -> RealsenseRecording:
    """Parse device info, options, stream info, intrinsics, extrinsics and per-frame metadata."""

    ts = _typestore_for(path)
    try:
        reader_cm = AnyReader([path], default_typestore=ts)
        reader = reader_cm.__enter__()
    except Exception as exc:
        if cut_mcap_files(path):  # a rosbag2 MCAP cut short: the ROS reader recovers its complete chunks
            raise NotThisFormat(path, f"is no readable ROS bag ({type(exc).__name__}: {exc})") from exc
        raise InputError(path, f"is no readable ROS bag ({type(exc).__name__}: {exc})") from exc
    try:
        return _parse(path, reader, ts)
    except InputError:
        raise
    except (KeyError, ValueError, IndexError, TypeError, AttributeError) as exc:  # a broken or cut file
        raise InputError(path, f"is no readable RealSense recording ({type(exc).__name__}: {exc})") from exc
    finally:
        reader_cm.__exit__(None, None, None)


def _parse(path: Path, reader: Any, ts: Any) -> RealsenseRecording:
    streams: dict[str, _Stream] = {}
    device: dict[str, Any] = {}
    sensors: dict[int, dict[str, Any]] = {}
    version = 0
    counts: dict[str, int] = {}
    topics_small = []
    for c in reader.connections:
        m = _STREAM_RE.match(c.topic)
        if m and m.group(3) in _KINDS:
            kind = _KINDS[m.group(3)]
            if kind == "infrared" and kind in streams and int(m.group(4)) != 1:
                continue  # keep Infrared_1 (left imager) when both are recorded
            prefix = f"/device_{m.group(1)}/sensor_{m.group(2)}/{m.group(3)}_{m.group(4)}"
            streams.setdefault(kind, _Stream(kind, int(m.group(2)), prefix))
            if "/image/data" in c.topic:
                counts[kind] = counts.get(kind, 0) + c.msgcount
                continue
        if "/image/data" in c.topic:
            continue
        topics_small.append(c)
    if not any(c.topic.startswith("/device_") for c in reader.connections):
        raise NotThisFormat(path, "is no RealSense SDK recording (no /device_N topics)")
    if "depth" not in streams or counts.get("depth", 0) == 0:
        raise InputError(path, "has no depth stream")
    prefix_kind = {s.prefix: k for k, s in streams.items()}

    for conn, bag_t, raw in reader.messages(connections=topics_small):
        topic = conn.topic
        msg = reader.deserialize(raw, conn.msgtype)
        if topic == "/file_version":
            version = int(msg.data)
            continue
        if topic == "/device_0/info":
            kv = {msg.key: msg.value} if hasattr(msg, "key") else _kv_string(msg.data)
            device.update({_snake(k): v for k, v in kv.items()})
            continue
        sm = re.match(r"^/device_\d+/sensor_(\d+)/(.*)$", topic)
        if sm is None:
            if topic == "/tf_static":
                _tf_static(msg, streams)
            continue
        sensor = sensors.setdefault(int(sm.group(1)), {"options": {}})
        rest = sm.group(2)
        if rest == "info":
            kv = {msg.key: msg.value} if hasattr(msg, "key") else _kv_string(msg.data)
            sensor.update({_snake(k): v for k, v in kv.items()})
            continue
        om = re.match(r"^option/(.+)/value$", rest)
        if om:
            sensor["options"][om.group(1).replace("_", " ")] = _scalar(msg)
            continue
        sm2 = _STREAM_RE.match(topic)
        if sm2 is None:
            continue
        prefix = topic[: len(topic) - len(sm2.group(5)) - 1]
        kind_or_none = prefix_kind.get(prefix)
        if kind_or_none is None:
            continue
        kind = kind_or_none
        s = streams[kind]
        sub = sm2.group(5)
        if sub == "info":
            if hasattr(msg, "fps"):
                s.fps, s.encoding = float(msg.fps), str(msg.encoding)
            else:
                kv = _kv_string(msg.data)
                s.fps = float(kv["fps"]) if "fps" in kv else None
                s.encoding = kv.get("encoding")
        elif sub == "info/camera_info" or (sub == "image/camera_info" and s.intr is None):
            s.intr = rosmsgs.intrinsics_from_camera_info(msg)
        elif sub == "camera_info":  # version 4 string: 6 decimals, but the only exact model name
            kv = _kv_string(msg.data)
            s.model_hint = kv.get("model")
            s.intr_str = Intrinsics(
                int(kv["width"]),
                int(kv["height"]),
                float(kv["fx"]),
                float(kv["fy"]),
                float(kv["ppx"]),
                float(kv["ppy"]),
                rosmsgs.model_name(kv.get("model", "none")),
                tuple(float(x) for x in kv.get("coeffs", "0,0,0,0,0").split(",")),
            )
        elif sub.startswith("tf/"):
            if hasattr(msg, "rotation"):
                s.ref_to_stream = rosmsgs.extrinsics_from_transform(msg)
            else:
                kv = _kv_string(msg.data)
                s.ref_to_stream = Extrinsics.from_librealsense(
                    [float(x) for x in kv["rotation"].split(",")],
                    [float(x) for x in kv["translation"].split(",")],
                )
        elif sub == "image/metadata":
            _add_metadata(s, bag_t, msg)
    for s in streams.values():
        if s.intr is None:
            s.intr = s.intr_str
        elif s.model_hint:  # the CameraInfo says plumb_bob; the string names librealsense's model
            s.intr = Intrinsics(
                s.intr.width,
                s.intr.height,
                s.intr.fx,
                s.intr.fy,
                s.intr.ppx,
                s.intr.ppy,
                rosmsgs.model_name(s.model_hint),
                s.intr.coeffs,
            )
    _fill_frames_from_headers(reader, streams)
    return _build(path, streams, device, sensors, version, counts, ts)


def _add_metadata(s: _Stream, bag_t: int, msg: Any) -> None:
    """Per-frame metadata: v3 one KeyValue per key, v4 one 'k=v;' string per frame."""
    if hasattr(msg, "key"):
        if s.frames and s.frames[-1]["bag_t"] == bag_t:
            s.frames[-1]["metadata"][msg.key] = msg.value
        else:
            s.frames.append({"bag_t": bag_t, "metadata": {msg.key: msg.value}})
    else:
        s.frames.append({"bag_t": bag_t, "metadata": _kv_string(msg.data)})


def _tf_static(msg: Any, streams: dict[str, _Stream]) -> None:
    names = {"Depth": "depth", "Color": "color", "Infrared": "infrared", "Infrared 1": "infrared"}
    for t in msg.transforms:
        kind = names.get(str(t.child_frame_id))
        if kind in streams:
            streams[kind].stream_to_ref = rosmsgs.extrinsics_from_transform(t.transform)


def _fill_frames_from_headers(reader: Any, streams: dict[str, _Stream]) -> None:
    """Frame number and times: from metadata; version 3 needs the Image header for device time."""
    for s in streams.values():
        for f in s.frames:
            md = f["metadata"]
            number = md.get("Frame number", md.get("Frame Counter"))
            f["number"] = int(float(number)) if number is not None else None
            domain = str(md.get("timestamp_domain", ""))
            t_ms = md.get("timestamp")
            if t_ms is None and "Frame Timestamp" in md:
                t_ms = float(md["Frame Timestamp"]) / 1000.0  # microseconds in version 3
            f["time_ms"] = float(t_ms) if t_ms is not None else None
            sys_ms = float(md.get("system_time", 0) or 0)
            if domain.lower().replace(" ", "_") == "system_time" and f["time_ms"] is not None:
                f["epoch_ns"] = round(f["time_ms"] * 1e6)
            elif sys_ms > 0:
                f["epoch_ns"] = round(sys_ms * 1e6)
            else:
                f["epoch_ns"] = round((f["time_ms"] or 0.0) * 1e6)
    # Images without metadata (or missing fields): take the Image header (stamp, seq).
    need = {
        s.prefix: s
        for s in streams.values()
        if not s.frames or any(f["number"] is None or f["time_ms"] is None for f in s.frames)
    }
    if not need:
        return
    conns = [c for c in reader.connections
             if _image_topic(c.topic) in need and c.msgtype.endswith(("/Image", "/CompressedImage"))]
    if not conns:  # a declared stream that never delivered (no colour frames): nothing to read, and
        return     # an empty list would ask the reader for every message of the file
    for conn, bag_t, raw in reader.messages(connections=conns):
        s = need[_image_topic(conn.topic)]
        header = reader.deserialize(raw, conn.msgtype).header
        t_ms = rosmsgs.stamp_ns(header) / 1e6
        match = [f for f in s.frames if f["bag_t"] == bag_t]
        if not match:
            f = {"bag_t": bag_t, "metadata": {}, "number": None, "time_ms": None, "epoch_ns": 0}
            s.frames.append(f)
            match = [f]
        for f in match:
            if f["number"] is None:
                f["number"] = int(getattr(header, "seq", len(s.frames)))
            if f["time_ms"] is None:
                f["time_ms"] = t_ms
                f["epoch_ns"] = f["epoch_ns"] or round(t_ms * 1e6)
    for s in streams.values():
        s.frames.sort(key=lambda f: f["bag_t"])


def _build(
    path: Path,
    streams: dict[str, _Stream],
    device: dict[str, Any],
    sensors: dict[int, dict[str, Any]],
    version: int,
    counts: dict[str, int],
    ts: Any,
) -> RealsenseRecording:
    depth = streams["depth"]
    if depth.intr is None:
        raise InputError(path, "depth stream has no intrinsics")
    dopts = sensors.get(depth.sensor, {}).get("options", {})
    units = dopts.get("Depth Units")
    baseline_mm = dopts.get("Stereo Baseline")
    color = streams.get("color")
    infra = streams.get("infrared")

    def to_ref(s: _Stream) -> Extrinsics | None:
        if s.stream_to_ref is not None:
            return s.stream_to_ref
        if s.ref_to_stream is not None:
            return s.ref_to_stream.inverse()
        return None

    d2c = Extrinsics()
    if color is not None:
        td, tc = to_ref(depth), to_ref(color)
        if tc is not None:
            td_m = td.matrix if td is not None else np.eye(4)
            d2c = Extrinsics.from_matrix(np.linalg.inv(tc.matrix) @ td_m)
    options = {sensors[k].get("name", f"sensor_{k}"): sensors[k]["options"] for k in sorted(sensors)}
    dev = dict(device)
    dev["options"] = options
    fps = depth.fps
    info = StreamInfo(
        depth_intrinsics=depth.intr,
        color_intrinsics=None if color is None else color.intr,
        depth_to_color=d2c,
        depth_units_m=float(units) if isinstance(units, float) else 0.001,
        depth_aligned_to_color=False,
        infrared_intrinsics=None if infra is None else infra.intr,
        baseline_m=float(baseline_mm) / 1000.0 if isinstance(baseline_mm, float) else None,
        fps=fps,
        device={k: v for k, v in dev.items() if k != "options"},
    )
    meta = {"device": dev, "source": {"kind": "realsense", "file_version": version, "path": str(path)}}
    name = path.name.split(".")[0]
    if color is not None and color.intr is None:
        raise InputError(path, "colour stream has no intrinsics")
    return RealsenseRecording(
        name, path, info, meta, counts.get("depth"), counts, streams=streams, version=version, typestore=ts
    )
