"""A `Camera` over a RealSense recording through pyrealsense2's own file playback.

The same rs.pipeline, frames, intrinsics and options as a live device, so the acquire stage and the
tests run unchanged without hardware. Not real-time by default: every recorded frame is delivered
as fast as the consumer takes it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.errors import CameraError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Streams

#: Timeouts in a row a playback that still runs may take before it counts as stalled (CameraError).
LATE_RETRIES = 2


def _intrinsics(profile: Any) -> Intrinsics:
    i = profile.as_video_stream_profile().get_intrinsics()
    return Intrinsics(
        int(i.width),
        int(i.height),
        float(i.fx),
        float(i.fy),
        float(i.ppx),
        float(i.ppy),
        str(i.model).split(".")[-1],
        tuple(float(c) for c in i.coeffs),
    )


class PlaybackCamera:
    """Plays a `.bag`/`.db3` file; `wait_for_frames` raises EOFError after the last frame."""

    def __init__(self, path: Path, *, real_time: bool = False) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        if self.path.suffix.lower() not in (".bag", ".db3"):
            raise InputError(self.path, "playback needs a RealSense .bag or .db3 recording")
        self.real_time = real_time
        self._pipe: Any = None
        self._profile: Any = None
        self._info: StreamInfo | None = None
        self._last_depth: int | None = None
        self._index = 0
        self._held: Any = None  # the paused playback device until the first frame is asked for

    def start(self, streams: Streams | None = None) -> StreamInfo:
        """Start playback; streams the recording lacks are an InputError (a live camera would fail too)."""
        import pyrealsense2 as rs

        cfg = rs.config()
        cfg.enable_device_from_file(str(self.path), repeat_playback=False)
        pipe = rs.pipeline()
        try:
            # Resolve first so the playback device is non-real-time before the first frame is read.
            cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(self.real_time)
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise InputError(self.path, f"librealsense cannot play it: {exc}") from exc
        playback = profile.get_device().as_playback()
        playback.set_real_time(self.real_time)
        if not self.real_time:
            # held until the first wait_for_frames: the pipeline's queue holds one frame set, and a
            # playback running on while the caller still sets up (a busy machine) dropped frames
            playback.pause()
            self._held = playback
        self._pipe, self._profile = pipe, profile
        kinds = {s.stream_type(): s for s in profile.get_streams()}
        if rs.stream.depth not in kinds:
            self.stop()
            raise InputError(self.path, "has no depth stream")
        want = streams or Streams()
        if want.color and rs.stream.color not in kinds:
            self.stop()
            raise InputError(self.path, "has no colour stream")
        depth = kinds[rs.stream.depth]
        color = kinds.get(rs.stream.color)
        infra = kinds.get(rs.stream.infrared)
        d2c = Extrinsics()
        if color is not None:
            e = depth.get_extrinsics_to(color)
            d2c = Extrinsics.from_librealsense(e.rotation, e.translation)
        opts = self.options()
        baseline = opts.get("stereo_baseline")
        self._info = StreamInfo(
            depth_intrinsics=_intrinsics(depth),
            color_intrinsics=None if color is None else _intrinsics(color),
            depth_to_color=d2c,
            depth_units_m=float(profile.get_device().first_depth_sensor().get_depth_scale()),
            infrared_intrinsics=None if infra is None else _intrinsics(infra),
            baseline_m=None if baseline is None else baseline / 1000.0,
            fps=float(depth.fps()),
            device=self.device_info(),
        )
        return self._info

    def _playback_status(self) -> Any:
        """librealsense's playback status (playing, paused, stopped at the end of the file)."""
        return self._profile.get_device().as_playback().current_status()

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        """Next frame set (a copy, so the caller may keep it); EOFError at the end of the file."""
        import pyrealsense2 as rs

        if self._pipe is None:
            raise CameraError("playback camera not started")
        if self._held is not None:
            self._held.resume()
            self._held = None
        late = 0
        while True:
            try:  # try_wait_for_frames misses frames of a fresh playback in 2.59; this does not
                fs = self._pipe.wait_for_frames(int(timeout_s * 1000))
            except RuntimeError as exc:
                # the end only when the playback says so: on a loaded machine a fresh playback
                # has missed the timeout with frames still to come (a truncated read otherwise)
                if self._playback_status() != rs.playback_status.playing:
                    raise EOFError(f"{self.path}: end of recording") from exc
                late += 1
                if late > LATE_RETRIES:
                    raise CameraError(f"{self.path}: no frame within {(late * timeout_s):.0f} s while the "
                                      "playback still runs") from exc
                continue
            depth = fs.get_depth_frame()
            if not depth:
                continue
            number = int(depth.get_frame_number())
            if number == self._last_depth:  # the syncer repeats a depth frame while waiting on colour
                continue
            self._last_depth = number
            color = fs.get_color_frame()
            infra = fs.first_or_default(rs.stream.infrared)
            meta: dict[str, Any] = {
                "frame_number": number,
                "device_timestamp_ms": float(depth.get_timestamp()),
            }
            for attr in (rs.frame_metadata_value.actual_exposure, rs.frame_metadata_value.frame_laser_power):
                if depth.supports_frame_metadata(attr):
                    meta[str(attr).split(".")[-1]] = int(depth.get_frame_metadata(attr))
            t_ms = depth.get_timestamp()
            self._index += 1
            return FrameSet(
                index=number,
                timestamp_ns=round(t_ms * 1e6),
                depth=np.array(depth.get_data(), dtype=np.uint16, copy=True),
                color=np.array(color.get_data(), dtype=np.uint8, copy=True) if color else None,
                infrared=np.array(infra.get_data(), dtype=np.uint8, copy=True) if infra else None,
                metadata=meta,
            )

    def stop(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            finally:
                self._pipe = None

    def temperatures(self) -> dict[str, float]:
        """Temperatures the recording kept as options (asic/projector on D4xx), degrees C."""
        return {
            k.removesuffix("_temperature"): v for k, v in self.options().items() if k.endswith("_temperature")
        }

    def device_info(self) -> dict[str, str]:
        import pyrealsense2 as rs

        if self._profile is None:
            return {}
        dev = self._profile.get_device()
        out = {}
        for key in ("name", "serial_number", "firmware_version", "product_id", "product_line"):
            info = getattr(rs.camera_info, key)
            if dev.supports(info):
                out[key] = str(dev.get_info(info))
        return out

    def options(self) -> dict[str, float]:
        """Options of the depth sensor as recorded (snake_case names; baseline in mm as librealsense)."""
        if self._profile is None:
            return {}
        sensor = self._profile.get_device().first_depth_sensor()
        out = {}
        for opt in sensor.get_supported_options():
            try:
                out[str(opt).split(".")[-1].strip().lower().replace(" ", "_")] = float(sensor.get_option(opt))
            except RuntimeError:
                continue
        return out

    def __enter__(self) -> PlaybackCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
