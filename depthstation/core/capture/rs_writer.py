"""Write RealSense recordings with librealsense's own recorder (software_device + rs.recorder).

Used by the simulator for `.db3` output and by tests to make fixtures the way a real device would:
what pyrealsense2 plays back and what the RealSense Viewer opens. SDK 2.59 writes only the ROS 2
`.db3` layout (file version 4); a `.bag` path is refused with a clear message.
"""

from __future__ import annotations

import gc
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.capture.realsense_bag import open_realsense
from depthstation.core.device import realsense
from depthstation.core.errors import CaptureError, InputError
from depthstation.core.frames import FrameSet

_DEVICE_INFO = {
    "name": "name",
    "serial_number": "serial_number",
    "firmware_version": "firmware_version",
    "product_id": "product_id",
    "product_line": "product_line",
    "usb_type_descriptor": "usb_type_descriptor",
    "recommended_firmware_version": "recommended_firmware_version",
    "physical_port": "physical_port",
}


def _rs_intrinsics(rs: Any, intr: Intrinsics) -> Any:
    i = rs.intrinsics()
    i.width, i.height = intr.width, intr.height
    i.fx, i.fy, i.ppx, i.ppy = intr.fx, intr.fy, intr.ppx, intr.ppy
    i.model = getattr(rs.distortion, intr.model, rs.distortion.none)
    i.coeffs = [float(c) for c in (list(intr.coeffs) + [0.0] * 5)[:5]]
    return i


def _video_stream(rs: Any, kind: str, uid: int, intr: Intrinsics, fps: int) -> Any:
    fmt, bpp, stype, index = {
        "depth": (rs.format.z16, 2, rs.stream.depth, 0),
        "color": (rs.format.rgb8, 3, rs.stream.color, 0),
        "infrared": (rs.format.y8, 1, rs.stream.infrared, 1),
    }[kind]
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = stype, index, uid
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = intr.width, intr.height, fps, bpp, fmt
    vs.intrinsics = _rs_intrinsics(rs, intr)
    return vs


def write_realsense_recording(path: Path, info: StreamInfo, frames: Iterable[FrameSet]) -> int:
    """Record `frames` as a RealSense `.db3`; returns the number of depth frames written."""
    rs = realsense()

    path = Path(path)
    if path.suffix.lower() != ".db3":
        raise InputError(path, "librealsense 2.59 records only .db3 (ROS 2); use a .db3 path")
    if path.exists():
        raise InputError(path, "exists already; captures are never overwritten")
    if not path.parent.is_dir():
        raise InputError(path, "its folder does not exist")
    fps = round(info.fps or 30)
    dev = rs.software_device()
    for key, value in info.device.items():
        if key in _DEVICE_INFO and value is not None:
            dev.register_info(getattr(rs.camera_info, _DEVICE_INFO[key]), str(value))
    if "name" not in info.device:
        dev.register_info(rs.camera_info.name, "depthstation software device")
    depth_sensor = dev.add_sensor("Stereo Module")
    profiles: dict[str, Any] = {}
    sensors: dict[str, Any] = {"depth": depth_sensor}
    profiles["depth"] = depth_sensor.add_video_stream(
        _video_stream(rs, "depth", 0, info.depth_intrinsics, fps), True
    )
    depth_sensor.add_read_only_option(rs.option.depth_units, float(info.depth_units_m))
    if info.baseline_m is not None:
        depth_sensor.add_read_only_option(rs.option.stereo_baseline, float(info.baseline_m) * 1000.0)
    if info.infrared_intrinsics is not None:
        profiles["infrared"] = depth_sensor.add_video_stream(
            _video_stream(rs, "infrared", 2, info.infrared_intrinsics, fps)
        )
        sensors["infrared"] = depth_sensor
    if info.color_intrinsics is not None:
        color_sensor = dev.add_sensor("RGB Camera")
        profiles["color"] = color_sensor.add_video_stream(
            _video_stream(rs, "color", 1, info.color_intrinsics, fps), True
        )
        sensors["color"] = color_sensor
        rot, trans = info.depth_to_color.to_librealsense()
        ext = rs.extrinsics()
        ext.rotation, ext.translation = rot, trans
        profiles["depth"].register_extrinsics_to(profiles["color"], ext)
    if "infrared" in profiles:
        ident = rs.extrinsics()
        ident.rotation, ident.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
        profiles["depth"].register_extrinsics_to(profiles["infrared"], ident)

    recorder = rs.recorder(str(path), dev)
    depth_profiles = [profiles[k] for k in ("depth", "infrared") if k in profiles]
    depth_sensor.open(depth_profiles)
    depth_sensor.start(lambda f: None)
    if "color" in profiles:
        sensors["color"].open(profiles["color"])
        sensors["color"].start(lambda f: None)
    keep: list[Any] = []  # the pixel buffers must outlive the recorder's use of them
    n = 0
    try:
        for fs in frames:
            ts_ms = fs.timestamp_ns / 1e6
            for kind, arr in (("depth", fs.depth), ("infrared", fs.infrared), ("color", fs.color)):
                if arr is None or kind not in profiles:
                    continue
                a = np.ascontiguousarray(arr)
                keep.append(a)
                f = rs.software_video_frame()
                f.pixels = a
                f.stride = a.strides[0]
                f.bpp = a.itemsize * (a.shape[2] if a.ndim == 3 else 1)
                f.timestamp = ts_ms
                f.domain = rs.timestamp_domain.system_time
                f.frame_number = int(fs.index)
                f.profile = profiles[kind].as_video_stream_profile()
                if kind == "depth":
                    f.depth_units = float(info.depth_units_m)
                sensors[kind].on_video_frame(f)
            n += fs.depth is not None
            if len(keep) > 64:
                keep = keep[-16:]
    except RuntimeError as exc:
        raise CaptureError(f"{path}: librealsense recorder failed: {exc}") from exc
    finally:
        for s in {id(s): s for s in sensors.values()}.values():
            s.stop()
            s.close()
        del recorder
        gc.collect()
    return _check_written(path, n)


def _check_written(path: Path, n: int) -> int:
    """The recorder reports no write error (a full disk loses frames silently): read the file back
    and count its depth frames."""
    try:
        written = open_realsense(path).stream_counts.get("depth", 0)
    except InputError as exc:
        raise CaptureError(f"{path}: the librealsense recorder left no readable file ({exc.problem}); "
                           "is the disk full?") from exc
    except Exception as exc:  # rosbags on a torn sqlite file
        raise CaptureError(f"{path}: the librealsense recorder left no readable file "
                           f"({type(exc).__name__}: {exc}); is the disk full?") from exc
    if written != n:
        raise CaptureError(f"{path}: the librealsense recorder wrote {written} of {n} depth frames; "
                           "is the disk full?")
    return n
