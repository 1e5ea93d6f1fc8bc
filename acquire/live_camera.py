"""The live D455 through pyrealsense2: streams, preset, emitter, options, temperatures, on-chip/tare.

pyrealsense2 is imported inside the methods, so this module imports (and its helpers are unit
tested) on machines without a camera; the tests that need a device carry `@pytest.mark.hardware`.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any

import numpy as np

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.device import CalibrationResult
from depthstation.core.errors import CameraDisconnected, CameraError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Streams

# option name (pyrealsense2.option member) -> our key in `temperatures()`
TEMPERATURE_OPTIONS = {"asic_temperature": "asic", "projector_temperature": "projector"}
# frame metadata that some firmwares report per frame
TEMPERATURE_METADATA = {"temperature": "sensor"}

# on-chip calibration speed 'Slow' (3) as Intel recommends for a textured scene; host assistance off
ON_CHIP_JSON = '{"calib type": 0, "speed": 3, "scan parameter": 0, "adjust both sides": 0, ' \
               '"white wall mode": 0, "host assistance": 0}'
TARE_JSON = '{"average step count": 20, "step count": 20, "accuracy": 2, "scan parameter": 0, ' \
            '"data sampling": 0}'


def intrinsics_from_rs(intr: Any) -> Intrinsics:
    """Our Intrinsics from an `rs.intrinsics` (the distortion model by its name)."""
    model = getattr(intr.model, "name", str(intr.model))
    return Intrinsics(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy),
                      float(intr.ppx), float(intr.ppy), model, tuple(float(c) for c in intr.coeffs))


def read_options(sensor: Any) -> dict[str, float]:
    """Every option a sensor supports, by its pyrealsense2 name: recorded with each session."""
    out: dict[str, float] = {}
    for opt in sensor.get_supported_options():
        try:
            out[getattr(opt, "name", str(opt))] = float(sensor.get_option(opt))
        except (RuntimeError, TypeError, ValueError):
            continue  # some options cannot be read while streaming
    return out


def read_temperatures(sensor: Any, metadata: dict[str, float] | None = None) -> dict[str, float]:
    """Device temperatures (degrees C) from the depth sensor's options, else from frame metadata."""
    import pyrealsense2 as rs

    out: dict[str, float] = {}
    for name, key in TEMPERATURE_OPTIONS.items():
        opt = getattr(rs.option, name)
        try:
            if sensor.supports(opt):
                out[key] = float(sensor.get_option(opt))
        except RuntimeError:
            continue
    if not out and metadata:
        for name, key in TEMPERATURE_METADATA.items():
            if name in metadata:
                out[key] = float(metadata[name])
    return out


def frame_metadata(frame: Any) -> dict[str, float]:
    """All per-frame metadata the frame supports, by name (exposure, gain, temperature, ...)."""
    import pyrealsense2 as rs

    out: dict[str, float] = {}
    for name, value in rs.frame_metadata_value.__members__.items():
        try:
            if frame.supports_frame_metadata(value):
                out[name] = float(frame.get_frame_metadata(value))
        except RuntimeError:
            continue
    return out


def preset_value(sensor: Any, name: str) -> float:
    """The numeric `visual_preset` value for a preset name ('Default', 'High Accuracy', ...)."""
    import pyrealsense2 as rs

    rng = sensor.get_option_range(rs.option.visual_preset)
    wanted = name.strip().lower().replace("_", " ")
    names = []
    for v in np.arange(rng.min, rng.max + 1, max(rng.step, 1.0)):
        desc = sensor.get_option_value_description(rs.option.visual_preset, float(v))
        names.append(desc)
        if desc.lower() == wanted:
            return float(v)
    raise InputError(None, f"streams.preset '{name}' is not one of the device presets {names}")


class LiveCamera:
    """A RealSense device; `serial` picks one when several are attached."""

    def __init__(self, serial: str | None = None) -> None:
        self.serial = serial
        self._pipe: Any = None
        self._profile: Any = None
        self._depth_sensor: Any = None
        self._last_meta: dict[str, float] = {}

    def _device(self) -> Any:
        import pyrealsense2 as rs

        devices = list(rs.context().query_devices())
        if self.serial is not None:
            devices = [d for d in devices if d.get_info(rs.camera_info.serial_number) == self.serial]
        if not devices:
            which = "" if self.serial is None else f" with serial {self.serial}"
            raise CameraError(f"no RealSense device{which} attached")
        return devices[0]

    def start(self, streams: Streams) -> StreamInfo:
        import pyrealsense2 as rs

        dev = self._device()
        serial = dev.get_info(rs.camera_info.serial_number)
        self.serial = serial
        cfg = rs.config()
        cfg.enable_device(serial)
        w, h, fps = streams.width, streams.height, streams.fps
        if streams.depth:
            cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
        if streams.color:
            cfg.enable_stream(rs.stream.color, w, h, rs.format.rgb8, fps)
        if streams.infrared:
            cfg.enable_stream(rs.stream.infrared, 1, w, h, rs.format.y8, fps)
        self._pipe = rs.pipeline()
        try:
            self._profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise CameraError(f"cannot start {w}x{h}@{fps} on {serial}: {exc}") from exc
        self._depth_sensor = self._profile.get_device().first_depth_sensor()
        ds = self._depth_sensor
        ds.set_option(rs.option.visual_preset, preset_value(ds, streams.preset))
        if ds.supports(rs.option.emitter_enabled):
            ds.set_option(rs.option.emitter_enabled, 1.0 if streams.emitter else 0.0)
        return self._stream_info(streams)

    def _stream_info(self, streams: Streams) -> StreamInfo:
        import pyrealsense2 as rs

        prof = self._profile
        dprof = prof.get_stream(rs.stream.depth).as_video_stream_profile()
        cprof = prof.get_stream(rs.stream.color).as_video_stream_profile() if streams.color else None
        iprof = (prof.get_stream(rs.stream.infrared, 1).as_video_stream_profile()
                 if streams.infrared else None)
        d2c = Extrinsics()
        if cprof is not None:
            e = dprof.get_extrinsics_to(cprof)
            d2c = Extrinsics.from_librealsense(e.rotation, e.translation)
        ds = self._depth_sensor
        baseline = None
        if ds.supports(rs.option.stereo_baseline):
            baseline = float(ds.get_option(rs.option.stereo_baseline)) / 1000.0
        return StreamInfo(
            depth_intrinsics=intrinsics_from_rs(dprof.get_intrinsics()),
            color_intrinsics=None if cprof is None else intrinsics_from_rs(cprof.get_intrinsics()),
            depth_to_color=d2c,
            depth_units_m=float(ds.get_depth_scale()),
            infrared_intrinsics=None if iprof is None else intrinsics_from_rs(iprof.get_intrinsics()),
            baseline_m=baseline,
            fps=float(streams.fps),
            device={**self.device_info(), "preset": streams.preset, "emitter": streams.emitter},
        )

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        import pyrealsense2 as rs

        if self._pipe is None:
            raise CameraError("camera not started")
        ok, fs = self._pipe.try_wait_for_frames(int(timeout_s * 1000))
        if not ok:
            if not self._connected():
                raise CameraDisconnected(f"RealSense {self.serial} disconnected")
            raise CameraError(f"no frame within {timeout_s:g} s")
        depth = fs.get_depth_frame()
        color = fs.get_color_frame()
        ir = fs.get_infrared_frame(1) if fs.first_or_default(rs.stream.infrared) else None
        ref = depth if depth else color
        meta = frame_metadata(ref)
        self._last_meta = meta
        ts_ns = round(fs.get_timestamp() * 1e6) if fs.get_frame_timestamp_domain() == \
            rs.timestamp_domain.global_time else time.time_ns()
        return FrameSet(
            index=int(ref.get_frame_number()),
            timestamp_ns=ts_ns,
            depth=np.asanyarray(depth.get_data()).copy() if depth else None,
            color=np.asanyarray(color.get_data()).copy() if color else None,
            infrared=np.asanyarray(ir.get_data()).copy() if ir else None,
            metadata={**meta, "color_frame_number": int(color.get_frame_number()) if color else None},
        )

    def _connected(self) -> bool:
        import pyrealsense2 as rs

        try:
            return any(d.get_info(rs.camera_info.serial_number) == self.serial
                       for d in rs.context().query_devices())
        except RuntimeError:
            return False

    def stop(self) -> None:
        if self._pipe is not None:
            with contextlib.suppress(RuntimeError):
                self._pipe.stop()
            self._pipe = None

    def temperatures(self) -> dict[str, float]:
        if self._depth_sensor is None:
            return {}
        return read_temperatures(self._depth_sensor, self._last_meta)

    def device_info(self) -> dict[str, str]:
        import pyrealsense2 as rs

        dev = self._profile.get_device() if self._profile is not None else self._device()
        out: dict[str, str] = {}
        for name, key in (("name", "name"), ("serial_number", "serial"), ("firmware_version", "firmware"),
                          ("product_line", "product_line"), ("usb_type_descriptor", "usb")):
            info = getattr(rs.camera_info, name)
            if dev.supports(info):
                out[key] = dev.get_info(info)
        return out

    def options(self) -> dict[str, float]:
        return {} if self._depth_sensor is None else read_options(self._depth_sensor)

    # --- CalibratableCamera -------------------------------------------------------------
    def _acd(self) -> Any:
        import pyrealsense2 as rs

        dev = self._profile.get_device() if self._profile is not None else self._device()
        return rs.auto_calibrated_device(dev)

    def calibration_table(self) -> bytes:
        return bytes(self._acd().get_calibration_table())

    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult:
        try:
            table, health = self._acd().run_on_chip_calibration(ON_CHIP_JSON, int(timeout_s * 1000))
        except RuntimeError as exc:
            raise CameraError(f"on-chip calibration failed: {exc}") from exc
        return CalibrationResult("on_chip", bytes(table), tuple(float(h) for h in health),
                                 {"json": ON_CHIP_JSON})

    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult:
        try:
            table, health = self._acd().run_tare_calibration(ground_truth_m * 1000.0, TARE_JSON,
                                                             int(timeout_s * 1000))
        except RuntimeError as exc:
            raise CameraError(f"tare calibration failed: {exc}") from exc
        return CalibrationResult("tare", bytes(table), tuple(float(h) for h in health),
                                 {"json": TARE_JSON, "ground_truth_m": ground_truth_m})

    def set_calibration_table(self, table: bytes) -> None:
        self._acd().set_calibration_table(list(table))

    def write_calibration(self) -> None:
        self._acd().write_calibration()
