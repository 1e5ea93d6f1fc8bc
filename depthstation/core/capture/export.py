"""Captures out into the formats the ecosystem reads: a realsense-ros-style rosbag2, a TUM RGB-D
folder (what ORB-SLAM3 and RTAB-Map read, so users make the scan study's poses with the SLAM system
they already use) and a RealSense `.db3` for the Viewer.

rosbag2: one folder per standpoint (MCAP storage, metadata version 8 so Humble plays it), the ROS 2
wrapper's topics under `/camera/camera/`, CameraInfo with every image, each stream's own stamp as
log time and header stamp, `/tf_static` and `extrinsics/depth_to_color` at the first frame,
offered transient-local.

TUM: `depth/` 16-bit PNGs at 5000 counts per metre (the TUM and RTAB-Map factor; a finer source,
e.g. 0.1 mm, keeps its own so nothing is lost), `rgb/` the image registered to the depth camera
(the left infrared imager when recorded, else the colour image resampled into the depth pixels),
`rgb.txt`, `depth.txt`, `associations.txt` (rgb first, no comments: ORB-SLAM3's reader),
`camera.json` (our reader) and an ORB-SLAM3 settings file; the trajectory SLAM writes from it is
then the depth camera's, as `evaluate scan` wants.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer

from depthstation.core.camera_model import Intrinsics, StreamInfo, pixel_grid
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture import rosmsgs
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.ros_bag import typestore
from depthstation.core.capture.rs_writer import write_realsense_recording
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.results import write_json
from depthstation.core.run_warnings import warn

TARGETS = ("rosbag2", "tum", "db3")
ROS2_NAMESPACE = "/camera/camera/"
TUM_FACTOR = 5000.0  # depth PNG counts per metre (TUM RGB-D, RTAB-Map's default)
EXTRINSICS_TYPE = "realsense2_camera_msgs/msg/Extrinsics"
_QTIME = QosTime(0, 0)
LATCHED_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                  _QTIME, _QTIME, QosLiveliness.AUTOMATIC, _QTIME, False)

FrameHook = Callable[[Recording, int], None]


def _new_dir(path: Path) -> Path:
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise InputError(path, "exists and is not empty; exports never overwrite")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _counted(rec: Recording, on_frame: FrameHook | None) -> Iterator[FrameSet]:
    for i, fs in enumerate(rec.frames()):
        yield fs
        if on_frame is not None:
            on_frame(rec, i)


# -- rosbag2 -----------------------------------------------------------------------------------
def export_rosbag2(rec: Recording, out: Path, on_frame: FrameHook | None = None) -> int:
    """One realsense-ros-style rosbag2 folder (MCAP storage); returns the depth frames written."""
    info = rec.info
    ts = typestore()
    ns = ROS2_NAMESPACE
    aligned = info.depth_aligned_to_color
    depth_image = ns + ("aligned_depth_to_color/image_raw" if aligned else "depth/image_rect_raw")
    depth_info = ns + ("aligned_depth_to_color/camera_info" if aligned else "depth/camera_info")
    depth_frame = mw.COLOR_FRAME_ID if aligned else mw.DEPTH_FRAME_ID
    color_intr = info.color_intrinsics or (info.depth_intrinsics if aligned else None)
    streams: list[tuple[str, str, str, str, Intrinsics | None, str]] = [
        ("depth", depth_image, depth_info, "16UC1", info.depth_intrinsics, depth_frame),
        ("color", ns + "color/image_raw", ns + "color/camera_info", "rgb8", color_intr, mw.COLOR_FRAME_ID),
        ("infrared", ns + "infra1/image_rect_raw", ns + "infra1/camera_info", "mono8",
         info.infrared_intrinsics, mw.INFRARED_FRAME_ID),
    ]
    n = 0
    to_mm = ros_millimetres(info.depth_units_m)
    beyond = 0
    with Writer(out, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conns: dict[str, Any] = {}

        def write(topic: str, msgtype: str, t_ns: int, data: bytes, latched: bool = False) -> None:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts,
                                                offered_qos_profiles=[LATCHED_QOS] if latched else [])
            w.write(conns[topic], t_ns, data)

        for fs in _counted(rec, on_frame):
            t = int(fs.timestamp_ns)
            if n == 0:
                _write_static(write, info, t, ts)
                if aligned and info.stereo_intrinsics is not None:  # the imager's own, as the wrapper
                    write(ns + "depth/camera_info", rosmsgs.CAMERA_INFO, t,  # publishes beside aligned depth
                          rosmsgs.camera_info_msg(info.stereo_intrinsics, t, mw.DEPTH_FRAME_ID), latched=True)
            stamps = (fs.metadata or {}).get(mw.STREAM_STAMPS_KEY) or {}
            depth = fs.depth
            if to_mm is not None and depth is not None:
                depth, lost = to_mm(depth)
                beyond += lost
            arrays = {"depth": depth, "color": fs.color, "infrared": fs.infrared}
            for kind, image_topic, info_topic, encoding, intr, frame in streams:
                a = arrays[kind]
                if a is None:
                    continue
                tk = int(stamps.get(kind, t))
                write(image_topic, rosmsgs.IMAGE, tk, rosmsgs.image_msg(a, encoding, tk, frame))
                if intr is not None:
                    write(info_topic, rosmsgs.CAMERA_INFO, tk, rosmsgs.camera_info_msg(intr, tk, frame))
            n += 1
    if to_mm is not None:
        finer = info.depth_units_m < 0.001
        warn(f"depth in units of {info.depth_units_m * 1e3:g} mm written as millimetres (16UC1 is "
             f"millimetres, REP 118){': resolution reduced to 1 mm' if finer else ''}"
             f"{f'; {beyond} pixels beyond 65.535 m written as no depth' if beyond else ''}",
             str(rec.path), "export-depth-units")
    return n


def ros_millimetres(units_m: float) -> Callable[[NDArray[np.uint16]], tuple[NDArray[np.uint16], int]] | None:
    """Depth counts -> ROS millimetres, for depth units other than 1 mm (None: already mm). Why:
    16UC1 means millimetres to every ROS tool and to our own reader; raw counts of 100 um units
    read back 10x too far. Returns the converted image and the pixels too far for 16 bits."""
    if abs(units_m - 0.001) <= 1e-12:
        return None
    k = units_m / 0.001

    def convert(counts: NDArray[np.uint16]) -> tuple[NDArray[np.uint16], int]:
        mm = np.rint(counts.astype(np.float64) * k)
        far = mm > 65535
        mm[far] = 0
        return mm.astype(np.uint16), int(np.count_nonzero(far))

    return convert


def _write_static(write: Callable[..., None], info: StreamInfo, t_ns: int, ts: Any) -> None:
    """/tf_static (the wrapper's tree) and the wrapper's depth-to-colour extrinsics topic."""
    has_color = info.color_intrinsics is not None and not info.depth_aligned_to_color
    tree = rosmsgs.realsense_tf_tree(info.depth_to_color if has_color else None, info.baseline_m)
    write("/tf_static", rosmsgs.TF_MESSAGE, t_ns, rosmsgs.tf_message(tree, t_ns), latched=True)
    if has_color:
        rot, trans = info.depth_to_color.to_librealsense()  # column-major, as the wrapper sends it
        msg = ts.types[EXTRINSICS_TYPE](rotation=np.asarray(rot, dtype=np.float64),
                                        translation=np.asarray(trans, dtype=np.float64))
        write(ROS2_NAMESPACE + "extrinsics/depth_to_color", EXTRINSICS_TYPE, t_ns,
              bytes(ts.serialize_cdr(msg, EXTRINSICS_TYPE)), latched=True)


# -- TUM RGB-D ---------------------------------------------------------------------------------
def color_in_depth(fs: FrameSet, info: StreamInfo) -> NDArray[np.uint8] | None:
    """The colour image resampled into the depth camera's pixels (nearest colour pixel of each depth
    pixel's 3-D point; black where there is no depth or the point leaves the colour image)."""
    if fs.color is None or fs.depth is None or info.color_intrinsics is None:
        return None
    if info.depth_aligned_to_color:
        return fs.color
    d, c = info.depth_intrinsics, info.color_intrinsics
    z = fs.depth.astype(np.float64) * info.depth_units_m
    u, v = pixel_grid(d)
    pts = np.stack([(u - d.ppx) / d.fx * z, (v - d.ppy) / d.fy * z, z], axis=-1).reshape(-1, 3)
    e = info.depth_to_color
    rvec, _ = cv2.Rodrigues(e.R)
    uv, _ = cv2.projectPoints(pts, rvec, e.t, c.K, c.opencv_distortion())
    uv = uv.reshape(d.height, d.width, 2).astype(np.float32)
    uv[z <= 0] = -1.0
    out = cv2.remap(fs.color, uv[..., 0], uv[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0)
    return np.asarray(out, dtype=np.uint8)


def tum_factor(depth_units_m: float) -> float:
    """Depth PNG counts per metre: TUM's 5000 when the source's counts map onto it exactly (1 mm:
    x5), else the source's own (0.1 mm: 10000), so the export loses no depth resolution."""
    k = depth_units_m * TUM_FACTOR
    if k >= 1.0 - 1e-9 and abs(k - round(k)) < 1e-9:
        return TUM_FACTOR
    return float(round(1.0 / depth_units_m))


def _tum_name(t_ns: int) -> str:
    return f"{t_ns / 1e9:.6f}"


def export_tum(rec: Recording, out: Path, on_frame: FrameHook | None = None) -> int:
    """One TUM RGB-D folder in the depth camera's frame; returns the depth frames written."""
    info = rec.info
    for sub in ("rgb", "depth"):
        (out / sub).mkdir()
    depth_lines: list[str] = []
    rgb_lines: list[str] = []
    assoc: list[str] = []
    factor = tum_factor(info.depth_units_m)
    scale = info.depth_units_m * factor
    names: set[str] = set()
    repeated = beyond = 0
    for fs in _counted(rec, on_frame):
        if fs.depth is None:
            continue
        name = _tum_name(int(fs.timestamp_ns))
        if name in names:  # one file name per time stamp: a second frame would overwrite the first
            repeated += 1
            continue
        names.add(name)
        counts = fs.depth.astype(np.float64) * scale
        far = counts >= 65535.5
        beyond += int(np.count_nonzero(far))
        png = np.where(far, 0, np.rint(counts)).astype(np.uint16)
        if not cv2.imwrite(str(out / "depth" / f"{name}.png"), png):
            raise InputError(out, "cannot write depth PNGs there")
        depth_lines.append(f"{name} depth/{name}.png")
        image = fs.infrared if fs.infrared is not None else color_in_depth(fs, info)
        if image is not None:
            bgr = image[..., ::-1] if image.ndim == 3 else image
            cv2.imwrite(str(out / "rgb" / f"{name}.png"), np.ascontiguousarray(bgr))
            rgb_lines.append(f"{name} rgb/{name}.png")
            assoc.append(f"{name} rgb/{name}.png {name} depth/{name}.png")
    header = "# {} images\n# file: '{}'\n# timestamp filename\n"
    (out / "depth.txt").write_text(header.format("depth", rec.name) + "\n".join(depth_lines) + "\n")
    if rgb_lines:
        (out / "rgb.txt").write_text(header.format("rgb", rec.name) + "\n".join(rgb_lines) + "\n")
        (out / "associations.txt").write_text("\n".join(assoc) + "\n")
    if repeated:
        warn(f"{repeated} frame(s) repeat an earlier frame's time stamp (to the microsecond TUM names "
             "its files by): left out of the TUM export", str(rec.path), "export-repeated-stamp")
    if beyond:
        warn(f"{beyond} pixels beyond {65535 / factor:.3f} m (16-bit PNG at {factor:g} counts per metre) "
             "written as no depth", str(rec.path), "export-depth-units")
    units = 1.0 / factor
    di = info.depth_intrinsics
    camera = {**di.to_dict(), "depth_units_m": units,
              "rgb": "left infrared imager" if info.infrared_intrinsics is not None
              else "colour resampled into the depth camera"}
    write_json(out / "camera.json", camera)
    (out / "orbslam3_rgbd.yaml").write_text(_orbslam3_settings(di, info, units))
    return len(depth_lines)


def _orbslam3_settings(d: Intrinsics, info: StreamInfo, units: float) -> str:
    """ORB-SLAM3 RGB-D settings (File.version 1.0) for the exported folder."""
    k = list(d.opencv_distortion()) + [0.0] * 5
    fps = round(info.fps or 30)
    return "\n".join([
        "%YAML:1.0", "# ORB-SLAM3 RGB-D settings written by depthstation (capture export --to tum)",
        'File.version: "1.0"', 'Camera.type: "PinHole"',
        f"Camera1.fx: {d.fx:.6f}", f"Camera1.fy: {d.fy:.6f}",
        f"Camera1.cx: {d.ppx:.6f}", f"Camera1.cy: {d.ppy:.6f}",
        f"Camera1.k1: {k[0]:.8f}", f"Camera1.k2: {k[1]:.8f}", f"Camera1.p1: {k[2]:.8f}",
        f"Camera1.p2: {k[3]:.8f}", f"Camera1.k3: {k[4]:.8f}",
        f"Camera.width: {d.width}", f"Camera.height: {d.height}", f"Camera.fps: {fps}",
        "Camera.RGB: 1", "Stereo.ThDepth: 40.0", f"Stereo.b: {info.baseline_m or 0.095:.6f}",
        f"RGBD.DepthMapFactor: {1.0 / units:.1f}",
        "ORBextractor.nFeatures: 1250", "ORBextractor.scaleFactor: 1.2", "ORBextractor.nLevels: 8",
        "ORBextractor.iniThFAST: 20", "ORBextractor.minThFAST: 7",
        "Viewer.KeyFrameSize: 0.05", "Viewer.KeyFrameLineWidth: 1.0", "Viewer.GraphLineWidth: 0.9",
        "Viewer.PointSize: 2.0", "Viewer.CameraSize: 0.08", "Viewer.CameraLineWidth: 3.0",
        "Viewer.ViewpointX: 0.0", "Viewer.ViewpointY: -0.7", "Viewer.ViewpointZ: -1.8",
        "Viewer.ViewpointF: 500.0",
        "",
    ])


# -- all ---------------------------------------------------------------------------------------
def export_recordings(recordings: Sequence[Recording], to: str, out: Path,
                      on_frame: FrameHook | None = None) -> list[tuple[Path, int]]:
    """Export every standpoint of `recordings` into `out` (new or empty): a folder each for rosbag2
    and TUM, a `<name>.db3` each for the RealSense Viewer. Returns (path, frames) per standpoint."""
    if to not in TARGETS:
        raise InputError(None, f"--to must be one of {', '.join(TARGETS)}, not {to!r}")
    _new_dir(Path(out))
    done: list[tuple[Path, int]] = []
    used: set[str] = set()
    for rec in recordings:
        name, k = rec.name, 2
        while name in used:
            name, k = f"{rec.name}-{k}", k + 1
        used.add(name)
        if to == "db3":
            path = Path(out) / f"{name}.db3"
            done.append((path, write_realsense_recording(path, rec.info, _counted(rec, on_frame))))
        elif to == "rosbag2":
            path = Path(out) / name  # rosbags creates the folder
            done.append((path, export_rosbag2(rec, path, on_frame)))
        else:
            path = _new_dir(Path(out) / name)
            done.append((path, export_tum(rec, path, on_frame)))
    return done
