"""ROS recordings as users record them: rosbag2 folders or single files (MCAP, sqlite3) and ROS 1
`.bag`, with the realsense-ros layouts found automatically.

Why a reader of its own: a `ros2 bag record` of the realsense-ros wrapper (ROS 2: `/camera/camera/
depth/image_rect_raw`; ROS 1: `/camera/depth/image_rect_raw`; any namespace) has none of the
RealSense SDK's `/device_0/...` topics nor our metadata records. Geometry comes from what ROS
carries: CameraInfo (intrinsics), the wrapper's `extrinsics/depth_to_color` topic or the
`/tf_static` chain (depth to colour), the infra2 CameraInfo or TF (baseline). Each stream keeps its
own header stamps; colour and infrared are matched to each depth frame by stamp within half a
depth frame period, in one streaming pass (no index is read first).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML, YAMLError

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture import rosmsgs
from depthstation.core.capture.mcap_reader import MCAP_MAGIC, mcap_messages
from depthstation.core.capture.recording import Recording, log, size_problem
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.run_warnings import warn

IMAGE_TYPES = (rosmsgs.IMAGE, rosmsgs.COMPRESSED_IMAGE)
TF_TOPICS = ("/tf_static", "/tf")
# realsense-ros image topics after the camera namespace, best first (ROS 1 and ROS 2 wrappers)
LAYOUT: dict[str, tuple[str, ...]] = {
    "depth": ("depth/image_rect_raw", "depth/image_raw", "aligned_depth_to_color/image_raw",
              "depth_registered/image_rect", "depth/image_rect"),
    "color": ("color/image_raw", "color/image_rect_raw", "color/image_rect_color", "rgb/image_raw"),
    "infrared": ("infra1/image_rect_raw", "infra1/image_raw", "infra/image_rect_raw", "ir/image_raw"),
}
TRANSPORTS = ("", "/compressedDepth", "/compressed")  # raw images first
DEPTH_UNITS_M = 0.001  # 16UC1 is millimetres (REP 118, realsense-ros); 32FC1 metres: `depth_units_for`
FINE_DEPTH_UNITS_M = 0.0001  # float depth finer than 1 mm (a D405, a filtered pipeline): 6.55 m of range


def depth_units_for(first: NDArray[Any]) -> float:
    """Depth units for a recording, from its first depth image.

    16-bit images are millimetres. Float metres (32FC1) that are whole millimetres (a z16 stream
    republished) stay at 1 mm. Finer ones are read at 0.1 mm: rounded to 1 mm, a D405's 0.2 mm
    noise read as 0.33 mm without a word. Not by the first image's range: bags of one session
    would then differ in units, and explain refuses a session of two cameras. Pixels beyond
    6.55 m, the 16-bit range at 0.1 mm, are said when they come (`RosRecording._depth`).
    """
    if first.dtype == np.uint16:
        return DEPTH_UNITS_M
    z = np.asarray(first, dtype=np.float64)
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0 or float(np.max(np.abs(z * 1000.0 - np.rint(z * 1000.0)))) < 0.01:
        return DEPTH_UNITS_M
    return FINE_DEPTH_UNITS_M


_EXTRINSICS_DEFS = {
    "realsense2_camera_msgs/msg/Extrinsics": "float64[9] rotation\nfloat64[3] translation",
    "realsense2_camera/msg/Extrinsics": "std_msgs/Header header\nfloat64[9] rotation\nfloat64[3] translation",
}


def transport_base(topic: str) -> str:
    """'/ns/depth/image_rect_raw/compressedDepth' -> '/ns/depth/image_rect_raw'."""
    for suffix in TRANSPORTS[1:]:
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def camera_namespace(image_topic: str) -> str:
    """'/camera/camera/depth/image_rect_raw' -> '/camera/camera/' (where the wrapper's topics live)."""
    stream_dir = transport_base(image_topic).rsplit("/", 1)[0]
    return stream_dir.rsplit("/", 1)[0] + "/"


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo beside an image topic (image_transport's convention)."""
    return transport_base(image_topic).rsplit("/", 1)[0] + "/camera_info"


@dataclass
class RosStream:
    """One image stream of the recording: its topic, message type, geometry and frame id."""

    kind: str
    topic: str
    msgtype: str
    count: int
    info_topic: str
    intrinsics: Intrinsics | None = None
    frame_id: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def typestore() -> Any:
    """ROS 2 Humble types plus the realsense-ros extrinsics messages (for bags without definitions)."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in _EXTRINSICS_DEFS.items():
        with contextlib.suppress(Exception):
            ts.register(get_types_from_msg(text, name))
    return ts


def _reader(path: Path, ts: Any) -> Any:
    try:
        return AnyReader([path], default_typestore=ts)
    except Exception as exc:
        raise InputError(path, f"is no readable ROS bag ({type(exc).__name__}: {exc})") from exc


def _topic_list(conns: list[Any]) -> str:
    return ", ".join(f"{c.topic} [{c.msgtype.split('/')[-1]}]" for c in sorted(conns, key=lambda c: c.topic))


def _pick_auto(path: Path, images: dict[str, Any]) -> dict[str, str]:
    """Image topics per kind by the realsense-ros layout (one camera namespace), else by name."""
    found: list[tuple[int, int, str, str]] = []  # (layout rank, transport rank, namespace, topic)
    for topic in images:
        for rank, pattern in enumerate(LAYOUT["depth"]):
            for trank, tr in enumerate(TRANSPORTS):
                tail = "/" + pattern + tr
                if topic.endswith(tail):
                    found.append((rank, trank, topic[: len(topic) - len(tail) + 1], topic))
    if not found:
        named = [t for t in images if "depth" in t.lower()]
        if len({transport_base(t) for t in named}) == 1:
            return {"depth": min(named, key=lambda t: (t != transport_base(t), t))}
        return {}
    spaces = sorted({ns for _, _, ns, _ in found})
    if len(spaces) > 1:
        raise InputError(path, f"depth images of several cameras ({', '.join(spaces)}): choose one with "
                               "--depth-topic (and --color-topic / --infrared-topic)")
    return {"depth": min(found)[3], **_siblings(spaces[0], images)}


def _siblings(ns: str, images: dict[str, Any]) -> dict[str, str]:
    """Colour and infrared image topics of the realsense-ros layout in the camera namespace `ns`."""
    out: dict[str, str] = {}
    for kind in ("color", "infrared"):
        for pattern in LAYOUT[kind]:
            hit = next((ns + pattern + tr for tr in TRANSPORTS if ns + pattern + tr in images), None)
            if hit is not None:
                out[kind] = hit
                break
    return out


def _choose_topics(path: Path, conns: list[Any], choice: TopicChoice | None) -> dict[str, str]:
    images = {c.topic: c for c in conns if c.msgtype in IMAGE_TYPES}
    if choice is None or choice.depth is None:
        picked = _pick_auto(path, images)
    else:  # the named depth; colour and infrared of the layout beside it unless named too
        picked = _siblings(camera_namespace(choice.depth), images)
    if choice is not None:
        for kind, topic in choice.to_dict().items():
            if topic is None:
                continue
            if topic not in images:
                seen = _topic_list(list(images.values())) or "none"
                raise InputError(path, f"no image topic {topic} (--{kind}-topic); image topics: {seen}")
            picked[kind] = topic
    if "depth" not in picked:
        raise InputError(path, "has no depth image topic (topics: "
                               f"{_topic_list(conns) or 'none'}); name it with --depth-topic")
    # one topic as two streams: the depth named as colour read every frame as colour and none as
    # depth (an empty import, exit 0), the colour named as infrared stored RGB as infrared
    given = {} if choice is None else {k: t for k, t in choice.to_dict().items() if t is not None}
    seen_as: dict[str, str] = {}
    for kind, topic in picked.items():
        if topic in seen_as:
            named = [f"--{k}-topic" for k in (seen_as[topic], kind) if k in given]
            raise InputError(path, f"{topic} would be read as both {seen_as[topic]} and {kind}"
                                   f"{' (' + ' and '.join(named) + ')' if named else ''}; each stream "
                                   "needs its own topic")
        seen_as[topic] = kind
    return picked


def _first(reader: Any, conns: list[Any]) -> Any | None:
    """The first message of these connections, deserialized (None when there is none)."""
    if not conns:  # rosbags reads every topic when given none
        return None
    for conn, _, raw in reader.messages(connections=conns):
        return reader.deserialize(raw, conn.msgtype)
    return None


def _tf_tree(reader: Any) -> dict[str, tuple[str, Extrinsics]]:
    """child frame -> (parent frame, pose of the child in the parent) from /tf_static (and /tf)."""
    tree: dict[str, tuple[str, Extrinsics]] = {}
    conns = [c for c in reader.connections if c.topic in TF_TOPICS and c.msgtype.endswith("TFMessage")]
    for topic in TF_TOPICS:  # static first; a dynamic /tf only fills frames the static one lacks
        these = [c for c in conns if c.topic == topic]
        if not these:  # (rosbags reads every topic when given none)
            continue
        for conn, _, raw in reader.messages(connections=these):
            for t in reader.deserialize(raw, conn.msgtype).transforms:
                child = str(t.child_frame_id).lstrip("/")
                if topic == "/tf" and child in tree:
                    continue
                parent = str(t.header.frame_id).lstrip("/")
                tree[child] = (parent, rosmsgs.extrinsics_from_transform(t.transform))
    return tree


def _to_root(tree: dict[str, tuple[str, Extrinsics]], frame: str) -> tuple[str, NDArray[np.float64]]:
    """(root frame, pose of `frame` in the root) by walking up the tree."""
    m = np.eye(4)
    seen = {frame}
    while frame in tree:
        parent, pose = tree[frame]
        m = pose.matrix @ m
        frame = parent
        if frame in seen:
            break  # a cycle: stop where it closes
        seen.add(frame)
    return frame, m


def tf_between(tree: dict[str, tuple[str, Extrinsics]], a: str, b: str) -> Extrinsics | None:
    """p_b = R p_a + t between two frames of one TF tree (None when they share no root)."""
    a, b = a.lstrip("/"), b.lstrip("/")
    if a == b:
        return Extrinsics()
    root_a, m_a = _to_root(tree, a)
    root_b, m_b = _to_root(tree, b)
    if root_a != root_b or (a not in tree and b not in tree):
        return None
    return Extrinsics.from_matrix(np.linalg.inv(m_b) @ m_a)


def _baseline(reader: Any, ns: str, tree: dict[str, tuple[str, Extrinsics]],
              depth_frame: str) -> float | None:
    """Stereo baseline (m): infra2 CameraInfo P[3] = -fx B, else the infra1 -> infra2 TF."""
    info = [c for c in reader.connections if c.topic == ns + "infra2/camera_info"]
    msg = _first(reader, info) if info else None
    if msg is not None:
        p = np.asarray(msg.p if hasattr(msg, "p") else msg.P, dtype=np.float64)
        if p[0] > 0 and p[3] != 0:
            return float(abs(p[3]) / p[0])
    # the camera's frame prefix ("camera_"): aligned depth is stamped in the colour frame
    prefix = next((depth_frame.split(k)[0] for k in ("depth", "color", "infra1", "aligned")
                   if k in depth_frame), "")
    lefts = (prefix + "infra1_optical_frame", prefix + "infra1_frame", depth_frame)
    left = next((f for f in lefts if f in tree), None)
    right = next((f for f in (prefix + "infra2_optical_frame", prefix + "infra2_frame") if f in tree), None)
    if left is None or right is None:
        return None
    e = tf_between(tree, left, right)
    return None if e is None else float(np.linalg.norm(e.t)) or None


def _fps(reader: Any, conns: list[Any], n: int = 8) -> float | None:
    """Frame rate from the header stamps of the first few frames (median period)."""
    stamps: list[int] = []
    for conn, bag_t, raw in reader.messages(connections=conns):
        stamps.append(rosmsgs.stamp_ns(reader.deserialize(raw, conn.msgtype).header) or bag_t)
        if len(stamps) >= n:
            break
    periods = np.diff(np.asarray(stamps, dtype=np.float64))
    periods = periods[periods > 0]
    return round(1e9 / float(np.median(periods)), 3) if periods.size else None


# colour / infrared messages kept while the depth frames before `start` are skipped (their stamps are
# not read): the start frame's partners lie among the last few. Before, every one was kept until the
# start frame came: the last of 300 640x480 frames of a sqlite3 rosbag2 peaked at 866 MB against
# 655 MB now, in 0.92 against 0.17 s (benchmarks/bench_ros_seek.py; MCAP keeps views of the file)
PRE_START_KEEP = 64


class RosRecording(Recording):
    """A ROS bag's depth frames, colour and infrared matched by header stamp (picklable: workers
    reopen it from its path and topic choice)."""

    def __init__(self, *args: Any, streams: dict[str, RosStream], tolerance_ns: int,
                 frame_topic: str | None, temperature_topic: str | None, mcap_files: list[Path],
                 db3_files: list[Path] | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.mcap_files = mcap_files
        self.db3_files = db3_files or []
        self.streams = streams
        self.tolerance_ns = int(tolerance_ns)
        self.frame_topic = frame_topic
        self.temperature_topic = temperature_topic
        self.cut_files: list[Path] = []   # MCAP files cut short: read up to their last complete chunk
        self.truncated = False
        self.recovered_frames: int | None = None

    def _iter(self, start: int) -> Iterator[FrameSet]:
        kinds = {s.topic: k for k, s in self.streams.items()}
        others = [k for k in ("color", "infrared") if k in self.streams]
        tol = self.tolerance_ns
        pending: deque[tuple[int, int, Any, str]] = deque()  # depth: (order, stamp, msg, msgtype)
        buffers: dict[str, deque[tuple[int, Any, str]]] = {k: deque() for k in others}
        last: dict[str, float] = {k: -np.inf for k in others}
        records: dict[int, dict[str, Any]] = {}
        n_depth = 0
        prev_stamp = -1

        def ready(done: bool) -> Iterator[FrameSet]:
            while pending and (done or all(last[k] > pending[0][1] + tol for k in others)):
                order, stamp, msg, msgtype = pending.popleft()
                parts: dict[str, tuple[Any, str]] = {}
                stamps: dict[str, int] = {}
                for k in others:
                    buf = buffers[k]
                    while buf and buf[0][0] < stamp - tol:
                        buf.popleft()  # too old for this and every later depth frame
                    best = min(buf, key=lambda e: abs(e[0] - stamp), default=None)
                    if best is not None and abs(best[0] - stamp) <= tol:
                        parts[k] = (best[1], best[2])
                        if best[0] != stamp:
                            stamps[k] = best[0]
                yield self._frameset(order, stamp, (msg, msgtype), parts, stamps, records.pop(stamp, None))

        wanted = set(kinds) | {t for t in (self.frame_topic,) if t}
        for topic, msgtype, bag_t, raw, deserialize in self._messages(wanted):
            if topic == self.frame_topic:
                rec = json.loads(deserialize(raw, msgtype).data)
                records[int(rec["timestamp_ns"])] = rec
                continue
            kind = kinds[topic]
            if kind == "depth":
                order = n_depth
                n_depth += 1
                if order < start:
                    continue
                msg = deserialize(raw, msgtype)
                stamp = rosmsgs.stamp_ns(msg.header) or bag_t
                if stamp <= prev_stamp and others:  # pairing by stamp cannot tell these frames apart
                    warn(f"depth header stamps of {topic} repeat or go back: colour and infrared are paired "
                         "by stamp, so such frames may carry another frame's images", str(self.path),
                         "ros-stamps")
                prev_stamp = max(prev_stamp, stamp)
                pending.append((order, stamp, msg, msgtype))
            else:
                msg = deserialize(raw, msgtype)
                stamp = rosmsgs.stamp_ns(msg.header) or bag_t
                buf = buffers[kind]
                buf.append((stamp, msg, msgtype))
                last[kind] = max(last[kind], stamp)
                if n_depth < start and len(buf) > PRE_START_KEEP:  # no depth frame to trim by yet
                    buf.popleft()
            yield from ready(False)
        yield from ready(True)

    def _messages(self, topics: set[str]) -> Iterator[tuple[str, str, int, Any, Any]]:
        """(topic, message type, log time, raw data, deserializer) of these topics in file order.

        rosbag2 MCAP files are parsed by the chunk reader of our own MCAP (memoryviews, no copy of
        the images: 3-4x what rosbags' reader gives at 1280x720); rosbag2 sqlite3 files are queried
        directly with sqlite's memory map (the images leave sqlite once, as bytes; 2x rosbags'
        reader); ROS 1 bags by rosbags.
        """
        types = {s.topic: s.msgtype for s in self.streams.values()}
        types.update({t: rosmsgs.STRING for t in (self.frame_topic,) if t})
        if self.mcap_files:
            for path in self.mcap_files:
                names: dict[int, str] = {}
                with path.open("rb") as fh:
                    found = mcap_messages(fh, names)
                    while True:
                        try:
                            cid, log_time, data = next(found)
                        except StopIteration:
                            break
                        except Exception:
                            if path in self.cut_files:  # the chunk the cut fell in (said at the opening)
                                break
                            raise
                        topic = names.get(cid)
                        if topic in topics:
                            yield topic, types[topic], log_time, data, rosmsgs.deserialize
            return
        if self.db3_files:
            for path in self.db3_files:
                for topic, log_time, data in _db3_messages(path, topics):
                    yield topic, types[topic], log_time, data, rosmsgs.deserialize
            return
        with _reader(self.path, typestore()) as reader:
            conns = [c for c in reader.connections if c.topic in topics]
            for conn, bag_t, raw in reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, bag_t, raw, reader.deserialize

    def _frameset(self, order: int, stamp: int, depth: tuple[Any, str], parts: dict[str, tuple[Any, str]],
                  stamps: dict[str, int], record: dict[str, Any] | None) -> FrameSet:
        pixels = self._pixels("depth", *depth, order=order)
        if pixels.ndim != 2:  # refused before any conversion: a colour image read as depth said nothing true
            enc = getattr(depth[0], "encoding", None) or getattr(depth[0], "format", "?")
            raise InputError(self.path, f"depth topic {self.streams['depth'].topic}, message {order}: "
                                        f"{enc!s} holds no single-channel depth image (shape "
                                        f"{pixels.shape}); give the depth topic with --depth-topic")
        d = self._depth(pixels)
        self._check_size("depth", d, self.info.depth_intrinsics)
        color = infrared = None
        if "color" in parts:
            color = self._pixels("color", *parts["color"], order=order)
            self._check_size("color", color, self.info.color_intrinsics)
            if color.ndim == 2:
                color = np.repeat((color >> 8 if color.dtype == np.uint16 else color)[..., None], 3, axis=2)
            color = color.astype(np.uint8, copy=False)
        if "infrared" in parts:
            ir = self._pixels("infrared", *parts["infrared"], order=order)
            self._check_size("infrared", ir, self.info.infrared_intrinsics)
            ir = ir[..., 0] if ir.ndim == 3 else ir
            infrared = (ir >> 8 if ir.dtype == np.uint16 else ir).astype(np.uint8, copy=False)
        if record is not None:  # our MCAP rewritten by a ROS tool: its frame records survive
            meta = dict(record.get("metadata") or {})
            return FrameSet(int(record["index"]), stamp, d, color, infrared, meta)
        return FrameSet(order, stamp, d, color, infrared, {mw.STREAM_STAMPS_KEY: stamps} if stamps else {})

    def _depth(self, image: NDArray[Any]) -> NDArray[np.uint16]:
        """z16 counts of a depth image; float depth beyond the counts' range is said, not lost
        without a word (0.1 mm counts end at 6.55 m)."""
        units = self.info.depth_units_m
        if image.dtype != np.uint16:
            with np.errstate(invalid="ignore"):
                beyond = int(np.count_nonzero(np.asarray(image, dtype=np.float64) >= 65535.5 * units))
            if beyond:
                warn(f"depth {self.streams['depth'].topic}: float depth beyond {65535 * units:.2f} m, the "
                     f"16-bit range at {units * 1000:g} mm counts, is read as no depth", str(self.path),
                     code="ros-reading")
        return rosmsgs.depth_to_units(image, units)

    def _pixels(self, kind: str, msg: Any, msgtype: str, order: int | None = None) -> NDArray[Any]:
        """An image's pixels; an encoding we cannot read or data shorter than the image is bad input
        naming the bag, the topic and the message (depth frame `order`; its partner for the others)."""
        try:
            return _pixels(msg, msgtype)
        except ValueError as exc:
            where = "" if order is None else (f", message {order}" if kind == "depth"
                                              else f", the image paired with depth message {order}")
            raise InputError(self.path, f"{kind} topic {self.streams[kind].topic}{where}: {exc}") from exc

    def _check_size(self, kind: str, image: NDArray[Any], intr: Intrinsics | None) -> None:
        """An image of another size than its CameraInfo: every pixel on the wrong ray (PNG sets
        and TUM folders refuse the same)."""
        problem = size_problem(image, intr, "its camera_info says")
        if problem:
            raise InputError(self.path, f"{kind} topic {self.streams[kind].topic}: an image {problem}")

    def temperatures(self) -> dict[str, tuple[list[int], list[float]]]:
        out: dict[str, tuple[list[int], list[float]]] = {}
        if self.temperature_topic is None:
            return out
        with _reader(self.path, typestore()) as reader:
            conns = [c for c in reader.connections if c.topic == self.temperature_topic]
            for conn, _, raw in reader.messages(connections=conns):
                m = reader.deserialize(raw, conn.msgtype)
                ts, vs = out.setdefault(str(m.header.frame_id), ([], []))
                ts.append(rosmsgs.stamp_ns(m.header))
                vs.append(float(m.temperature))
        return out


def _pixels(msg: Any, msgtype: str) -> NDArray[Any]:
    if msgtype == rosmsgs.COMPRESSED_IMAGE:
        return rosmsgs.compressed_image_array(msg)
    return rosmsgs.image_array(msg)


def _mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a rosbag2 recording in order (split files `x_0.mcap`, `x_1.mcap`, ...);
    empty for another storage."""
    if path.is_file():
        with path.open("rb") as fh:
            return [path] if fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC else []
    files = [p for p in path.iterdir() if p.suffix.lower() == ".mcap"]
    if not files or any(p.suffix.lower() == ".db3" for p in path.iterdir()):
        return []
    return sorted(files, key=_split_order)


def _split_order(p: Path) -> tuple[int, str]:
    """rosbag2's order of split files: `x_0`, `x_1`, ..., `x_10` by the number after the last '_'."""
    tail = p.stem.rsplit("_", 1)[-1]
    return (int(tail) if tail.isdigit() else -1, p.name)


def _db3_files(path: Path) -> list[Path]:
    """The sqlite3 files of a rosbag2 recording in order (`x_0.db3`, `x_1.db3`, ...); empty for
    another storage."""
    if path.is_file():
        return [path] if path.suffix.lower() == ".db3" else []
    return sorted((p for p in path.iterdir() if p.suffix.lower() == ".db3"), key=_split_order)


def _db3_messages(path: Path, topics: set[str]) -> Iterator[tuple[str, int, memoryview]]:
    """(topic, log time, CDR data) of these topics from one rosbag2 sqlite3 file, in time order
    (rosbag2's own order: timestamp, then insertion)."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        con.execute(f"PRAGMA mmap_size={1 << 40}")  # sqlite reads pages from the map, not read()
        names = {int(i): str(n) for i, n in con.execute("SELECT id, name FROM topics") if n in topics}
        if not names:
            return
        marks = ",".join("?" * len(names))
        rows = con.execute(f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) "
                           "ORDER BY timestamp, id", list(names))
        for tid, t, data in rows:
            yield names[int(tid)], int(t), memoryview(data)  # a view: rosbags copies bytes
    finally:
        con.close()


def _cut_short(path: Path) -> bool:
    """An MCAP without its closing magic: its writer stopped (a kill, a full disk, a copy cut)."""
    with path.open("rb") as fh:
        fh.seek(0, 2)
        if fh.tell() < 2 * len(MCAP_MAGIC):
            return True
        fh.seek(-len(MCAP_MAGIC), 2)
        return fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC


METADATA_FILE = "metadata.yaml"


def listed_messages(path: Path, topic: str) -> int | None:
    """How many messages of `topic` a rosbag2 folder's metadata.yaml lists; None for a single file,
    a folder without it, or one that does not say. Why: a cut bag's warning says how much of the
    recording it recovered ("N of M"), where the recording said how much it held."""
    meta = path / METADATA_FILE
    if not meta.is_file():
        return None
    try:
        doc = YAML(typ="safe", pure=True).load(meta.read_text())
        topics = doc["rosbag2_bagfile_information"]["topics_with_message_count"]
        counts = [int(t["message_count"]) for t in topics if t["topic_metadata"]["name"] == topic]
    except (OSError, YAMLError, KeyError, TypeError, ValueError):
        return None
    return sum(counts) if counts else None


def cut_mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a rosbag2 recording (file or folder) that are cut short."""
    try:
        return [f for f in _mcap_files(path) if _cut_short(f)]
    except OSError:
        return []


@dataclass
class _CutConnection:
    id: int
    topic: str
    msgtype: str
    msgcount: int = 0


class CutMcapReader:
    """The part of rosbags' AnyReader that `_open` uses, over rosbag2 MCAP files cut short.

    Why: rosbags refuses an MCAP without its summary ('File end magic is invalid'), and a cut file
    read as ours was called 'cut short before its first complete chunk' whatever it held. The
    complete chunks are read in order, as our own MCAP reader reads a cut capture; the chunk the
    cut fell in is lost."""

    is2 = True

    def __init__(self, path: Path, files: list[Path]) -> None:
        self.path = path
        self.files = files
        self._ts = typestore()
        self.connections: list[_CutConnection] = []
        self._by_key: dict[tuple[int, int], _CutConnection] = {}  # (file, channel id)
        for k, f in enumerate(files):
            schemas: dict[int, str] = {}
            for r in self._records(f):
                if isinstance(r, Schema):
                    schemas[r.id] = r.name
                elif isinstance(r, Channel) and (k, r.id) not in self._by_key:
                    known = next((c for c in self.connections if c.topic == r.topic), None)
                    conn = known or _CutConnection(len(self.connections), r.topic,
                                                   schemas.get(r.schema_id, ""))
                    if known is None:
                        self.connections.append(conn)
                    self._by_key[(k, r.id)] = conn
                elif isinstance(r, Message) and (k, r.channel_id) in self._by_key:
                    self._by_key[(k, r.channel_id)].msgcount += 1
        if not any(c.msgcount for c in self.connections):
            raise InputError(path, "is cut short before its first complete chunk: no frame can be recovered")

    @staticmethod
    def _records(path: Path) -> Iterator[Any]:
        """The file's records, messages unpacked from its complete chunks, up to the cut."""
        with path.open("rb") as fh:
            records = iter(StreamReader(fh, emit_chunks=False, record_size_limit=None).records)
            while True:
                try:
                    r = next(records)
                except StopIteration:
                    return
                except Exception:  # the cut: a record (a chunk) that ends past the file's end
                    return
                yield r

    def __enter__(self) -> CutMcapReader:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def messages(self, connections: list[Any]) -> Iterator[tuple[Any, int, bytes]]:
        wanted = {id(c) for c in connections}
        for k, f in enumerate(self.files):
            for r in self._records(f):
                if isinstance(r, Message):
                    conn = self._by_key.get((k, r.channel_id))
                    if conn is not None and id(conn) in wanted:
                        yield conn, r.log_time, r.data

    def deserialize(self, raw: Any, msgtype: str) -> Any:
        return self._ts.deserialize_cdr(raw, msgtype)


def open_ros(path: Path, topics: TopicChoice | None = None) -> RosRecording:
    """Find the streams, read CameraInfo, extrinsics, baseline; count the depth frames. A rosbag2
    MCAP cut short is read from its complete chunks, with a warning saying how much was recovered."""
    path = Path(path)
    ts = typestore()
    try:
        files = _mcap_files(path)
        cut = cut_mcap_files(path)
        if cut:
            with CutMcapReader(path, files) as cut_reader:
                rec = _open(path, cut_reader, topics)
            rec.cut_files = cut
            rec.truncated = True
            rec.recovered_frames = rec.frame_count
            total = sum(f.stat().st_size for f in files)
            listed = listed_messages(path, rec.streams["depth"].topic)
            of = (f" ({rec.frame_count} of the {listed} its {METADATA_FILE} lists)"
                  if listed is not None and listed >= (rec.frame_count or 0) else "")
            warn(f"rosbag2 MCAP cut short ({', '.join(f.name for f in cut)} has no summary): recovered "
                 f"{rec.frame_count} depth frames{of} from its complete chunks ({total / 1e6:.1f} MB of "
                 "file); what followed the last complete chunk is lost", str(path), "truncated-input")
            return rec
        with _reader(path, ts) as reader:
            return _open(path, reader, topics)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, f"is no readable ROS bag ({type(exc).__name__}: {exc})") from exc


def _open(path: Path, reader: Any, choice: TopicChoice | None) -> RosRecording:
    conns = list(reader.connections)
    picked = _choose_topics(path, conns, choice)
    by_topic: dict[str, list[Any]] = {}
    for c in conns:
        by_topic.setdefault(c.topic, []).append(c)
    streams: dict[str, RosStream] = {}
    for kind, topic in picked.items():
        cs = by_topic[topic]
        count = sum(c.msgcount for c in cs)
        streams[kind] = RosStream(kind, topic, cs[0].msgtype, count, camera_info_topic(topic))
    if streams["depth"].count == 0:
        raise InputError(path, f"depth topic {streams['depth'].topic} holds no message")
    rect_notes: list[str] = []
    for kind, s in list(streams.items()):
        info_conns = [c for c in by_topic.get(s.info_topic, []) if c.msgtype.endswith("CameraInfo")]
        msg = _first(reader, info_conns) if info_conns else None
        if msg is None:
            if kind == "infrared":
                log.warning("%s: no %s for the infrared images; infrared left out", path, s.info_topic)
                del streams[kind]
                continue
            raise InputError(path, f"no CameraInfo {s.info_topic} for the {kind} images {s.topic}")
        rectified = rosmsgs.is_rectified_topic(transport_base(s.topic))   # .../image_rect/compressed too
        s.intrinsics = rosmsgs.intrinsics_from_camera_info(msg, rectified=rectified)
        raw = rosmsgs.intrinsics_from_camera_info(msg) if rectified else None
        if raw is not None and (raw.has_distortion or raw.K.tolist() != s.intrinsics.K.tolist()):
            rect_notes.append(f"{kind} {s.topic} is rectified: its camera is {s.info_topic}'s P, "
                              f"without the distortion ({msg.distortion_model}) of the raw images")
        s.frame_id = str(msg.header.frame_id).lstrip("/")
        if not s.frame_id:
            first = _first(reader, by_topic[s.topic])
            s.frame_id = str(first.header.frame_id).lstrip("/") if first is not None else ""
        s.extra = {"distortion_model": str(msg.distortion_model)}
    depth = streams["depth"]
    color = streams.get("color")
    infra = streams.get("infrared")
    ns = camera_namespace(depth.topic)
    aligned = "aligned_depth_to" in depth.topic or (color is not None and depth.frame_id == color.frame_id
                                                     and bool(depth.frame_id))
    tree = _tf_tree(reader)
    notes: list[str] = list(rect_notes)
    d2c = Extrinsics()
    source = "none"
    if color is not None and not aligned:
        ext_conns = [c for c in by_topic.get(ns + "extrinsics/depth_to_color", [])
                     if c.msgtype.endswith("/Extrinsics")]
        ext = _first(reader, ext_conns) if ext_conns else None
        if ext is not None:
            d2c = Extrinsics.from_librealsense(list(ext.rotation), list(ext.translation))
            source = ext_conns[0].topic
        else:
            e = tf_between(tree, depth.frame_id, color.frame_id)
            if e is None:
                notes.append(f"no /tf_static chain from {depth.frame_id or '?'} to {color.frame_id or '?'}: "
                             "depth and colour taken as one frame")
            else:
                d2c, source = e, "/tf_static"
    units = DEPTH_UNITS_M
    first_depth = _first(reader, by_topic[depth.topic])
    if first_depth is not None:
        with contextlib.suppress(ValueError):  # an unreadable encoding is refused with the frames
            units = depth_units_for(_pixels(first_depth, depth.msgtype))
    for note in notes:  # what the reading assumed: on stderr, in result.json, --strict
        warn(note, str(path), code="ros-reading")
    stereo = None
    if aligned:
        own = [c for c in by_topic.get(ns + "depth/camera_info", []) if c.msgtype.endswith("CameraInfo")]
        msg = _first(reader, own) if own else None
        stereo = None if msg is None else rosmsgs.intrinsics_from_camera_info(msg)
    baseline = _baseline(reader, ns, tree, depth.frame_id)
    fps = _fps(reader, by_topic[depth.topic])
    assert depth.intrinsics is not None
    info = StreamInfo(
        depth_intrinsics=depth.intrinsics,
        color_intrinsics=None if color is None else color.intrinsics,
        depth_to_color=d2c,
        depth_units_m=units,
        depth_aligned_to_color=aligned,
        infrared_intrinsics=None if infra is None else infra.intrinsics,
        baseline_m=baseline,
        fps=fps,
        stereo_intrinsics=stereo,
    )
    period_ns = 1e9 / fps if fps else 1e9 / 30.0
    topic_names = {t for t in by_topic}
    meta: dict[str, Any] = {
        "source": {
            "kind": "ros", "path": str(path), "ros_version": 2 if reader.is2 else 1,
            "topics": {k: s.topic for k, s in streams.items()},
            "camera_info": {k: s.info_topic for k, s in streams.items()},
            "frames": {k: s.frame_id for k, s in streams.items()},
            "distortion_models": {k: s.extra.get("distortion_model") for k, s in streams.items()},
            "extrinsics": source, "notes": notes,
        },
    }
    counts = {k: s.count for k, s in streams.items()}
    name = path.name.split(".")[0] if path.is_file() else path.name
    rec = RosRecording(
        name, path, info, meta, depth.count, counts, streams=streams, tolerance_ns=int(period_ns / 2),
        frame_topic=mw.FRAME_TOPIC if mw.FRAME_TOPIC in topic_names else None,
        temperature_topic=mw.TEMPERATURE_TOPIC if mw.TEMPERATURE_TOPIC in topic_names else None,
        mcap_files=_mcap_files(path) if reader.is2 else [],
        db3_files=_db3_files(path) if reader.is2 else [],
    )
    rec.topics = choice
    return rec
