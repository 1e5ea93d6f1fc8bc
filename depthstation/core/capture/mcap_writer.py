"""Our MCAP layout: ROS 2 cdr images, CameraInfo, /tf_static, temperatures and JSON metadata records.

`McapFileWriter` writes synchronously (the session's background thread drives it);
`write_mcap` is the one-shot form used by importers and the simulator.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import mcap.writer as _mcap_writer
import zstandard
from mcap.writer import CompressionType, Writer

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture import rosmsgs
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
# Chunk compression by default (docs/capture-format.md, "Compression", has the measurements):
# live capture and imports use lz4, which keeps 30 fps of 1280x720 depth + colour on two busy
# cores with no drop and reads back at > 300 frame sets/s; simulated sequences are written
# offline, where zstd (level 3) makes them ~1.6x smaller than lz4 (~2x smaller than raw).
CAPTURE_COMPRESSION = "lz4"
SIMULATION_COMPRESSION = "zstd"
ZSTD_LEVEL = 1  # zstd's fastest level: 3x less CPU than its default (3) for 5-10 % larger chunks


class _Zstd:
    """What mcap's writer calls for zstd chunks (`zstandard.compress(data)`, level 3), at ZSTD_LEVEL.

    Why: the simulator writes while it renders on the same two cores, and level 3 made the writer
    the bottleneck of `simulate scan` (21 ms of CPU per 640x480 depth + colour frame set against
    6.5 ms at level 1, for chunks 11 % smaller). The mcap package has no level option.
    """

    def __init__(self, level: int) -> None:
        self.level = level

    def compress(self, data: bytes) -> bytes:
        return bytes(zstandard.ZstdCompressor(level=self.level).compress(data))


_mcap_writer.zstandard = _Zstd(ZSTD_LEVEL)  # type: ignore[attr-defined,assignment]


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
    ) -> None:

        if compression not in COMPRESSIONS:
            raise InputError(
                None, f"unknown compression {compression!r}; use one of {', '.join(COMPRESSIONS)}"
            )
        self.path = Path(path)
        self.info = info
        try:
            self._file: IO[bytes] = self.path.open("xb")
        except FileExistsError as exc:
            raise InputError(self.path, "exists already; captures are never overwritten") from exc
        except OSError as exc:
            raise CaptureError(f"{self.path}: cannot create: {exc.strerror}") from exc
        self._writer = Writer(
            self._file, chunk_size=chunk_size, compression=CompressionType[compression.upper()]
        )
        self._writer.start(profile="ros2", library=f"depthstation {FORMAT_NAME} v{FORMAT_VERSION}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.frames_written = 0
        self.first_index: int | None = None
        self.last_index: int | None = None
        self._closed = False
        self._write_header(metadata or {})

    # -- setup ---------------------------------------------------------------------------------
    def _channel(self, topic: str, msgtype: str) -> int:
        if topic not in self._channels:
            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    msgtype, "ros2msg", rosmsgs.msgdef(msgtype).encode()
                )
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schemas[msgtype])
        return self._channels[topic]

    def _write_header(self, metadata: dict[str, Any]) -> None:
        info = self.info
        self.add_metadata("format", {"name": FORMAT_NAME, "version": FORMAT_VERSION})
        self.add_metadata("streams", info.to_dict())
        device = dict(info.device)
        device.update(metadata.get("device") or {})
        device.setdefault("depth_units_m", info.depth_units_m)
        device.setdefault("baseline_m", info.baseline_m)
        self.add_metadata("device", device)
        for key, value in metadata.items():
            if key != "device":
                self.add_metadata(key, value)
        # Static topics first so that a truncated file still has its geometry.
        di = info.depth_intrinsics  # equals the colour intrinsics when depth is aligned to colour
        depth_frame = COLOR_FRAME_ID if info.depth_aligned_to_color else DEPTH_FRAME_ID
        self._static(DEPTH_INFO_TOPIC, rosmsgs.CAMERA_INFO, rosmsgs.camera_info_msg(di, 0, depth_frame))
        if info.color_intrinsics is not None:
            self._static(
                COLOR_INFO_TOPIC,
                rosmsgs.CAMERA_INFO,
                rosmsgs.camera_info_msg(info.color_intrinsics, 0, COLOR_FRAME_ID),
            )
            if not info.depth_aligned_to_color:
                self._static(
                    TF_STATIC_TOPIC,
                    rosmsgs.TF_MESSAGE,
                    rosmsgs.tf_static_msg(DEPTH_FRAME_ID, COLOR_FRAME_ID, info.depth_to_color.inverse()),
                )
        if info.infrared_intrinsics is not None:
            self._static(
                INFRARED_INFO_TOPIC,
                rosmsgs.CAMERA_INFO,
                rosmsgs.camera_info_msg(info.infrared_intrinsics, 0, INFRARED_FRAME_ID),
            )
        # Register the frame channels up front: a reader then knows which streams to expect.
        self._channel(FRAME_TOPIC, rosmsgs.STRING)
        self._channel(DEPTH_TOPIC, rosmsgs.IMAGE)
        if info.color_intrinsics is not None:
            self._channel(COLOR_TOPIC, rosmsgs.IMAGE)
        if info.infrared_intrinsics is not None:
            self._channel(INFRARED_TOPIC, rosmsgs.IMAGE)

    def _static(self, topic: str, msgtype: str, data: bytes) -> None:
        self._writer.add_message(self._channel(topic, msgtype), 0, data, 0, 0)

    # -- writing -------------------------------------------------------------------------------
    def add_metadata(self, name: str, value: Any) -> None:
        """A metadata record holding one JSON document; a later record of the same name wins."""
        self._writer.add_metadata(name, {"json": _json(value)})

    def write(self, fs: FrameSet) -> None:
        """One frame set: a frame record, then depth, colour, infrared with sequence = frame index."""
        if fs.depth is None:
            raise CaptureError(f"{self.path}: frame {fs.index} has no depth")
        t, seq = int(fs.timestamp_ns), int(fs.index) & 0xFFFFFFFF
        w = self._writer
        streams = ["depth"] + [
            k for k, a in (("color", fs.color), ("infrared", fs.infrared)) if a is not None
        ]
        record = {"index": int(fs.index), "timestamp_ns": t, "streams": streams, "metadata": fs.metadata}
        w.add_message(self._channels[FRAME_TOPIC], t, rosmsgs.string_msg(_json(record)), t, seq)
        depth_frame = COLOR_FRAME_ID if self.info.depth_aligned_to_color else DEPTH_FRAME_ID
        w.add_message(
            self._channels[DEPTH_TOPIC], t, rosmsgs.image_msg(fs.depth, "16UC1", t, depth_frame), t, seq
        )
        if fs.color is not None:
            w.add_message(
                self._channel(COLOR_TOPIC, rosmsgs.IMAGE),
                t,
                rosmsgs.image_msg(fs.color, "rgb8", t, COLOR_FRAME_ID),
                t,
                seq,
            )
        if fs.infrared is not None:
            w.add_message(
                self._channel(INFRARED_TOPIC, rosmsgs.IMAGE),
                t,
                rosmsgs.image_msg(fs.infrared, "mono8", t, INFRARED_FRAME_ID),
                t,
                seq,
            )
        self.frames_written += 1
        if self.first_index is None:
            self.first_index = int(fs.index)
        self.last_index = int(fs.index)

    def write_temperature(self, t_ns: int, temperatures: dict[str, float]) -> None:
        """One sensor_msgs/Temperature per sensor, header.frame_id = sensor name ('asic', 'projector')."""
        ch = self._channel(TEMPERATURE_TOPIC, rosmsgs.TEMPERATURE)
        for name, value in temperatures.items():
            self._writer.add_message(
                ch, int(t_ns), rosmsgs.temperature_msg(int(t_ns), name, float(value)), int(t_ns), 0
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
) -> int:
    """Write a whole recording at once (never overwrites); returns the number of frame sets written."""
    with McapFileWriter(Path(path), info, metadata, compression=compression) as w:
        for t_ns, temps in temperatures:
            w.write_temperature(t_ns, temps)
        for fs in frames:
            w.write(fs)
        return w.frames_written
