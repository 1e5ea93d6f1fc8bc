"""A fake pyrealsense2 that behaves like a RealSense D455 where our live path meets it.

Not our model of the device: each rule copies what librealsense's sources, Intel's examples and its
issue tracker say the device does (the research note behind docs/acquisition.md, which cites them):

- identity: `camera_info` name "RealSense D455" (SDK >= 2.58), product ID "0B5C", product line
  "D400", `usb_type_descriptor` "3.2" or "2.1", `advanced_mode` "YES"/"NO";
- the profiles offered depend on the USB link; `pipeline.start` refuses one that is not offered
  ("Couldn't resolve requests"); the calibration mode (depth Z16 256x144 at 90 fps) exists on USB 3
  only; on USB 2, 1280x720 only at 6 fps (a D455's USB 2 list is not in the sources: the D435's of
  librealsense#4962 and the D455's USB 2 default 640x480 at 15 fps, d400-factory.cpp, stand in);
- `asic_temperature` / `projector_temperature` are whole degrees (int8 in the firmware) and answer
  only while streaming ("query is available during streaming only"); frames carry no temperature;
- `visual_preset` exists only in advanced mode ("object doesn't support option Visual Preset",
  "option 'Visual Preset' not supported"); `toggle_advanced_mode` resets the device;
- auto-calibration: `run_on_chip_calibration` returns (table, (health, 0.0)), `run_tare_calibration`
  (table, (before, after)) as fractions Z / GT - 1; both leave the new table active in RAM; tare
  with `apply preset` (default 1) needs advanced mode; out-of-range JSON values are refused; and, a
  test policy the SDK does not enforce, both demand the calibration profile alone with frames
  already delivered; `get_calibration_table` reads flash, `set_calibration_table` sets RAM,
  `write_calibration` burns the last table set (and fails without one);
- a reset or replug clears RAM (the table, the options) and re-enumerates: the old handles fail,
  the devices-changed callbacks fire on another thread, the device comes back (maybe as USB 2);
- frames: the firmware frame counter per stream; a device-side drop skips numbers; a missing
  frame makes the aggregator repeat the stream's last frame; without metadata the numbers come
  from a host counter (no gaps visible) and `frame_counter` is not supported;
- a stall: no frame arrives while the device stays listed, until a hardware reset;
- dynamics (each where the live path depends on it): frames made in real time on a thread, into a
  pipeline callback (the synchronised frames only: `async_set`, src/pipeline/aggregator.cpp) or
  into the aggregator's 1-frameset queue that drops the older (`single_consumer_frame_queue(1)`,
  rsutils concurrency.h); partial sets filled with a stream's last frame (`_last_set`); timestamp
  domains (src/ds/ds-timestamp.cpp); a re-enumeration that lasts and throws from device creation
  (`device_list.__getitem__` -> `rs2_create_device`, wrappers/python/pyrs_device.cpp; "failed to
  set power state", src/uvc/uvc-device.cpp) with extra remove/add events (src/device_hub.cpp
  tries again); a RAM table kept or lost on stop (unknown: configurable); a refused table
  swallowed (d400-auto-calibration.cpp `set_calibration_table`); self-calibration verdicts
  (`handle_calibration_error`); a motion module (src/ds/d400/d400-motion.cpp).

Inject with `monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)`. Errors are
RuntimeError (IndexError for an empty device list), with the SDK's texts where it has them.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
import types
from collections.abc import Callable
from typing import Any

import numpy as np

Scene = Callable[[str, tuple[int, int, float, float, float, float], "FakeUnit"], Any]


class Member:
    """An enum member as pybind11 exposes it: `.name`, `.value`, hashable."""

    def __init__(self, enum: str, name: str, value: int) -> None:
        self.enum, self.name, self.value = enum, name, value

    def __repr__(self) -> str:
        return f"<{self.enum}.{self.name}: {self.value}>"

    def __str__(self) -> str:
        return f"{self.enum}.{self.name}"

    def __int__(self) -> int:
        return self.value


def _enum(name: str, members: list[str]) -> type:
    cls = type(name, (), {"__members__": {}})
    for i, m in enumerate(members):
        mem = Member(name, m, i)
        setattr(cls, m, mem)
        cls.__members__[m] = mem  # type: ignore[attr-defined]
    return cls


camera_info = _enum("camera_info", [
    "name", "serial_number", "firmware_version", "recommended_firmware_version", "physical_port",
    "debug_op_code", "advanced_mode", "product_id", "camera_locked", "usb_type_descriptor", "product_line",
    "asic_serial_number", "firmware_update_id", "ip_address", "dfu_device_path", "connection_type"])
option = _enum("option", [
    "visual_preset", "emitter_enabled", "laser_power", "enable_auto_exposure", "exposure", "gain",
    "depth_units", "stereo_baseline", "asic_temperature", "projector_temperature",
    "motion_module_temperature", "thermal_compensation", "frames_queue_size", "emitter_on_off"])
stream = _enum("stream", ["any", "depth", "color", "infrared", "fisheye", "gyro", "accel"])
format = _enum("format", ["any", "z16", "disparity16", "xyz32f", "yuyv", "rgb8", "bgr8", "rgba8", "bgra8",
                          "y8", "y16"])
frame_metadata_value = _enum("frame_metadata_value", [
    "frame_counter", "frame_timestamp", "sensor_timestamp", "actual_exposure", "gain_level",
    "auto_exposure", "white_balance", "time_of_arrival", "temperature", "backend_timestamp",
    "actual_fps", "frame_laser_power", "frame_laser_power_mode", "exposure_priority"])
timestamp_domain = _enum("timestamp_domain", ["hardware_clock", "system_time", "global_time"])
distortion = _enum("distortion", ["none", "modified_brown_conrady", "inverse_brown_conrady", "ftheta",
                                  "brown_conrady", "kannala_brandt4"])
# what a D400 frame reports over UVC metadata (no temperature: the D400 registers none)
FRAME_METADATA = ("frame_counter", "frame_timestamp", "sensor_timestamp", "actual_exposure", "gain_level",
                  "auto_exposure", "time_of_arrival", "backend_timestamp", "actual_fps", "frame_laser_power",
                  "frame_laser_power_mode", "exposure_priority")
PRESETS = ["Custom", "Default", "Hand", "High Accuracy", "High Density", "Medium Density"]

_DEPTH_USB3 = {(1280, 720): (30, 15, 5), (848, 480): (90, 60, 30, 15, 5), (640, 480): (90, 60, 30, 15, 5),
               (640, 360): (90, 60, 30, 15, 5), (480, 270): (90, 60, 30, 15, 5),
               (424, 240): (90, 60, 30, 15, 5), (256, 144): (90,)}
_COLOR_USB3 = {(1280, 800): (30, 15, 5), (1280, 720): (30, 15, 5), (848, 480): (60, 30, 15, 5),
               (640, 480): (60, 30, 15, 5), (640, 360): (90, 60, 30, 15, 5), (424, 240): (90, 60, 30, 15, 5)}
_DEPTH_USB2 = {(1280, 720): (6,), (640, 480): (30, 15, 6), (480, 270): (60, 30, 15, 6),
               (424, 240): (60, 30, 15, 6)}
_COLOR_USB2 = {(1280, 720): (6,), (640, 480): (30, 15, 6), (424, 240): (30, 15, 6)}


def profile_table(usb: str) -> list[tuple[str, int, int, str, int, int]]:
    """(stream, width, height, format, fps, index) the device offers on a link."""
    usb3 = usb.startswith("3.")
    depth, color = (_DEPTH_USB3, _COLOR_USB3) if usb3 else (_DEPTH_USB2, _COLOR_USB2)
    out = []
    for (w, h), rates in depth.items():
        for fps in rates:
            out.append(("depth", w, h, "z16", fps, 0))
            out.extend(("infrared", w, h, "y8", fps, i) for i in (1, 2))
    for (w, h), rates in color.items():
        out.extend(("color", w, h, "rgb8", fps, 0) for fps in rates)
    return out


def encode_table(bias: float, health: float, serial: str) -> list[int]:
    """A calibration table: a header and the parameters this fake's depth follows."""
    body = json.dumps({"bias": round(bias, 9), "health": round(health, 6), "serial": serial}, sort_keys=True)
    return list(b"FAKE-D4-CAL1" + body.encode())


def decode_table(table: list[int]) -> dict[str, Any]:
    raw = bytes(table)
    if not raw.startswith(b"FAKE-D4-CAL1"):
        raise RuntimeError("Calibration table is not valid")
    out: dict[str, Any] = json.loads(raw[12:].decode())
    return out


# the firmware's verdicts on a failed self-calibration (src/ds/d400/d400-auto-calibration.cpp,
# `handle_calibration_error`); "timeout": the SDK's own wait running out
CALIBRATION_FAILURES = {
    "edges": "Calibration didn't converge! - edges too close\nPlease retry in different lighting conditions",
    "fill": "Not enough depth pixels! - low fill factor)\nPlease retry in different lighting conditions",
    "converge": "Calibration failed to converge\nPlease retry in different lighting conditions",
    "timeout": "Operation timed out!",
}


def default_temperature(t_s: float) -> float:
    """ASIC: first-order warm-up from 25 to 42 degrees C with a 12-min time constant."""
    return 42.0 - 17.0 * math.exp(-t_s / 720.0)


class FakeUnit:
    """One physical camera: identity, link, flash and RAM, options, counters and injectable faults."""

    def __init__(self, *, serial: str = "215322070001", name: str = "RealSense D455",
                 product_id: str = "0B5C", product_line: str = "D400", usb: str = "3.2",
                 firmware: str = "5.16.0.1", advanced_mode: bool = True, metadata: bool = True,
                 scene: Scene | None = None,
                 hfov_deg: float = 87.0, temperature: Callable[[float], float] = default_temperature,
                 projector_offset_c: float = 3.0, depth_origin_mm: float = 4.55,
                 glass_to_target_mm: float = 1000.0, depth_bias: float = 0.006, on_chip_health: float = 0.42,
                 reset_delays_s: tuple[float, float] = (0.05, 0.3), enumerate_s: float = 0.0,
                 flaps: int = 0, real_time: bool = False, speed: float = 1.0,
                 ram_on_stop: str = "kept", global_time: bool = True) -> None:
        self.serial, self.name, self.product_id, self.product_line = serial, name, product_id, product_line
        self.usb, self.firmware, self.advanced, self.metadata = usb, firmware, advanced_mode, metadata
        self.scene, self.hfov_deg = scene, hfov_deg
        self.temperature, self.projector_offset_c = temperature, projector_offset_c
        self.depth_origin_mm, self.glass_to_target_mm = depth_origin_mm, glass_to_target_mm
        self.reset_delays_s = reset_delays_s
        # re-enumeration: for `enumerate_s` after it is listed again the unit's interfaces are
        # still coming up: making a device from the list and option calls throw; `flaps` extra
        # remove/add pairs fire meanwhile (a D4xx re-enumerates its UVC and HID interfaces one by
        # one: src/device_hub.cpp tries again on "Could not open device"; the uvc backend throws
        # "failed to set power state", src/uvc/uvc-device.cpp)
        self.enumerate_s, self.flaps = enumerate_s, flaps
        self.enumerated_at = -math.inf
        # frames: `real_time` (and always with a callback) a producer thread makes a frameset every
        # 1 / (fps * speed) s whether or not anyone fetches it (the UVC streaming thread); else
        # the older on-demand mode, one frameset per fetch (kept for tests that place a fault on
        # an exact frameset)
        self.real_time, self.speed = real_time, speed
        # partial sets: each stream's frame goes missing with this probability (seeded)
        self.miss_p, self.rng = 0.0, np.random.default_rng(0)
        # a table set in RAM after `pipeline.stop()`: 'kept' or 'lost'. The sources do not say
        # (set_calibration_table sends CALIBRECALC, d400-auto-calibration.cpp; the Viewer sets the
        # table again after each restart, common/on-chip-calib.cpp): the live path must hold either way
        self.ram_on_stop = ram_on_stop
        # timestamp domain (src/ds/ds-timestamp.cpp, src/global_timestamp_reader.cpp): with frame
        # metadata the device's clock ('hardware_clock', ms since it booted), mapped to the host's
        # epoch when global time is on ('global_time', the default); without metadata the host's
        # clock at arrival ('system_time')
        self.global_time = global_time
        self.booted = time.monotonic()
        # the next self-calibrations' outcomes: 'ok' or a CALIBRATION_FAILURES key
        self.verdicts: list[str] = []
        self.flash = encode_table(depth_bias, on_chip_health, serial)
        self.ram: list[int] | None = None
        self.last_set: list[int] | None = None
        self.generation = 0
        self.listed = True
        self.stalled = False
        self.stop_hang_s = 0.0
        self.pipeline: Any = None  # the module's pipeline streaming on this unit
        self.pending: list[dict[str, Any]] = []  # faults for the next framesets, one entry each
        self.power_on: float | None = None
        self.world: FakeRealSense | None = None
        self._power_cycle_state()

    def _power_cycle_state(self) -> None:
        """What a reset or replug clears: RAM table, options, frame counters."""
        self.ram = None
        self.last_set = None
        self.options: dict[str, float] = {
            "emitter_enabled": 1.0, "laser_power": 150.0, "enable_auto_exposure": 1.0, "exposure": 33000.0,
            "gain": 16.0, "depth_units": 0.001, "stereo_baseline": 95.0, "thermal_compensation": 1.0,
            "frames_queue_size": 16.0, "visual_preset": 1.0, "emitter_on_off": 0.0}
        self.counters = {"depth": 0, "color": 0, "infrared": 0}
        self.host_counters = {"depth": 0, "color": 0, "infrared": 0}
        self.last_frames: dict[str, FakeFrame] = {}

    # -- what the device computes -----------------------------------------------------------
    def active_table(self) -> list[int]:
        return self.ram if self.ram is not None else self.flash

    def bias(self) -> float:
        return float(decode_table(self.active_table())["bias"])

    def true_depth_mm(self) -> float:
        """The target's distance from the depth origin (the glass distance plus the offset)."""
        return self.glass_to_target_mm + self.depth_origin_mm

    def temperature_c(self) -> float:
        assert self.world is not None
        if self.power_on is None:
            self.power_on = self.world.clock()
        return self.temperature(self.world.clock() - self.power_on)

    def domain(self) -> str:
        return "system_time" if not self.metadata else "global_time" if self.global_time else "hardware_clock"

    def enumerating(self) -> bool:
        return time.monotonic() < self.enumerated_at + self.enumerate_s

    def streaming(self) -> bool:
        return self.pipeline is not None and self.pipeline.started and self.listed

    def describe_streams(self) -> list[tuple[str, int, int, str, int, int]]:
        return [] if self.pipeline is None else list(self.pipeline.streams)

    # -- faults a test injects ----------------------------------------------------------------
    def inject(self, **fault: Any) -> None:
        """The next frameset: repeat='depth'|'color' (the aggregator re-sends the last frame),
        missing='depth'|'color' (the device lost that stream's frame: a partial set the aggregator
        fills with the last frame), drop={'depth': n} (the firmware counter skips n numbers: frames
        lost on the device)."""
        self.pending.append(fault)

    def stall(self) -> None:
        """Frames stop; the device stays listed (librealsense#8439) until a hardware reset."""
        self.stalled = True

    def unplug(self, down_s: float, usb: str | None = None, resume: bool = False) -> None:
        """Unplug now and plug back in after `down_s`; `usb` is the new link; with `resume` the old
        pipeline delivers frames again after the replug (only the callback and the frame counter
        restarting from 1 tell that the device was power-cycled)."""
        assert self.world is not None
        self.world._remove(self, keep_pipeline=resume)
        threading.Timer(down_s, self.world._add, args=(self, usb)).start()


class FakeRealSense:
    """The world the fake module sees: its units, the callbacks, the log of calls."""

    def __init__(self, *units: FakeUnit, clock: Callable[[], float] = time.monotonic) -> None:
        self.units = list(units)
        for u in self.units:
            u.world = self
        self.clock = clock
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.callbacks: list[Callable[[Any], None]] = []
        self.lock = threading.RLock()
        self.module = build_module(self)

    def log(self, what: str, **values: Any) -> None:
        self.calls.append((what, values))

    def names(self) -> list[str]:
        return [c[0] for c in self.calls]

    def _fire(self, removed: list[tuple[FakeUnit, int]], added: list[tuple[FakeUnit, int]]) -> None:
        info = self.module.event_information(removed, added)
        for cb in list(self.callbacks):
            threading.Thread(target=cb, args=(info,), daemon=True).start()

    def _remove(self, unit: FakeUnit, keep_pipeline: bool = False) -> None:
        with self.lock:
            gone = (unit, unit.generation)
            unit.listed = False
            unit.generation += 1
            unit.stalled = False
            unit._power_cycle_state()
            if not keep_pipeline:
                unit.pipeline = None
            elif unit.pipeline is not None:
                unit.pipeline.generation = unit.generation
            self.log("removed", serial=unit.serial)
        self._fire([gone], [])

    def _add(self, unit: FakeUnit, usb: str | None = None, flaps: int | None = None) -> None:
        with self.lock:
            if usb is not None:
                unit.usb = usb
            unit.listed = True
            unit.enumerated_at = time.monotonic()
            self.log("added", serial=unit.serial, usb=unit.usb)
        self._fire([], [(unit, unit.generation)])
        left = unit.flaps if flaps is None else flaps
        if left > 0 and unit.enumerate_s > 0:
            # the interfaces come and go once more while enumerating: removed, then added again
            step = unit.enumerate_s / (2 * left + 1)
            threading.Timer(step, self._flap, args=(unit, left, step)).start()

    def _flap(self, unit: FakeUnit, left: int, step: float) -> None:
        with self.lock:
            if not unit.listed:
                return  # unplugged meanwhile
            gone = (unit, unit.generation)
            unit.listed = False
            unit.generation += 1
            if unit.pipeline is not None:
                unit.pipeline = None
            self.log("removed", serial=unit.serial, flap=True)
        self._fire([gone], [])
        threading.Timer(step, self._add, args=(unit, None, left - 1)).start()

    def reset(self, unit: FakeUnit) -> None:
        """Asynchronous, as `hardware_reset` is: gone after a moment, back after a few (scaled)."""
        remove_s, back_s = unit.reset_delays_s
        threading.Timer(remove_s, self._remove, args=(unit,)).start()
        threading.Timer(remove_s + back_s, self._add, args=(unit,)).start()


class FakeFrame:
    def __init__(self, unit: FakeUnit, kind: str, index: int, number: int, host_number: int, ts_ms: float,
                 data: Any, profile: Any, fresh: bool = True, arrival_ms: float | None = None) -> None:
        self.unit, self.kind, self.index, self.fresh = unit, kind, index, fresh
        self.arrival_ms = time.time() * 1000.0 if arrival_ms is None else arrival_ms
        self.number, self.host_number, self.ts_ms = number, host_number, ts_ms
        self.data, self.profile = data, profile

    def __bool__(self) -> bool:
        return True

    def get_frame_number(self) -> int:
        return self.number if self.unit.metadata else self.host_number

    def supports_frame_metadata(self, v: Member) -> bool:
        return self.unit.metadata and v.name in FRAME_METADATA

    def get_frame_metadata(self, v: Member) -> int:
        if not self.supports_frame_metadata(v):
            raise RuntimeError(f"metadata value {v.name} is not supported")
        if v.name == "frame_counter":
            return self.number
        if v.name in ("time_of_arrival", "backend_timestamp"):
            return int(self.arrival_ms)  # host epoch ms
        if v.name in ("frame_timestamp", "sensor_timestamp"):
            return int(self.ts_ms * 1000)
        return 1

    def get_data(self) -> Any:
        return self.data

    def keep(self) -> None:
        """rs2_keep_frame: the frame stays valid past the callback (a no-op here)."""

    def is_frameset(self) -> bool:
        return False

    def get_timestamp(self) -> float:
        return self.ts_ms

    def get_frame_timestamp_domain(self) -> Member:
        return getattr(timestamp_domain, self.unit.domain())  # type: ignore[no-any-return]

    def get_profile(self) -> Any:
        return self.profile


class EmptyFrame:
    def __bool__(self) -> bool:
        return False


def build_module(world: FakeRealSense) -> types.ModuleType:
    """The `pyrealsense2` namespace over a world of fake units."""
    mod = types.ModuleType("pyrealsense2")
    mod.__dict__.update(camera_info=camera_info, option=option, stream=stream, format=format,
                        frame_metadata_value=frame_metadata_value, timestamp_domain=timestamp_domain,
                        distortion=distortion)
    mod.__fake__ = world  # type: ignore[attr-defined]

    def intrinsics_of(unit: FakeUnit, w: int, h: int) -> tuple[int, int, float, float, float, float]:
        f = w / 2.0 / math.tan(math.radians(unit.hfov_deg) / 2.0)
        return (w, h, f, f, (w - 1) / 2.0, (h - 1) / 2.0)

    class intrinsics:
        def __init__(self, t: tuple[int, int, float, float, float, float]) -> None:
            self.width, self.height, self.fx, self.fy, self.ppx, self.ppy = t
            self.model = distortion.brown_conrady  # type: ignore[attr-defined]
            self.coeffs = [0.0] * 5

    class extrinsics:
        def __init__(self) -> None:
            self.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            self.translation = [0.0, 0.0, 0.0]

    class option_range:
        def __init__(self, lo: float, hi: float, step: float, default: float) -> None:
            self.min, self.max, self.step, self.default = lo, hi, step, default

    class video_stream_profile:
        def __init__(self, unit: FakeUnit, s: str, w: int, h: int, fmt: str, fps: int, index: int) -> None:
            self.unit, self.key = unit, (s, w, h, fmt, fps, index)

        def stream_type(self) -> Member:
            return getattr(stream, self.key[0])  # type: ignore[no-any-return]

        def format(self) -> Member:
            return getattr(format, self.key[3])  # type: ignore[no-any-return]

        def fps(self) -> int:
            return self.key[4]

        def stream_index(self) -> int:
            return self.key[5]

        def width(self) -> int:
            return self.key[1]

        def height(self) -> int:
            return self.key[2]

        def is_video_stream_profile(self) -> bool:
            return True

        def as_video_stream_profile(self) -> video_stream_profile:
            return self

        def get_intrinsics(self) -> intrinsics:
            return intrinsics(intrinsics_of(self.unit, self.key[1], self.key[2]))

        def get_extrinsics_to(self, other: Any) -> extrinsics:
            return extrinsics()

    class motion_stream_profile:
        def __init__(self, s: str, fps: int) -> None:
            self.s, self._fps = s, fps

        def stream_type(self) -> Member:
            return getattr(stream, self.s)  # type: ignore[no-any-return]

        def format(self) -> Member:
            return format.xyz32f  # type: ignore[attr-defined,no-any-return]

        def fps(self) -> int:
            return self._fps

        def is_video_stream_profile(self) -> bool:
            return False

        def is_motion_stream_profile(self) -> bool:
            return True

    class device:
        def __init__(self, unit: FakeUnit, generation: int) -> None:
            self.unit, self.generation = unit, generation

        def _check(self) -> FakeUnit:
            if self.generation != self.unit.generation or not self.unit.listed:
                raise RuntimeError("Device is not connected (the handle outlived a reset or replug)")
            if self.unit.enumerating():
                raise RuntimeError("xioctl(VIDIOC_QUERYCAP) failed")  # src/linux/backend-v4l2.cpp
            return self.unit

        def supports(self, info: Member) -> bool:
            self._check()
            return info.name in ("name", "serial_number", "firmware_version", "product_id", "product_line",
                                 "usb_type_descriptor", "advanced_mode", "connection_type",
                                 "recommended_firmware_version", "camera_locked", "physical_port")

        def get_info(self, info: Member) -> str:
            u = self._check()
            values = {"name": u.name, "serial_number": u.serial, "firmware_version": u.firmware,
                      "recommended_firmware_version": "5.16.0.1", "product_id": u.product_id,
                      "product_line": u.product_line, "usb_type_descriptor": u.usb,
                      "advanced_mode": "YES" if u.advanced else "NO", "connection_type": "USB",
                      "camera_locked": "YES", "physical_port": "/sys/devices/fake"}
            if info.name not in values:
                raise RuntimeError(f"Selected camera info '{info.name}' is not supported by this device")
            return values[info.name]

        def hardware_reset(self) -> None:
            u = self._check()
            world.log("hardware_reset", serial=u.serial)
            world.reset(u)

        def first_depth_sensor(self) -> sensor:
            self._check()
            return sensor(self, "depth")

        def query_sensors(self) -> list[sensor]:
            """Stereo module, RGB camera and, on a D455, the motion module (BMI055: gyro at 200 or
            400 Hz, accel at 63 or 250 Hz; src/ds/d400/d400-motion.cpp): not video profiles."""
            self._check()
            return [sensor(self, "depth"), sensor(self, "color"), sensor(self, "motion")]

        def is_connected(self) -> bool:
            return self.generation == self.unit.generation and self.unit.listed

    class sensor:
        def __init__(self, dev: device, kind: str) -> None:
            self.dev, self.kind = dev, kind

        def _names(self) -> list[str]:
            u = self.dev._check()
            if self.kind == "motion":
                return ["motion_module_temperature"]
            if self.kind != "depth":
                return ["enable_auto_exposure", "exposure", "gain"]
            names = [k for k in u.options if k != "visual_preset"]
            names += ["asic_temperature", "projector_temperature"]
            return names + (["visual_preset"] if u.advanced else [])

        def supports(self, opt: Member) -> bool:
            return opt.name in self._names()

        def get_supported_options(self) -> list[Member]:
            return [getattr(option, n) for n in self._names()]

        def get_option(self, opt: Member) -> float:
            u = self.dev._check()
            if opt.name not in self._names():
                raise RuntimeError(f"object doesn't support option {_title(opt.name)}")
            if opt.name in ("asic_temperature", "projector_temperature"):
                if not u.streaming():
                    raise RuntimeError("query is available during streaming only")
                t = u.temperature_c() + (u.projector_offset_c if opt.name == "projector_temperature" else 0.0)
                return float(math.trunc(t))  # int8 whole degrees in the firmware
            if opt.name == "motion_module_temperature":
                return float(u.temperature_c())
            return u.options[opt.name]

        def set_option(self, opt: Member, value: float) -> None:
            u = self.dev._check()
            if opt.name not in self._names():
                raise RuntimeError(f"object doesn't support option {_title(opt.name)}")
            if opt.name in ("asic_temperature", "projector_temperature", "stereo_baseline"):
                raise RuntimeError(f"option {_title(opt.name)} is read-only")
            if opt.name == "visual_preset" and not 0 <= value <= len(PRESETS) - 1:
                raise RuntimeError(f"invalid value {value} for Visual Preset")
            u.options[opt.name] = float(value)
            world.log("set_option", option=opt.name, value=float(value), streams=u.describe_streams())

        def get_option_range(self, opt: Member) -> option_range:
            self.dev._check()
            if opt.name not in self._names():
                raise RuntimeError(f"option '{_title(opt.name)}' not supported")
            if opt.name == "visual_preset":
                return option_range(0.0, float(len(PRESETS) - 1), 1.0, 1.0)
            return option_range(0.0, 1e6, 1.0, 0.0)

        def get_option_value_description(self, opt: Member, value: float) -> str:
            if opt.name != "visual_preset" or opt.name not in self._names():
                raise RuntimeError(f"option '{_title(opt.name)}' has no value descriptions")
            return PRESETS[int(value)]

        def get_stream_profiles(self) -> list[Any]:
            u = self.dev._check()
            if self.kind == "motion":
                imu = (("gyro", (200, 400)), ("accel", (63, 250)))
                return [motion_stream_profile(s, f) for s, rates in imu for f in rates]
            keep = ("depth", "infrared") if self.kind == "depth" else ("color",)
            return [video_stream_profile(u, *p) for p in profile_table(u.usb) if p[0] in keep]

        def get_depth_scale(self) -> float:
            return self.dev._check().options["depth_units"]

    class device_list:
        """Devices are made when taken from the list (`__getitem__` calls `rs2_create_device`,
        wrappers/python/pyrs_device.cpp): that opens the device and throws while it enumerates."""

        def __init__(self, devices: list[tuple[FakeUnit, int]]) -> None:
            self.devices = devices

        def __len__(self) -> int:
            return len(self.devices)

        def __getitem__(self, i: int) -> device:
            u, g = self.devices[i]  # IndexError when empty, as pyrealsense2
            if u.enumerating():
                world.log("create_device_failed", serial=u.serial)
                raise RuntimeError("failed to set power state")
            return device(u, g)

        def __iter__(self) -> Any:
            return (self[i] for i in range(len(self.devices)))

        def size(self) -> int:
            return len(self.devices)

    class event_information:
        def __init__(self, removed: list[tuple[FakeUnit, int]], added: list[tuple[FakeUnit, int]]) -> None:
            self.removed, self.added = removed, added

        def was_removed(self, dev: device) -> bool:
            return (dev.unit, dev.generation) in self.removed

        def was_added(self, dev: device) -> bool:
            return (dev.unit, dev.generation) in self.added

        def get_new_devices(self) -> device_list:
            return device_list(list(self.added))

    class context:
        def query_devices(self) -> device_list:
            with world.lock:
                return device_list([(u, u.generation) for u in world.units if u.listed])

        @property
        def devices(self) -> device_list:
            return self.query_devices()

        def set_devices_changed_callback(self, cb: Callable[[Any], None]) -> None:
            world.callbacks.append(cb)

    class config:
        def __init__(self) -> None:
            self.serial: str | None = None
            self.requests: list[tuple[str, int, int, str, int, int]] = []

        def enable_device(self, serial: str) -> None:
            self.serial = serial

        def enable_stream(self, *args: Any) -> None:
            if len(args) == 6:
                s, index, w, h, fmt, fps = args
            else:
                s, w, h, fmt, fps = args
                index = 0
            self.requests.append((s.name, int(w), int(h), fmt.name, int(fps), int(index)))

    class pipeline_profile:
        def __init__(self, dev: device, streams: list[tuple[str, int, int, str, int, int]]) -> None:
            self.dev, self.streams = dev, streams

        def get_device(self) -> device:
            return self.dev

        def get_stream(self, s: Member, index: int = -1) -> video_stream_profile:
            for key in self.streams:
                if key[0] == s.name and index in (-1, key[5]):
                    return video_stream_profile(self.dev.unit, *key)
            raise RuntimeError(f"Profile not found for stream {s.name}")

    class composite_frame:
        def __init__(self, frames: list[FakeFrame]) -> None:
            self.frames = frames

        def is_frameset(self) -> bool:
            return True

        def as_frameset(self) -> composite_frame:
            return self

        def __iter__(self) -> Any:
            return iter(self.frames)

        def keep(self) -> None:
            pass

        def __bool__(self) -> bool:
            return bool(self.frames)

        def size(self) -> int:
            return len(self.frames)

        def first_or_default(self, s: Member) -> Any:
            return next((f for f in self.frames if f.kind == s.name), EmptyFrame())

        def get_depth_frame(self) -> Any:
            return self.first_or_default(stream.depth)  # type: ignore[attr-defined]

        def get_color_frame(self) -> Any:
            return self.first_or_default(stream.color)  # type: ignore[attr-defined]

        def get_infrared_frame(self, index: int = 0) -> Any:
            found = (f for f in self.frames if f.kind == "infrared" and index in (0, f.index))
            return next(found, EmptyFrame())

        def get_timestamp(self) -> float:
            return self.frames[0].ts_ms

        def get_frame_timestamp_domain(self) -> Member:
            return self.frames[0].get_frame_timestamp_domain()

    class pipeline:
        def __init__(self, ctx: Any = None) -> None:
            self.started = False
            self.unit: FakeUnit | None = None
            self.generation = -1
            self.streams: list[tuple[str, int, int, str, int, int]] = []
            self.delivered = 0

        def start(self, cfg: config, callback: Callable[[Any], None] | None = None) -> pipeline_profile:
            with world.lock:
                units = [u for u in world.units if u.listed and cfg.serial in (None, u.serial)]
                if not units:
                    raise RuntimeError("No device connected")
                u = units[0]
                if u.enumerating():
                    raise RuntimeError("failed to set power state")  # src/uvc/uvc-device.cpp
                offered = set(profile_table(u.usb))
                if any(req not in offered for req in cfg.requests):
                    raise RuntimeError("Couldn't resolve requests")
                if u.pipeline is not None and u.pipeline.started:
                    raise RuntimeError("Device or resource busy")
                self.unit, self.generation, self.streams = u, u.generation, list(cfg.requests)
                self.started, self.delivered = True, 0
                self.callback = callback
                self.slot: list[composite_frame] = []  # the aggregator's 1-frameset queue
                self.overwritten = 0
                self.cv = threading.Condition(world.lock)
                u.pipeline = self
                world.log("pipeline.start", serial=u.serial, streams=list(self.streams), usb=u.usb,
                          callback=callback is not None)
                if callback is not None or u.real_time:
                    threading.Thread(target=self._producer, name="fake-uvc", daemon=True).start()
                return pipeline_profile(device(u, u.generation), self.streams)

        def _producer(self) -> None:
            """Frames at the stream's rate, into the callback (the synchronised frames only, no
            repeats: `async_set`) or into a queue of one frameset that drops the older
            (`single_consumer_frame_queue(1)`, src/pipeline/aggregator.cpp)."""
            u = self.unit
            assert u is not None
            period = 1.0 / (max(k[4] for k in self.streams) * u.speed)
            t_next = time.monotonic()
            while self.started:
                t_next += period
                time.sleep(max(0.0, t_next - time.monotonic()))
                if not self.started:
                    return
                with world.lock:
                    if not self._alive():
                        t_next = time.monotonic()
                        continue
                    fs = self._produce()
                    if self.callback is None:
                        if self.slot:
                            self.overwritten += 1
                        self.slot[:] = [fs]
                        self.cv.notify_all()
                if self.callback is not None:
                    fresh = [f for f in fs.frames if getattr(f, "fresh", True)]
                    if fresh:
                        with contextlib.suppress(Exception):
                            self.callback(composite_frame(fresh))

        def stop(self) -> None:
            if not self.started:
                raise RuntimeError("stop() cannot be called before start()")
            u = self.unit
            assert u is not None
            if u.stalled and u.stop_hang_s:
                time.sleep(u.stop_hang_s)  # librealsense#7252: stop() hangs after a stall
            self.started = False
            with world.lock:
                if u.pipeline is self:
                    u.pipeline = None
                    if u.ram_on_stop == "lost":
                        u.ram = None
                world.log("pipeline.stop", serial=u.serial, streams=list(self.streams))

        @property
        def threaded(self) -> bool:
            return self.callback is not None or (self.unit is not None and self.unit.real_time)

        def _alive(self) -> bool:
            u = self.unit
            return (u is not None and self.started and u.listed and not u.stalled and u.pipeline is self
                    and self.generation == u.generation)

        def try_wait_for_frames(self, timeout_ms: int = 5000) -> tuple[bool, composite_frame]:
            if not self.started:
                raise RuntimeError("wait_for_frames cannot be called before start()")
            if self.callback is not None:
                raise RuntimeError("try_wait_for_frames cannot be called if a callback was provided")
            t_end = time.monotonic() + timeout_ms / 1000.0
            if self.threaded:
                with self.cv:
                    while not self.slot:
                        left = t_end - time.monotonic()
                        if left <= 0:
                            return False, composite_frame([])
                        self.cv.wait(left)
                    return True, self.slot.pop()
            while not self._alive():
                if time.monotonic() >= t_end:
                    return False, composite_frame([])
                time.sleep(min(0.005, timeout_ms / 1000.0))
            with world.lock:
                return True, self._produce()

        def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
            ok, fs = self.try_wait_for_frames(timeout_ms)
            if not ok:
                raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
            return fs

        def _produce(self) -> composite_frame:
            u = self.unit
            assert u is not None
            fault = u.pending.pop(0) if u.pending else {}
            self.delivered += 1
            if self.delivered == 1:
                world.log("first_frame", streams=list(self.streams))
            frames = []
            for key in self.streams:
                kind, w, h, _fmt, fps, index = key
                missing = fault.get("missing") == kind or (u.miss_p > 0 and u.rng.random() < u.miss_p)
                if missing and kind in u.last_frames:
                    # the device lost this stream's frame: its counter moves on, and the aggregator
                    # fills the set with the stream's last frame (src/pipeline/aggregator.cpp,
                    # `_last_set`); a callback gets the set without it
                    u.counters[kind] += 1
                    fault = {**fault, "repeat": kind}
                if fault.get("repeat") == kind and kind in u.last_frames:
                    old = u.last_frames[kind]
                    frames.append(FakeFrame(u, kind, old.index, old.number, old.host_number, old.ts_ms,
                                            old.data, old.profile, fresh=False))
                    continue
                u.counters[kind] += 1 + int(fault.get("drop", {}).get(kind, 0))
                u.host_counters[kind] += 1
                n = u.counters[kind]
                if u.domain() == "hardware_clock":
                    ts = (time.monotonic() - u.booted) * 1000.0
                elif self.threaded or u.domain() == "system_time":
                    ts = time.time() * 1000.0
                else:  # on demand: frame-paced times on the host's epoch
                    ts = 1.7e12 + n * 1000.0 / fps
                data = _frame_data(u, kind, intrinsics_of(u, w, h))
                f = FakeFrame(u, kind, index, n, u.host_counters[kind], ts, data,
                              video_stream_profile(u, *key))
                u.last_frames[kind] = f
                frames.append(f)
            return composite_frame(frames)

    class auto_calibrated_device:
        def __init__(self, dev: device) -> None:
            dev._check()
            self.dev = dev

        def _mode_check(self, what: str) -> FakeUnit:
            u = self.dev._check()
            p = u.pipeline
            ok = (p is not None and p.started and p.streams == [("depth", 256, 144, "z16", 90, 0)]
                  and p.delivered > 0 and not u.stalled)
            if not ok:
                raise RuntimeError(f"{what}: test policy: the depth stream alone at 256x144 Z16 90 fps with "
                                   f"frames arriving is Intel's calibration mode (streaming "
                                   f"{u.describe_streams()})")
            return u

        def get_calibration_table(self) -> list[int]:
            u = self.dev._check()
            world.log("get_calibration_table")
            return list(u.flash)

        def set_calibration_table(self, table: list[int]) -> None:
            u = self.dev._check()
            try:
                decode_table(table)
            except RuntimeError:
                # the firmware refuses it and the SDK swallows that (LOG_ERROR "Flashing
                # coefficients_table_id failed", d400-auto-calibration.cpp): RAM stays as it was
                world.log("set_calibration_table_rejected")
                return
            u.ram = list(table)
            u.last_set = list(table)
            world.log("set_calibration_table", bias=decode_table(table)["bias"], streams=u.describe_streams())

        def write_calibration(self) -> None:
            u = self.dev._check()
            if u.last_set is None:
                raise RuntimeError("Write calibration can be called only after set calibration table "
                                   "was called")
            u.flash = list(u.last_set)
            world.log("write_calibration")

        def reset_to_factory_calibration(self) -> None:
            self.dev._check().ram = None

        def run_on_chip_calibration(self, json_content: str,
                                    *args: Any) -> tuple[list[int], tuple[float, float]]:
            u = self._mode_check("run_on_chip_calibration")
            _verdict(u, "run_on_chip_calibration")
            timeout_ms = args[-1]
            params = _checked_json(json_content, {
                "calib type": (0, 2), "speed": (0, 4), "scan parameter": (0, 1), "data sampling": (0, 1),
                "host assistance": (0, 3), "adjust both sides": (0, 1), "white wall mode": (0, 1)})
            current = decode_table(u.active_table())
            new = encode_table(current["bias"], 0.05, u.serial)
            u.ram = new  # the device uses the result at once (Intel's examples), not saved
            world.log("run_on_chip_calibration", streams=u.describe_streams(), json=params,
                      timeout_ms=timeout_ms, emitter=u.options["emitter_enabled"])
            return new, (float(current["health"]), 0.0)

        def run_tare_calibration(self, ground_truth_mm: float, json_content: str,
                                 *args: Any) -> tuple[list[int], tuple[float, float]]:
            u = self._mode_check("run_tare_calibration")
            _verdict(u, "run_tare_calibration")
            timeout_ms = args[-1]
            params = _checked_json(json_content, {
                "average step count": (1, 30), "step count": (5, 30), "accuracy": (0, 3),
                "scan parameter": (0, 1), "data sampling": (0, 1), "apply preset": (0, 1), "speed": (0, 4),
                "host assistance": (0, 2), "depth": (-1, 1)})
            if params.get("apply preset", 1) and not u.advanced:
                raise RuntimeError('Camera "Advanced Mode" must be enabled before running this calibration')
            z_true = u.true_depth_mm()
            if abs(ground_truth_mm - z_true) / z_true > 0.2:
                raise RuntimeError("Calibration failed to converge")
            current = decode_table(u.active_table())
            before = z_true * (1.0 + current["bias"]) / ground_truth_mm - 1.0
            residual = 1e-4
            new_bias = ground_truth_mm * (1.0 + residual) / z_true - 1.0
            new = encode_table(new_bias, current["health"], u.serial)
            u.ram = new
            world.log("run_tare_calibration", streams=u.describe_streams(), ground_truth_mm=ground_truth_mm,
                      json=params, timeout_ms=timeout_ms, advanced=u.advanced)
            return new, (before, residual)

    class rs400_advanced_mode:
        def __init__(self, dev: device) -> None:
            dev._check()
            self.dev = dev

        def is_enabled(self) -> bool:
            return self.dev._check().advanced

        def toggle_advanced_mode(self, enable: bool) -> None:
            u = self.dev._check()
            u.advanced = bool(enable)
            world.log("toggle_advanced_mode", enable=bool(enable))
            world.reset(u)  # the device resets; options return to their defaults

    for name, obj in list(locals().items()):
        if isinstance(obj, type):
            setattr(mod, name, obj)
    return mod


def _verdict(u: FakeUnit, what: str) -> None:
    """The next injected verdict: a failure throws as the SDK does."""
    v = u.verdicts.pop(0) if u.verdicts else "ok"
    if v != "ok":
        assert u.world is not None
        u.world.log(what + "_failed", verdict=v)
        raise RuntimeError(CALIBRATION_FAILURES[v])


def _title(name: str) -> str:
    return " ".join(w.capitalize() for w in name.split("_"))


def _checked_json(text: str, ranges: dict[str, tuple[int, int]]) -> dict[str, Any]:
    """librealsense's JSON checks: known keys in range (`invalid_value`), unknown keys ignored."""
    params: dict[str, Any] = json.loads(text)
    for key, (lo, hi) in ranges.items():
        if key in params and not lo <= params[key] <= hi:
            raise RuntimeError(f"Auto calibration failed! Given value of '{key}' {params[key]} is out of "
                               f"range ({lo} - {hi}).")
    return {k: v for k, v in params.items() if k in ranges}


def _frame_data(u: FakeUnit, kind: str, intr: tuple[int, int, float, float, float, float]) -> Any:
    """The scene's image, or a flat target at the glass distance (depth with the active bias)."""
    if u.scene is not None:
        return u.scene(kind, intr, u)
    w, h = intr[0], intr[1]
    if kind == "depth":
        z = u.true_depth_mm() * (1.0 + u.bias())
        return np.full((h, w), round(z), np.uint16)
    if kind == "color":
        return np.full((h, w, 3), 128, np.uint8)
    return np.full((h, w), 100, np.uint8)
