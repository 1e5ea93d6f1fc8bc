"""The live D455 through pyrealsense2, as the device behaves (sources in docs/acquisition.md).

- Before streaming: the model (name, product line, product ID) against the protocol, the profiles
  the device offers on its USB link (a D455 on USB 2 has no 1280x720 at 30 fps), advanced mode
  before a visual preset (enabled only with consent: the device resets).
- Calibration runs in Intel's mode: depth only, Z16 256x144 at 90 fps, emitter on, after the first
  frame has arrived; then the protocol's streams start again.
- A table set in the device's RAM is lost when it re-enumerates: the camera holds the session's
  table and sets it again after every reset or replug (event `calibration_reapplied`).
- Frames: the pipeline's aggregator repeats a stream's last frame when that stream missed one, so a
  frameset whose depth or colour frame number repeats is skipped; gaps in the firmware frame
  counter are counted as frames lost on the device side (per stream, in the frame's metadata).
- Faults: a devices-changed callback on a long-lived context notices a replug even when frames
  resume; frames that stop while the device stays listed raise `CameraStalled`, and
  `hardware_reset` resets the device and waits for it to re-enumerate.

pyrealsense2 is imported inside the methods, so this module imports (and its helpers are unit
tested) on machines without a camera; the tests drive it through a fake pyrealsense2
(tests/fake_realsense.py), and those that need a device carry `@pytest.mark.hardware`.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from depthstation.acquire.calibrate import CalibrationFailed
from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.device import (
    PRODUCT_IDS,
    CalibrationResult,
    CalibrationUnavailable,
    CameraStalled,
    CameraUnsuitable,
    device_model,
)
from depthstation.core.errors import CameraDisconnected, CameraError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Streams

# option name (pyrealsense2.option member) -> our key in `temperatures()`; the D400 registers no
# temperature frame metadata, and these options answer only while streaming (whole degrees)
TEMPERATURE_OPTIONS = {"asic_temperature": "asic", "projector_temperature": "projector"}
# camera_info member -> key in device_info() (the rs names; the older short keys are kept beside them)
CAMERA_INFO = ("name", "serial_number", "firmware_version", "recommended_firmware_version", "product_id",
               "product_line", "usb_type_descriptor", "connection_type", "advanced_mode")
LEGACY_INFO_KEYS = {"serial_number": "serial", "firmware_version": "firmware", "usb_type_descriptor": "usb"}

# Intel's self-calibration mode (rs-on-chip-calib.cpp, depth_auto_calibration_example.py, Viewer)
CALIBRATION_PROFILE = ("depth", 256, 144, "z16", 90)
MAX_CALIBRATION_EXPOSURE_US = 15500.0  # the Viewer refuses above: "Exposure value is limiting the fps"
# on-chip: speed 'Slow' (3) as Intel recommends for a textured scene; host assistance off (USB)
ON_CHIP_JSON = '{"calib type": 0, "speed": 3, "scan parameter": 0, "adjust both sides": 0, ' \
               '"white wall mode": 0, "host assistance": 0}'
# tare: 'apply preset' is left at its default (1, High Accuracy for the run), which needs advanced mode
TARE_JSON = '{"average step count": 20, "step count": 20, "accuracy": 2, "scan parameter": 0, ' \
            '"data sampling": 0}'
TARE_GROUND_TRUTH_MM = (60.0, 10000.0)  # librealsense rs_device.h
RESTART_PAUSE_S = 0.6  # a start that fails right after a stop is tried once more after this


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
            continue  # some options cannot be read now (temperatures: only while streaming)
    return out


def read_temperatures(sensor: Any) -> dict[str, float]:
    """Device temperatures (degrees C, whole degrees on a D4xx) from the depth sensor's options."""
    import pyrealsense2 as rs

    out: dict[str, float] = {}
    for name, key in TEMPERATURE_OPTIONS.items():
        opt = getattr(rs.option, name)
        try:
            if sensor.supports(opt):
                out[key] = float(sensor.get_option(opt))
        except RuntimeError:
            continue  # "query is available during streaming only"
    return out


def frame_metadata(frame: Any) -> dict[str, float]:
    """All per-frame metadata the frame supports, by name (exposure, gain, frame counter, ...)."""
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


def stream_requests(streams: Streams) -> list[tuple[str, int, int, str, int]]:
    """The (stream, width, height, format, fps) profiles a protocol's streams ask for."""
    w, h, fps = streams.width, streams.height, streams.fps
    out = []
    if streams.depth:
        out.append(("depth", w, h, "z16", fps))
    if streams.color:
        out.append(("color", w, h, "rgb8", fps))
    if streams.infrared:
        out.append(("infrared", w, h, "y8", fps))
    return out


# firmware: the thermal compensation loop needs 5.12.11 or later; Intel's recommended D455 firmware
# for the SDK the station is built on (librealsense release notes); compared and recorded
THERMAL_LOOP_FIRMWARE = (5, 12, 11)
RECOMMENDED_D455_FIRMWARE = "5.13.0.50"


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(p) for p in text.split(".") if p.isdigit())


def firmware_check(identity: dict[str, str]) -> dict[str, Any]:
    """The device's firmware against the thermal loop's minimum and the recommended version (the
    SDK's `recommended_firmware_version` where it says one)."""
    have = identity.get("firmware_version", "")
    rec = identity.get("recommended_firmware_version") or RECOMMENDED_D455_FIRMWARE
    v = _version(have)
    return {"firmware": have or None, "recommended": rec,
            "thermal_loop_min": ".".join(map(str, THERMAL_LOOP_FIRMWARE)),
            "thermal_loop_ok": bool(v) and v[:3] >= THERMAL_LOOP_FIRMWARE,
            "at_least_recommended": bool(v) and v >= _version(rec)}


def frame_time_ns(fs: Any, ref: Any) -> tuple[int, str]:
    """The frameset's host-epoch time (ns) and how it was had, by its timestamp domain
    (include/librealsense2/h/rs_frame.h): `global_time` and `system_time` are host-epoch ms
    already; `hardware_clock` counts from the device's boot, so the frame's arrival at the host
    (`time_of_arrival` metadata, host ms) stands in, else the time it was read here."""
    import pyrealsense2 as rs

    domain = _enum_name(fs.get_frame_timestamp_domain())
    if domain in ("global_time", "system_time"):
        return round(float(fs.get_timestamp()) * 1e6), domain
    toa = rs.frame_metadata_value.time_of_arrival
    with contextlib.suppress(RuntimeError):
        if ref.supports_frame_metadata(toa):
            return round(float(ref.get_frame_metadata(toa)) * 1e6), f"{domain} (time_of_arrival)"
    return time.time_ns(), f"{domain} (read time)"


def _describe(req: tuple[str, int, int, str, int]) -> str:
    return f"{req[0]} {req[1]}x{req[2]} {req[3]} at {req[4]} fps"


def _enum_name(v: Any) -> str:
    return str(getattr(v, "name", v)).split(".")[-1]


class _Assembled:
    """The newest frame of each stream, taken together: what `pipeline.try_wait_for_frames` hands
    out, for the frames a callback received."""

    def __init__(self, frames: dict[str, Any]) -> None:
        self.frames = frames

    def get_depth_frame(self) -> Any:
        return self.frames.get("depth")

    def get_color_frame(self) -> Any:
        return self.frames.get("color")

    def get_infrared_frame(self, index: int = 0) -> Any:
        return self.frames.get("infrared")

    def first_or_default(self, stream: Any) -> Any:
        return self.frames.get(_enum_name(stream))

    def _ref(self) -> Any:
        return self.frames.get("depth") or next(iter(self.frames.values()))

    def get_timestamp(self) -> float:
        return float(self._ref().get_timestamp())

    def get_frame_timestamp_domain(self) -> Any:
        return self._ref().get_frame_timestamp_domain()


class FrameFeed:
    """The frames the SDK hands a pipeline callback, counted as they arrive.

    Why not `wait_for_frames`: the pipeline's aggregator keeps one frameset (a
    `single_consumer_frame_queue` of capacity 1 that drops the oldest, src/pipeline/aggregator.cpp
    and rsutils concurrency.h): a frameset the host does not fetch in time is overwritten, and the
    gap it leaves in the frame numbers looks like a frame the device lost. With a callback
    (src/pipeline/pipeline.cpp, `start(config, callback)`: the synchronised frames only, no repeats)
    every frame that reaches the host is seen: a gap in the firmware counter at arrival is a frame
    the device (or the link) lost; a frame replaced here before the capture took it is a host drop.
    """

    def __init__(self, wanted: set[str]) -> None:
        self.wanted = wanted
        self.cv = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.fresh: set[str] = set()
        self.arrived: dict[str, int] = {}
        self.device_lost: dict[str, int] = {k: 0 for k in wanted}
        self.host_dropped: dict[str, int] = {k: 0 for k in wanted}
        self.counter = True

    def __call__(self, frame: Any) -> None:
        """The SDK's thread: one frame or a frameset."""
        import pyrealsense2 as rs

        try:
            frames = list(frame.as_frameset()) if frame.is_frameset() else [frame]
            with self.cv:
                for f in frames:
                    prof = f.get_profile()
                    kind = _enum_name(prof.stream_type())
                    if kind not in self.wanted or (kind == "infrared" and int(prof.stream_index()) != 1):
                        continue
                    n = int(f.get_frame_number())
                    counter = bool(f.supports_frame_metadata(rs.frame_metadata_value.frame_counter))
                    self.counter = self.counter and counter
                    last = self.arrived.get(kind)
                    if last is not None and n == last:
                        continue  # the same frame again: not new
                    if last is not None and n > last + 1 and counter:
                        self.device_lost[kind] += n - last - 1
                    self.arrived[kind] = n
                    if kind in self.fresh:
                        self.host_dropped[kind] += 1  # the one before was never taken
                    keep = getattr(f, "keep", None)
                    if callable(keep):
                        keep()  # held past the callback (librealsense frames return to a pool)
                    self.latest[kind] = f
                    self.fresh.add(kind)
                if self.fresh >= self.wanted:
                    self.cv.notify_all()
        except RuntimeError:
            return  # a frame of a device going away

    def take(self, timeout_s: float, stop: Callable[[], bool]) -> tuple[_Assembled | None, dict[str, Any]]:
        """The next set with a new frame on every stream (None after `timeout_s` or when `stop()`),
        and the device losses and host drops counted since the last take."""
        t_end = time.monotonic() + timeout_s
        with self.cv:
            while not self.fresh >= self.wanted:
                left = t_end - time.monotonic()
                if left <= 0 or stop():
                    return None, {}
                self.cv.wait(min(left, 0.05))
            out = _Assembled({k: self.latest[k] for k in self.wanted})
            counts = {"device_lost": dict(self.device_lost), "host_dropped": dict(self.host_dropped),
                      "counter": self.counter}
            self.fresh.clear()
            self.device_lost = dict.fromkeys(self.wanted, 0)
            self.host_dropped = dict.fromkeys(self.wanted, 0)
            return out, counts


class LiveCamera:
    """A RealSense device; `serial` picks one when several are attached.

    `model` (the protocol's `[device] model`) is checked before streaming; `needs_advanced_mode`
    names what needs advanced mode besides a preset (tare); `consent(question)` may enable it.
    """

    def __init__(self, serial: str | None = None, *, model: str | None = None,
                 needs_advanced_mode: str | None = None, consent: Callable[[str], bool] | None = None,
                 removal_timeout_s: float = 10.0, enumeration_timeout_s: float = 20.0,
                 quiet_s: float = 1.0, stop_deadline_s: float = 3.0, first_frame_timeout_s: float = 5.0,
                 poll_s: float = 0.1) -> None:
        self.serial = serial
        self.model = model
        self.needs_advanced_mode = needs_advanced_mode
        self.consent = consent
        self.removal_timeout_s = removal_timeout_s
        self.enumeration_timeout_s = enumeration_timeout_s
        self.quiet_s = quiet_s
        self.stop_deadline_s = stop_deadline_s
        self.first_frame_timeout_s = first_frame_timeout_s
        self.poll_s = poll_s
        self._ctx: Any = None
        self._dev: Any = None
        self._pipe: Any = None
        self._profile: Any = None
        self._depth_sensor: Any = None
        self._streams: Streams | None = None
        self._info: StreamInfo | None = None
        self._mode: str | None = None  # 'protocol' or 'calibration' while streaming
        self._identity: dict[str, str] = {}
        self._preset: str | None = None
        self._feed: FrameFeed | None = None
        self._held: bytes | None = None  # the session's table, set in RAM: re-applied after a reset
        self._table_on_device = False
        self._lock = threading.Lock()
        self._removed = threading.Event()
        self._arrived = threading.Event()
        self._events: list[dict[str, Any]] = []
        self._reset_tracking()

    # -- device discovery and checks ------------------------------------------------------
    def _context(self) -> Any:
        """One long-lived context: its devices-changed callback must outlive every pipeline."""
        import pyrealsense2 as rs

        if self._ctx is None:
            ctx = rs.context()
            ctx.set_devices_changed_callback(self._on_devices_changed)
            self._ctx = ctx
        return self._ctx

    def _on_devices_changed(self, info: Any) -> None:
        """The SDK's thread: a removal of our device or the arrival of our serial."""
        import pyrealsense2 as rs

        with self._lock:
            if self._dev is not None:
                with contextlib.suppress(RuntimeError):
                    if info.was_removed(self._dev):
                        self._removed.set()
                        self._table_on_device = False
                        self._log("removed")
            try:
                new = info.get_new_devices()
                count = len(new)
            except RuntimeError:
                return
            for i in range(count):
                try:
                    serial = new[i].get_info(rs.camera_info.serial_number)
                except (RuntimeError, IndexError):
                    # made while its interfaces enumerate: it arrived, which one is told later
                    self._arrived.set()
                    continue
                if self.serial is None or serial == self.serial:
                    self._arrived.set()

    def _log(self, event: str, **values: Any) -> None:
        self._events.append({"event": event, "serial": self.serial, "time_ns": time.time_ns(), **values})

    def take_events(self) -> list[dict[str, Any]]:
        """Device events since the last call (removed, stalled, hardware_reset, reenumerated,
        advanced_mode_enabled, calibration_reapplied), for the session's capture log."""
        with self._lock:
            out, self._events = self._events, []
        return out

    def _find(self, wait: bool = True) -> Any:
        """Our device (waited for while a device is listed but still enumerating, up to
        `enumeration_timeout_s`, unless not `wait`), made from the context's list."""
        t_end = time.monotonic() + self.enumeration_timeout_s
        while True:
            try:
                return self._find_now()
            except CameraError as exc:
                if not wait or "still enumerating" not in str(exc) or time.monotonic() > t_end:
                    raise
            time.sleep(self.poll_s)

    def _find_now(self) -> Any:
        """Our device, made from the context's list. Making each device opens it over USB, which
        throws while its interfaces enumerate (pyrealsense2's `device_list.__getitem__` calls
        `rs2_create_device`, wrappers/python/pyrs_device.cpp; src/device_hub.cpp catches the same
        throw and tries again): a device that cannot be made now is one not listed yet."""
        import pyrealsense2 as rs

        devices, busy = [], 0
        try:
            listed = self._context().query_devices()
            count = len(listed)
        except RuntimeError as exc:
            raise CameraError(f"cannot list the RealSense devices now ({exc}): one may be re-enumerating") \
                from exc
        serials = []
        for i in range(count):
            try:
                d = listed[i]
                serial = str(d.get_info(rs.camera_info.serial_number))
            except (RuntimeError, IndexError):
                busy += 1
                continue  # a device leaving, or one still enumerating, while we look
            serials.append(serial)
            if self.serial is None or serial == self.serial:
                devices.append(d)
        if not devices:
            which = "" if self.serial is None else f" with serial {self.serial}"
            why = f" ({busy} still enumerating)" if busy else ""
            raise CameraError(f"no RealSense device{which} attached{why}")
        if self.serial is None and len(devices) > 1:
            raise CameraUnsuitable(f"{len(devices)} RealSense devices are attached (serials "
                                   f"{', '.join(serials)}): name one with --camera live:SERIAL")
        return devices[0]

    @contextlib.contextmanager
    def _answering(self, what: str) -> Iterator[None]:
        """A device call that throws (the device re-enumerating or gone) as a CameraError, which
        the capture's reconnect retries; a RuntimeError must not leave the station as an internal
        error."""
        try:
            yield
        except RuntimeError as exc:
            raise CameraError(f"{self._label()} did not answer {what} ({exc}): it may be re-enumerating; "
                              "re-plug it if this persists") from exc

    def _listed(self) -> bool:
        try:
            self._find(wait=False)
        except (CameraError, RuntimeError):
            return False
        return True

    def _read_identity(self, dev: Any) -> dict[str, str]:
        import pyrealsense2 as rs

        out: dict[str, str] = {}
        for name in CAMERA_INFO:
            info = getattr(rs.camera_info, name)
            with contextlib.suppress(RuntimeError):
                if dev.supports(info):
                    out[name] = str(dev.get_info(info))
        return out

    def _label(self) -> str:
        return f"{self._identity.get('name', 'RealSense')} {self.serial or ''}".strip()

    def _check_device(self, dev: Any) -> dict[str, str]:
        """Model, product line and product ID against the protocol, before anything streams."""
        ident = self._read_identity(dev)
        self._identity = ident
        self.serial = ident.get("serial_number", self.serial)
        if self.model is None:
            return ident
        want = self.model.upper()
        found = device_model(ident.get("name", ""))
        pid = ident.get("product_id", "?").upper()
        line = ident.get("product_line")
        ids = PRODUCT_IDS.get(want, ())
        if found != want or (line is not None and line != "D400") or (ids and pid not in ids):
            msg = (f"the protocol is for a {want} ([device] model), but the camera {self.serial} is a "
                   f"'{ident.get('name', '?')}' (product line {line or '?'}, product ID {pid}): attach a "
                   f"{want} or use a protocol written for this model")
            raise CameraUnsuitable(msg)
        return ident

    def _offered(self, dev: Any) -> set[tuple[str, int, int, str, int]]:
        """Every (stream, width, height, format, fps) the device offers on its current link."""
        out: set[tuple[str, int, int, str, int]] = set()
        for sensor in dev.query_sensors():
            for p in sensor.get_stream_profiles():
                if not p.is_video_stream_profile():
                    continue
                v = p.as_video_stream_profile()
                out.add((_enum_name(p.stream_type()), int(v.width()), int(v.height()),
                         _enum_name(p.format()), int(p.fps())))
        return out

    def _check_profiles(self, dev: Any, wanted: list[tuple[str, int, int, str, int]]) -> None:
        missing = [r for r in wanted if r not in self._offered(dev)]
        if not missing:
            return
        usb = self._identity.get("usb_type_descriptor", "?")
        hint = ("connect it to a USB 3 port (blue or SS) with a USB 3 cable" if not usb.startswith("3.")
                else "choose a mode the camera offers (rs-enumerate-devices lists them)")
        msg = f"{self._label()} on USB {usb} offers no {', '.join(_describe(r) for r in missing)}: {hint}"
        raise CameraUnsuitable(msg)

    def _advanced_mode_on(self, dev: Any) -> bool:
        import pyrealsense2 as rs

        return bool(rs.rs400_advanced_mode(dev).is_enabled())

    def _ensure_advanced_mode(self, dev: Any, why: str) -> Any:
        """Advanced mode on, or enabled with the operator's consent (the device resets and comes
        back with default options), else a one-line refusal."""
        import pyrealsense2 as rs

        if self._advanced_mode_on(dev):
            return dev
        question = (f"advanced mode is off on {self._label()}; {why} needs it. Enable it now? (the camera "
                    f"resets once and comes back with default options)")
        if self.consent is None or not self.consent(question):
            msg = (f"advanced mode is off on {self._label()}: {why} needs it; enable it in realsense-viewer, "
                   f"or answer yes (--yes) to let the station enable it (the camera resets once)")
            raise CameraUnsuitable(msg)
        self._removed.clear()
        self._arrived.clear()
        rs.rs400_advanced_mode(dev).toggle_advanced_mode(True)
        self._table_on_device = False
        self._log("advanced_mode_enabled")
        self._wait_reenumeration("enabling advanced mode")
        dev = self._find()
        self._check_device(dev)
        if not self._advanced_mode_on(dev):
            raise CameraUnsuitable(f"advanced mode is still off on {self._label()} after enabling it")
        return dev

    # -- streaming ---------------------------------------------------------------------------
    def _reset_tracking(self) -> None:
        self._last_number: dict[str, int] = {}
        self._lost: dict[str, int] = {"depth": 0, "color": 0}
        self._dropped: dict[str, int] = {"depth": 0, "color": 0}
        self._skipped: dict[str, int] = {"repeated": 0, "stale_color": 0}

    def _start_pipeline(self, dev: Any, wanted: list[tuple[str, int, int, str, int]], what: str,
                        feed: bool = False) -> None:
        import pyrealsense2 as rs

        cfg = rs.config()
        cfg.enable_device(self.serial)
        for stream, w, h, fmt, fps in wanted:
            if stream == "infrared":
                cfg.enable_stream(rs.stream.infrared, 1, w, h, rs.format.y8, fps)
            else:
                cfg.enable_stream(getattr(rs.stream, stream), w, h, getattr(rs.format, fmt), fps)
        pipe = rs.pipeline(self._context())
        self._feed = FrameFeed({r[0] for r in wanted if r[0] in ("depth", "color")}) if feed else None
        try:
            try:
                profile = pipe.start(cfg) if self._feed is None else pipe.start(cfg, self._feed)
            except RuntimeError:
                # right after a stop the device may still be busy: the Viewer waits 600 ms and
                # tries once more (common/on-chip-calib.cpp restarts)
                time.sleep(RESTART_PAUSE_S)
                pipe = rs.pipeline(self._context())
                profile = pipe.start(cfg) if self._feed is None else pipe.start(cfg, self._feed)
        except RuntimeError as exc:
            self._feed = None
            raise CameraError(f"cannot start {what} on {self._label()}: {exc}") from exc
        with self._lock:
            self._pipe, self._profile = pipe, profile
            self._dev = profile.get_device()
            self._removed.clear()
        self._depth_sensor = self._dev.first_depth_sensor()
        self._reset_tracking()

    def start(self, streams: Streams) -> StreamInfo:
        """Stream the protocol's profile (kept running when it runs already)."""
        if (self._pipe is not None and self._mode == "protocol" and self._streams == streams
                and self._info is not None and not self._removed.is_set()):
            return self._info
        self.stop()
        try:
            with self._answering("while starting"):
                return self._start_protocol(streams)
        except CameraError:
            self.stop()
            raise

    def _start_protocol(self, streams: Streams) -> StreamInfo:
        dev = self._find()
        self._check_device(dev)
        preset = streams.preset.strip().lower() != "default"
        reasons = [f"streams.preset '{streams.preset}'"] if preset else []
        reasons += [self.needs_advanced_mode] if self.needs_advanced_mode else []
        if reasons:
            dev = self._ensure_advanced_mode(dev, " and ".join(reasons))
        wanted = stream_requests(streams)
        self._check_profiles(dev, wanted)
        self._start_pipeline(dev, wanted, ", ".join(_describe(r) for r in wanted), feed=True)
        try:
            self._configure(streams)
        except (RuntimeError, CameraError) as exc:
            self.stop()
            if isinstance(exc, CameraError):
                raise
            raise CameraError(f"cannot set the options of {self._label()}: {exc}") from exc
        self._mode, self._streams = "protocol", streams
        self._info = self._stream_info(streams)
        return self._info

    def _configure(self, streams: Streams) -> None:
        """Preset (only in advanced mode; without it the firmware's defaults are the Default preset),
        emitter, and the session's calibration table if the device lost it."""
        import pyrealsense2 as rs

        ds = self._depth_sensor
        if self._advanced_mode_on(self._dev):
            ds.set_option(rs.option.visual_preset, preset_value(ds, streams.preset))
            value = float(ds.get_option(rs.option.visual_preset))
            self._preset = str(ds.get_option_value_description(rs.option.visual_preset, value))
        elif streams.preset.strip().lower() == "default":
            self._preset = "Default (firmware defaults: advanced mode off)"
        else:
            raise CameraUnsuitable(f"advanced mode is off on {self._label()}: streams.preset "
                                   f"'{streams.preset}' cannot be set")
        if ds.supports(rs.option.emitter_enabled):
            ds.set_option(rs.option.emitter_enabled, 1.0 if streams.emitter else 0.0)
        self._pin_emitter_on_off(ds)
        self._apply_held_table()

    def _pin_emitter_on_off(self, ds: Any) -> None:
        """`emitter_on_off` (the emitter on every other frame) persists in the device until a reset:
        left on by another program it blanks the pattern of every other depth frame. Pinned off."""
        import pyrealsense2 as rs

        opt = getattr(rs.option, "emitter_on_off", None)
        if opt is not None and ds.supports(opt) and ds.get_option(opt) != 0.0:
            ds.set_option(opt, 0.0)
            self._log("emitter_on_off_pinned_off")

    def _apply_held_table(self) -> None:
        """The session's table, set again after every pipeline start, as the Viewer does: whether
        a table set in RAM outlives `pipeline.stop()` is not documented, and a tare after an OCC
        that ran on the flash table would replace the OCC result without a word. Logged
        (`calibration_reapplied`) when the device is known to have lost it (reset, replug)."""
        if self._held is None:
            return
        lost = not self._table_on_device
        try:
            self._acd().set_calibration_table(list(self._held))
        except RuntimeError as exc:
            msg = (f"cannot set the session's calibration table on {self._label()} again ({exc}): "
                   "the capture stops rather than record with another calibration")
            raise CameraError(msg) from exc
        self._table_on_device = True
        if lost:
            self._log("calibration_reapplied")

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
            device={**self.device_info(), "preset": streams.preset, "emitter": streams.emitter,
                    "options": read_options(ds), "firmware_check": firmware_check(self._identity)},
        )

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        """The next frameset with new frames on every stream; repeated ones are skipped and counted."""
        import pyrealsense2 as rs

        if self._pipe is None:
            raise CameraError("camera not started")
        t_end = time.monotonic() + timeout_s
        while True:
            if self._removed.is_set():
                raise CameraDisconnected(f"{self._label()} was unplugged or reset (device-change event)")
            left = t_end - time.monotonic()
            ok, fs = False, None
            counts: dict[str, Any] = {}
            if left > 0 and self._feed is not None:
                fs, counts = self._feed.take(left, self._removed.is_set)
                ok = fs is not None
            elif left > 0:
                ok, fs = self._pipe.try_wait_for_frames(max(1, int(left * 1000)))
            if not ok or fs is None:
                if self._removed.is_set() or not self._listed():
                    raise CameraDisconnected(f"{self._label()} disconnected")
                raise CameraStalled(f"{self._label()}: no frame within {timeout_s:g} s while it stays "
                                    "connected (a stalled stream)")
            if self._removed.is_set():
                raise CameraDisconnected(f"{self._label()} was unplugged or reset (device-change event)")
            depth = fs.get_depth_frame()
            color = fs.get_color_frame()
            frames = {k: f for k, f in (("depth", depth), ("color", color)) if f}
            numbers = {k: int(f.get_frame_number()) for k, f in frames.items()}
            ref = depth if depth else color
            counter = bool(ref.supports_frame_metadata(rs.frame_metadata_value.frame_counter))
            repeated = {k for k, n in numbers.items() if self._last_number.get(k) == n}
            for k, n in numbers.items():
                last = self._last_number.get(k)
                if last is not None and n < last:
                    self._table_on_device = False
                    raise CameraDisconnected(f"{self._label()}: the {k} frame counter went back from {last} "
                                             f"to {n}: the camera was reset or re-plugged")
                if counts:  # counted as they arrived: the device's losses apart from the host's drops
                    self._lost[k] += int(counts["device_lost"].get(k, 0))
                    self._dropped[k] += int(counts["host_dropped"].get(k, 0))
                elif last is not None and n > last + 1 and counter:
                    self._lost[k] += n - last - 1  # no callback: the host's drops cannot be told apart
                self._last_number[k] = n
            if "depth" in repeated:
                self._skipped["repeated"] += 1
                continue
            if "color" in repeated:
                self._skipped["stale_color"] += 1
                continue
            return self._frameset(fs, depth, color, ref, numbers, counter)

    def _frameset(self, fs: Any, depth: Any, color: Any, ref: Any, numbers: dict[str, int],
                  counter: bool) -> FrameSet:
        import pyrealsense2 as rs

        ir = fs.get_infrared_frame(1) if fs.first_or_default(rs.stream.infrared) else None
        meta: dict[str, Any] = frame_metadata(ref)
        meta.update({
            "color_frame_number": numbers.get("color"),
            "frame_counter": "device" if counter else "host",
            "frames_lost_before": dict(self._lost) if counter else None,
            "host_frames_dropped_before": dict(self._dropped) if self._feed is not None else None,
            "framesets_skipped_before": dict(self._skipped),
        })
        self._lost = {"depth": 0, "color": 0}
        self._dropped = {"depth": 0, "color": 0}
        self._skipped = {"repeated": 0, "stale_color": 0}
        ts_ns, meta["timestamp_domain"] = frame_time_ns(fs, ref)
        return FrameSet(
            index=int(ref.get_frame_number()),
            timestamp_ns=ts_ns,
            depth=np.asanyarray(depth.get_data()).copy() if depth else None,
            color=np.asanyarray(color.get_data()).copy() if color else None,
            infrared=np.asanyarray(ir.get_data()).copy() if ir else None,
            metadata=meta,
        )

    def stop(self) -> None:
        """Stop streaming; a pipeline that hangs after a stall is left behind after a deadline."""
        pipe, self._pipe = self._pipe, None
        self._mode, self._info = None, None
        if pipe is None:
            return

        def _stop() -> None:
            with contextlib.suppress(RuntimeError):
                pipe.stop()

        worker = threading.Thread(target=_stop, name="rs-stop", daemon=True)
        worker.start()
        worker.join(self.stop_deadline_s)
        if worker.is_alive():
            self._log("stop_hung", deadline_s=self.stop_deadline_s)

    # -- recovery ----------------------------------------------------------------------------
    def _wait_reenumeration(self, why: str) -> float:
        """Wait for our device to leave and come back (callback, with polling as a backstop), then
        for a quiet spell; seconds it took."""
        t0 = time.monotonic()
        t_end = t0 + self.removal_timeout_s
        while not self._removed.is_set() and self._listed() and time.monotonic() < t_end:
            time.sleep(self.poll_s)
        t_end = time.monotonic() + self.enumeration_timeout_s
        while True:
            if self._arrived.is_set() or self._listed():
                break
            if time.monotonic() > t_end:
                msg = (f"{self._label()} did not come back within {self.enumeration_timeout_s:g} s after "
                       f"{why}: re-plug it")
                raise CameraError(msg)
            time.sleep(self.poll_s)
        # the device may re-enumerate more than once: take it after a quiet spell
        while True:
            self._arrived.clear()
            time.sleep(self.quiet_s)
            if not self._arrived.is_set() and self._listed():
                break
            if time.monotonic() > t_end + self.enumeration_timeout_s:
                raise CameraError(f"{self._label()} keeps re-enumerating after {why}")
        self._removed.clear()
        return time.monotonic() - t0

    def hardware_reset(self) -> None:
        """Reset the device (the recovery Intel suggests for a stalled stream) and wait for it."""
        self.stop()
        self._removed.clear()
        self._arrived.clear()
        try:
            dev = self._find()
        except CameraError:
            dev = None  # already gone: only wait for it
        if dev is not None:
            try:
                dev.hardware_reset()
            except RuntimeError as exc:
                raise CameraError(f"hardware reset of {self._label()} failed: {exc}") from exc
        self._table_on_device = False
        self._log("hardware_reset")
        took = self._wait_reenumeration("a hardware reset")
        self._log("reenumerated", after_s=round(took, 3))

    # -- what the device says ----------------------------------------------------------------
    def temperatures(self) -> dict[str, float]:
        if self._depth_sensor is None or self._pipe is None:
            return {}
        return read_temperatures(self._depth_sensor)

    def device_info(self) -> dict[str, str]:
        if not self._identity:
            self._identity = self._read_identity(self._find())
        out = dict(self._identity)
        for name, key in LEGACY_INFO_KEYS.items():
            if name in out:
                out[key] = out[name]
        if "usb_type_descriptor" in out:
            out["usb"] = out["usb_type_descriptor"]
        model = device_model(out.get("name", ""))
        if model:
            out["model"] = model
        if self._preset is not None:
            out["preset_applied"] = self._preset
        return out

    def options(self) -> dict[str, float]:
        return {} if self._depth_sensor is None else read_options(self._depth_sensor)

    # --- CalibratableCamera -------------------------------------------------------------
    def _acd(self) -> Any:
        import pyrealsense2 as rs

        return rs.auto_calibrated_device(self._dev if self._pipe is not None else self._find())

    def calibration_table(self) -> bytes:
        """The table in flash (what a reset brings back)."""
        with self._answering("reading its calibration table"):
            return bytes(self._acd().get_calibration_table())

    def active_calibration_table(self) -> bytes:
        """The table the device uses: the session's table held in RAM, else the one in flash."""
        return self._held if self._held is not None else self.calibration_table()

    def hold_calibration(self, table: bytes | None) -> None:
        """Keep `table` active in RAM from the next start on (a resumed session's calibration)."""
        self._held = None if table is None else bytes(table)
        self._table_on_device = False
        if self._pipe is not None:
            self._apply_held_table()

    @contextlib.contextmanager
    def _calibration_mode(self, kind: str) -> Iterator[None]:
        """Depth only, 256x144 Z16 at 90 fps, emitter on, first frame awaited; afterwards the
        protocol's streams run again if they ran before."""
        was = self._streams if self._mode == "protocol" else None
        self.stop()
        with self._answering(f"before the {kind} calibration"):
            dev = self._find()
            self._check_device(dev)
            if kind == "tare":
                dev = self._ensure_advanced_mode(dev, "tare calibration (it runs with the High Accuracy "
                                                        "preset)")
            offered = self._offered(dev)
        if CALIBRATION_PROFILE not in offered:
            usb = self._identity.get("usb_type_descriptor", "?")
            msg = (f"{self._label()} on USB {usb} offers no depth 256x144 at 90 fps, the mode Intel's "
                   f"self-calibration runs in: {kind} calibration skipped (connect it to a USB 3 port to "
                   "calibrate)")
            if was is not None:
                self.start(was)
            raise CalibrationUnavailable(msg)
        try:
            with self._answering("in the calibration mode"):
                self._enter_calibration_mode(dev)
            yield
        finally:
            self.stop()
            if was is not None:
                self.start(was)

    def _enter_calibration_mode(self, dev: Any) -> None:
        import pyrealsense2 as rs

        self._start_pipeline(dev, [CALIBRATION_PROFILE], "the calibration mode (depth 256x144 at 90 fps)")
        self._mode = "calibration"
        ds = self._depth_sensor
        manual = ds.supports(rs.option.enable_auto_exposure) and \
            ds.get_option(rs.option.enable_auto_exposure) == 0
        if manual and ds.get_option(rs.option.exposure) > MAX_CALIBRATION_EXPOSURE_US:
            msg = (f"manual exposure {ds.get_option(rs.option.exposure):g} us is above "
                   f"{MAX_CALIBRATION_EXPOSURE_US:g} us, too long for 90 fps: turn auto exposure on")
            raise CameraError(msg)
        if ds.supports(rs.option.emitter_enabled):
            ds.set_option(rs.option.emitter_enabled, 1.0)
        self._pin_emitter_on_off(ds)
        self._apply_held_table()
        ok, _ = self._pipe.try_wait_for_frames(int(self.first_frame_timeout_s * 1000))
        if not ok:
            msg = f"no frame within {self.first_frame_timeout_s:g} s in the calibration mode"
            if self._removed.is_set() or not self._listed():
                raise CameraDisconnected(f"{self._label()}: {msg}: it was unplugged")
            # a stall that began while warming up persists until a reset: the station resets it
            raise CameraStalled(f"{self._label()}: {msg} while it stays connected (a stalled stream)")

    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult:
        with self._calibration_mode("on-chip"):
            try:
                table, health = self._acd().run_on_chip_calibration(ON_CHIP_JSON, int(timeout_s * 1000))
            except RuntimeError as exc:
                raise CalibrationFailed(f"on-chip calibration failed: {' '.join(str(exc).split())}") from exc
        # pyrealsense2 returns (health, 0.0): the second value is a placeholder, not a health
        return CalibrationResult("on_chip", bytes(table), (float(health[0]),),
                                 {"json": ON_CHIP_JSON, "mode": _describe(CALIBRATION_PROFILE),
                                  "timeout_ms": int(timeout_s * 1000)})

    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult:
        """Tare at `ground_truth_m`, the distance from the depth origin (not the glass) to the target."""
        gt_mm = ground_truth_m * 1000.0
        lo, hi = TARE_GROUND_TRUTH_MM
        if not lo <= gt_mm <= hi:
            raise InputError(None, f"tare ground truth {gt_mm:.1f} mm is outside {lo:g}-{hi:g} mm")
        with self._calibration_mode("tare"):
            try:
                table, health = self._acd().run_tare_calibration(gt_mm, TARE_JSON, int(timeout_s * 1000))
            except RuntimeError as exc:
                raise CalibrationFailed(f"tare calibration failed: {' '.join(str(exc).split())}") from exc
        # the SDK passes the ground truth to the firmware in whole mm (static_cast<uint32_t>(gt) * 100,
        # d400-auto-calibration.cpp run_tare_calibration): what the device used is recorded beside it
        details = {"json": TARE_JSON, "ground_truth_mm": gt_mm, "ground_truth_mm_used": float(int(gt_mm)),
                   "mode": _describe(CALIBRATION_PROFILE),
                   "timeout_ms": int(timeout_s * 1000)}
        return CalibrationResult("tare", bytes(table), (float(health[0]), float(health[1])), details)

    def set_calibration_table(self, table: bytes) -> None:
        """Make `table` active in RAM; held and set again after every start and reset while it
        differs from flash. Flash is read before the set: what `get_calibration_table` (GETINTCAL)
        returns after a RAM set is not documented, and if it were the RAM table, comparing after
        the set would drop the hold and a reset would bring the flash table back unnoticed."""
        acd = self._acd()
        try:
            flash = bytes(acd.get_calibration_table())
            acd.set_calibration_table(list(table))
        except RuntimeError as exc:
            raise CameraError(f"cannot set the calibration table of {self._label()}: {exc}") from exc
        self._held = None if bytes(table) == flash else bytes(table)
        self._table_on_device = True

    def write_calibration(self) -> None:
        """Burn the table last set to flash: it survives resets and power cycles."""
        try:
            self._acd().write_calibration()
        except RuntimeError as exc:
            raise CameraError(f"cannot write the calibration of {self._label()}: {exc}") from exc
        self._held = None
