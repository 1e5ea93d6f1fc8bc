"""Our MCAP layout: ROS 2 cdr images, CameraInfo, /tf_static, temperatures and JSON metadata records.

`McapFileWriter` writes synchronously (the session's background thread drives it);
`write_mcap` is the one-shot form used by importers and the simulator.

The ROS side plays right in the ecosystem (`ros2 bag play`, Foxglove, rerun): the static messages
are stamped at the first frame (no message at time 0, so the file's time range is the frames'
span), every image has its CameraInfo with the same stamp (as the ROS 2 wrapper publishes), each
stream keeps its own stamp, and `/tf_static` is the wrapper's tree under `camera_link`, offered
transient-local (so a late tf2 listener still gets it on playback).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture import rosmsgs, yuv
from depthstation.core.capture.mcap_chunks import ChunkedMcapWriter
from depthstation.core.errors import CaptureError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.results import _jsonable

FORMAT_NAME = "depthstation-capture"
FORMAT_VERSION = 1

# Topics and frame ids of the format (documented in docs/capture-format.md).
DEPTH_TOPIC = "/camera/depth/image_rect_raw"
DEPTH_INFO_TOPIC = "/camera/depth/camera_info"
COLOR_TOPIC = "/camera/color/image_raw"
COLOR_INFO_TOPIC = "/camera/color/camera_info"
INFRARED_TOPIC = "/camera/infra1/image_rect_raw"
INFRARED_INFO_TOPIC = "/camera/infra1/camera_info"
TF_STATIC_TOPIC = "/tf_static"
FRAME_TOPIC = "/depthstation/frame"
TEMPERATURE_TOPIC = "/device/temperature"
DEPTH_FRAME_ID = "camera_depth_optical_frame"
COLOR_FRAME_ID = "camera_color_optical_frame"
INFRARED_FRAME_ID = "camera_infra1_optical_frame"

COMPRESSIONS = ("none", "lz4", "zstd")
# colour as RGB8 (what librealsense hands the host) or as the D4xx sends it over USB, YUYV 4:2:2
# (core/capture/yuv.py): 2 bytes a pixel instead of 3, and the simulator's choice for sequences
COLOR_ENCODINGS = ("rgb8", yuv.ENCODING)
SIMULATION_COLOR_ENCODING = yuv.ENCODING
# rosbag2's offered_qos_profiles of a latched topic (tf2_ros::StaticBroadcasterQoS: keep last 1,
# reliable, transient local), in the integer form every rosbag2 release decodes (Humble included)
TF_STATIC_QOS = (
    "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
    "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
    "  avoid_ros_namespace_conventions: false"
)
STREAM_STAMPS_KEY = "stream_timestamps_ns"  # FrameSet.metadata: {"color": ns, "infrared": ns} when apart
# Chunk compression by default (docs/capture-format.md, "Compression", has the measurements):
# live capture and imports use lz4, which keeps 30 fps of 1280x720 depth + colour on two busy
# cores with no drop and reads back at > 300 frame sets/s; simulated sequences are written
# offline, where zstd makes them ~1.6x smaller than lz4 (~2x smaller than raw).
CAPTURE_COMPRESSION = "lz4"
SIMULATION_COMPRESSION = "zstd"
# zstd's fastest level: 3x less CPU than its default (3) for 5-10 % larger chunks. Why it matters:
# the simulator writes while it renders on the same two cores, and level 3 made the writer the
# bottleneck of `simulate scan` (21 ms of CPU per 640x480 depth + colour frame set against 6.5 ms)
ZSTD_LEVEL = 1


def _json(value: Any) -> str:

    return json.dumps(_jsonable(value), sort_keys=True)


class McapFileWriter:
    """Writes one standpoint/sequence; the file is opened exclusively so nothing is overwritten."""

    def __init__(
        self,
        path: Path,
        info: StreamInfo,
        metadata: dict[str, Any] | None = None,
        *,
        compression: str = "none",
        chunk_size: int = 4 * 1024 * 1024,
        color_encoding: str = "rgb8",
    ) -> None:

        if compression not in COMPRESSIONS:
            raise InputError(
                None, f"unknown compression {compression!r}; use one of {', '.join(COMPRESSIONS)}"
            )
        if color_encoding not in COLOR_ENCODINGS:
            raise InputError(None, f"unknown colour encoding {color_encoding!r}; use one of "
                                   f"{', '.join(COLOR_ENCODINGS)}")
        self.path = Path(path)
        self.info = info
        self.color_encoding = color_encoding
        try:
            self._file: IO[bytes] = self.path.open("xb")
        except FileExistsError as exc:
            raise InputError(self.path, "exists already; captures are never overwritten") from exc
        except OSError as exc:
            raise CaptureError(f"{self.path}: cannot create: {exc.strerror}") from exc
        self._writer = ChunkedMcapWriter(
            self._file, profile="ros2", library=f"depthstation {FORMAT_NAME} v{FORMAT_VERSION}",
            compression="" if compression == "none" else compression, chunk_size=chunk_size,
            zstd_level=ZSTD_LEVEL,
        )
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.frames_written = 0
        self.first_index: int | None = None
        self.last_index: int | None = None
        self._closed = False
        self._statics_written = False
        self._depth_frame = COLOR_FRAME_ID if info.depth_aligned_to_color else DEPTH_FRAME_ID
        self._info_msgs: dict[str, tuple[str, Any]] = {}  # image topic -> (info topic, intrinsics)
        self._write_header(metadata or {})

    # -- setup ---------------------------------------------------------------------------------
    def _channel(self, topic: str, msgtype: str, metadata: dict[str, str] | None = None) -> int:
        if topic not in self._channels:
            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    msgtype, "ros2msg", rosmsgs.msgdef(msgtype).encode()
                )
            self._channels[topic] = self._writer.register_channel(
                topic, "cdr", self._schemas[msgtype], metadata or {}
            )
        return self._channels[topic]

    def _write_header(self, metadata: dict[str, Any]) -> None:
        info = self.info
        self.add_metadata("format", {"name": FORMAT_NAME, "version": FORMAT_VERSION,
                                     "color_encoding": self.color_encoding})
        self.add_metadata("streams", info.to_dict())
        device = dict(info.device)
        device.update(metadata.get("device") or {})
        device.setdefault("depth_units_m", info.depth_units_m)
        device.setdefault("baseline_m", info.baseline_m)
        self.add_metadata("device", device)
        for key, value in metadata.items():
            if key != "device":
                self.add_metadata(key, value)
        # Channels up front: a reader then knows which streams to expect. The static messages
        # follow with the first frame (its stamp); the geometry is in the 'streams' record anyway.
        di = info.depth_intrinsics  # equals the colour intrinsics when depth is aligned to colour
        self._info_msgs[DEPTH_TOPIC] = (DEPTH_INFO_TOPIC, di)
        color = info.color_intrinsics or (di if info.depth_aligned_to_color else None)
        if color is not None:
            self._info_msgs[COLOR_TOPIC] = (COLOR_INFO_TOPIC, color)
        if info.infrared_intrinsics is not None:
            self._info_msgs[INFRARED_TOPIC] = (INFRARED_INFO_TOPIC, info.infrared_intrinsics)
        self._channel(TF_STATIC_TOPIC, rosmsgs.TF_MESSAGE, {"offered_qos_profiles": TF_STATIC_QOS})
        self._channel(FRAME_TOPIC, rosmsgs.STRING)
        for topic, (info_topic, _) in self._info_msgs.items():
            self._channel(topic, rosmsgs.IMAGE)
            self._channel(info_topic, rosmsgs.CAMERA_INFO)

    def _write_statics(self, t_ns: int) -> None:
        """/tf_static (the wrapper's tree under camera_link) stamped at the first frame."""
        self._statics_written = True
        info = self.info
        d2c = info.depth_to_color if info.color_intrinsics is not None else None
        tree = rosmsgs.realsense_tf_tree(d2c, info.baseline_m)
        self._writer.add_message(self._channels[TF_STATIC_TOPIC], t_ns,
                                 (rosmsgs.tf_message(tree, t_ns),), t_ns, 0)

    def _image(self, topic: str, array: Any, encoding: str, t_ns: int, frame_id: str, seq: int) -> None:
        """An image and its CameraInfo, both stamped `t_ns` (as realsense-ros publishes them)."""
        w = self._writer
        image = rosmsgs.image_msg_parts(array, encoding, t_ns, frame_id)
        w.add_message(self._channel(topic, rosmsgs.IMAGE), t_ns, image, t_ns, seq)
        if topic in self._info_msgs:
            info_topic, intr = self._info_msgs[topic]
            cam = rosmsgs.camera_info_msg(intr, t_ns, frame_id)
            w.add_message(self._channels[info_topic], t_ns, (cam,), t_ns, seq)

    # -- writing -------------------------------------------------------------------------------
    def add_metadata(self, name: str, value: Any) -> None:
        """A metadata record holding one JSON document; a later record of the same name wins."""
        self._writer.add_metadata(name, {"json": _json(value)})

    def write(self, fs: FrameSet) -> None:
        """One frame set: a frame record, then depth, colour, infrared (each with its CameraInfo and
        its own stamp, `metadata['stream_timestamps_ns']` where the streams were apart), sequence =
        frame index."""
        if fs.depth is None:
            raise CaptureError(f"{self.path}: frame {fs.index} has no depth")
        t, seq = int(fs.timestamp_ns), int(fs.index) & 0xFFFFFFFF
        if not self._statics_written:
            self._write_statics(t)
        streams = ["depth"] + [
            k for k, a in (("color", fs.color), ("infrared", fs.infrared)) if a is not None
        ]
        record = {"index": int(fs.index), "timestamp_ns": t, "streams": streams, "metadata": fs.metadata}
        self._writer.add_message(self._channels[FRAME_TOPIC], t, (rosmsgs.string_msg(_json(record)),), t, seq)
        stamps = (fs.metadata or {}).get(STREAM_STAMPS_KEY) or {}
        self._image(DEPTH_TOPIC, fs.depth, "16UC1", t, self._depth_frame, seq)
        color = fs.color
        if color is not None and self.color_encoding == yuv.ENCODING:
            color = yuv.rgb_to_yuy2(color)
        for topic, kind, array, encoding, frame_id in (
            (COLOR_TOPIC, "color", color, self.color_encoding, COLOR_FRAME_ID),
            (INFRARED_TOPIC, "infrared", fs.infrared, "mono8", INFRARED_FRAME_ID),
        ):
            if array is None:
                continue
            self._image(topic, array, encoding, int(stamps.get(kind, t)), frame_id, seq)
        self.frames_written += 1
        if self.first_index is None:
            self.first_index = int(fs.index)
        self.last_index = int(fs.index)

    def write_temperature(self, t_ns: int, temperatures: dict[str, float]) -> None:
        """One sensor_msgs/Temperature per sensor, header.frame_id = sensor name ('asic', 'projector')."""
        ch = self._channel(TEMPERATURE_TOPIC, rosmsgs.TEMPERATURE)
        for name, value in temperatures.items():
            self._writer.add_message(
                ch, int(t_ns), (rosmsgs.temperature_msg(int(t_ns), name, float(value)),), int(t_ns), 0
            )

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        """Finish the summary section; fsync so a rename after it never exposes a half file."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def abort(self) -> None:
        """Close without a summary (what a crash leaves behind), keeping what was written."""
        if not self._closed:
            self._closed = True
            self._file.close()

    def __enter__(self) -> McapFileWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_mcap(
    path: Path,
    info: StreamInfo,
    frames: Iterable[FrameSet],
    metadata: dict[str, Any] | None = None,
    *,
    compression: str = "none",
    temperatures: Iterable[tuple[int, dict[str, float]]] = (),
    color_encoding: str = "rgb8",
) -> int:
    """Write a whole recording at once (never overwrites); returns the number of frame sets written."""
    with McapFileWriter(Path(path), info, metadata, compression=compression,
                        color_encoding=color_encoding) as w:
        for t_ns, temps in temperatures:
            w.write_temperature(t_ns, temps)
        for fs in frames:
            w.write(fs)
        return w.frames_written
