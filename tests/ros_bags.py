"""realsense-ros-style recordings written with rosbags' own writers (not the code under test).

The layouts follow realsense-ros (ROS 2 4.x: `/<namespace>/<name>/...`, ROS 1 2.x: `/camera/...`):
`depth/image_rect_raw`, `color/image_raw`, `infra1/image_rect_raw`, their `camera_info` with every
image, `/tf_static` under `camera_link` (offered transient-local), the `extrinsics/depth_to_color`
topic where asked; images raw or through image_transport's `compressedDepth` / `compressed`.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from depthstation.core.camera_model import StreamInfo
from depthstation.core.frames import FrameSet

TF_STATIC_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                    QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
# optical frame in its body frame: the wrapper's setRPY(-pi/2, 0, -pi/2)
Q_OPTICAL = (-0.5, 0.5, -0.5, 0.5)


def _quat(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd), written here independently of the package."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
    q = np.zeros(4)
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _optical_matrix() -> np.ndarray:
    x, y, z, w = Q_OPTICAL
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class BagWriter:
    """Writes FrameSets as the realsense-ros wrapper publishes them, into any rosbags storage."""

    def __init__(self, path: Path, info: StreamInfo, *, ros: int = 2, storage: str = "mcap",
                 namespace: str = "/camera/camera/", compressed: bool = False, depth_only: bool = False,
                 extrinsics_topic: bool = False, depth_float: bool = False, frame_prefix: str = "camera",
                 color_offset_ns: int = 0, color_encoding: str = "rgb8", aligned: bool = False) -> None:
        self.info = info
        self.aligned = aligned  # depth on aligned_depth_to_color, stamped in the colour optical frame
        self.color_encoding = color_encoding
        self.ros = ros
        self.ns = namespace
        self.compressed = compressed
        self.depth_only = depth_only
        self.depth_float = depth_float
        self.prefix = frame_prefix
        self.color_offset_ns = color_offset_ns
        self.extrinsics_topic = extrinsics_topic
        if ros == 1:
            self.ts = get_typestore(Stores.ROS1_NOETIC)
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
            self.ts.register(get_types_from_msg("std_msgs/Header header\nfloat64[9] rotation\n"
                                                "float64[3] translation", "realsense2_camera/msg/Extrinsics"))
            self.ext_type = "realsense2_camera/msg/Extrinsics"
            self.writer: Any = Writer1(path)
        else:
            self.ts = get_typestore(Stores.ROS2_HUMBLE)
            self.ts.register(get_types_from_msg("float64[9] rotation\nfloat64[3] translation",
                                                "realsense2_camera_msgs/msg/Extrinsics"))
            self.ext_type = "realsense2_camera_msgs/msg/Extrinsics"
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=8, storage_plugin=plugin)
        self.conns: dict[str, Any] = {}
        self.seq = 0

    def __enter__(self) -> BagWriter:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    # -- messages ------------------------------------------------------------------------------
    def _conn(self, topic: str, msgtype: str, latched: bool = False) -> Any:
        if topic not in self.conns:
            if self.ros == 1:
                self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts,
                                                               latching=1 if latched else None)
            else:
                qos = [TF_STATIC_QOS] if latched else []
                self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts,
                                                               offered_qos_profiles=qos)
        return self.conns[topic]

    def _write(self, topic: str, msgtype: str, msg: Any, t_ns: int, latched: bool = False) -> None:
        conn = self._conn(topic, msgtype, latched)
        data = self.ts.serialize_ros1(msg, msgtype) if self.ros == 1 else self.ts.serialize_cdr(msg, msgtype)
        self.writer.write(conn, t_ns, data)

    def _header(self, t_ns: int, frame_id: str) -> Any:
        T = self.ts.types
        sec, nsec = divmod(int(t_ns), 1_000_000_000)
        extra = {"seq": self.seq} if self.ros == 1 else {}
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        return T["std_msgs/msg/Header"](**extra, stamp=stamp, frame_id=frame_id)

    def _camera_info(self, intr: Any, t_ns: int, frame_id: str) -> Any:
        T = self.ts.types
        k = np.array([intr.fx, 0, intr.ppx, 0, intr.fy, intr.ppy, 0, 0, 1], dtype=np.float64)
        p = np.array([intr.fx, 0, intr.ppx, 0, 0, intr.fy, intr.ppy, 0, 0, 0, 1, 0], dtype=np.float64)
        mats = {"D": np.asarray(intr.coeffs, dtype=np.float64), "K": k, "R": np.eye(3).ravel(), "P": p}
        if self.ros == 2:
            mats = {key.lower(): v for key, v in mats.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](header=self._header(t_ns, frame_id), height=intr.height,
                                               width=intr.width, distortion_model="plumb_bob", binning_x=0,
                                               binning_y=0, roi=roi, **mats)

    def _image(self, a: np.ndarray, encoding: str, t_ns: int, frame_id: str) -> tuple[str, Any]:
        T = self.ts.types
        a = np.ascontiguousarray(a)
        if not self.compressed:
            return "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
                header=self._header(t_ns, frame_id), height=a.shape[0], width=a.shape[1], encoding=encoding,
                is_bigendian=0, step=a.strides[0], data=a.reshape(-1).view(np.uint8))
        if encoding == "16UC1":  # compressed_depth_image_transport: 12-byte ConfigHeader + PNG of mm
            ok, png = cv2.imencode(".png", a)
            data = struct.pack("<iff", 0, 0.0, 0.0) + png.tobytes()
            fmt = "16UC1; compressedDepth png"
        elif encoding == "32FC1":  # inverse-depth quantisation, depth_max 10 m, quantization 100
            depth_max, quant = 10.0, 100.0
            qa = quant * (quant + 1.0)
            qb = 1.0 - qa / depth_max
            inv = np.zeros(a.shape, np.uint16)
            ok_px = np.isfinite(a) & (a > qa / (65535.0 - qb)) & (a < depth_max)  # what fits 16 bits
            inv[ok_px] = (qa / a[ok_px] + qb).astype(np.uint16)
            ok, png = cv2.imencode(".png", inv)
            data = struct.pack("<iff", 0, qa, qb) + png.tobytes()
            fmt = "32FC1; compressedDepth png"
        else:  # compressed_image_transport, lossless PNG so that the study sees the same pixels
            bgr = a[..., ::-1] if a.ndim == 3 else a
            ok, png = cv2.imencode(".png", np.ascontiguousarray(bgr))
            data = png.tobytes()
            fmt = f"{encoding}; png compressed {'bgr8' if a.ndim == 3 else 'mono8'}"
        assert ok
        return "sensor_msgs/msg/CompressedImage", T["sensor_msgs/msg/CompressedImage"](
            header=self._header(t_ns, frame_id), format=fmt, data=np.frombuffer(data, np.uint8))

    def _topic(self, stream: str, kind: str = "image") -> str:
        image = {"depth": "depth/image_rect_raw", "color": "color/image_raw",
                 "infra1": "infra1/image_rect_raw"}[stream]
        if stream == "depth" and self.aligned:
            image = "aligned_depth_to_color/image_raw"
            if kind == "info":
                return self.ns + "aligned_depth_to_color/camera_info"
        if kind == "info":
            return self.ns + stream + "/camera_info"
        if self.compressed:
            return self.ns + image + ("/compressedDepth" if stream == "depth" else "/compressed")
        return self.ns + image

    def write_static(self, t_ns: int) -> None:
        """/tf_static under camera_link (depth frame = link) and the extrinsics topic if asked."""
        T = self.ts.types
        p = self.prefix
        o = _optical_matrix()
        tf: list[tuple[str, str, np.ndarray]] = []

        def stream(name: str, body: np.ndarray) -> None:
            tf.append((f"{p}_link", f"{p}_{name}_frame", body))
            opt = np.eye(4)
            opt[:3, :3] = o
            tf.append((f"{p}_{name}_frame", f"{p}_{name}_optical_frame", opt))

        stream("depth", np.eye(4))
        if not self.depth_only and self.info.color_intrinsics is not None:
            e = self.info.depth_to_color.matrix
            o4 = np.eye(4)
            o4[:3, :3] = o
            stream("color", o4 @ np.linalg.inv(e) @ np.linalg.inv(o4))
        stream("infra1", np.eye(4))
        if self.info.baseline_m:
            b = np.eye(4)
            b[1, 3] = -self.info.baseline_m
            stream("infra2", b)
        stamped = []
        for parent, child, m in tf:
            x, y, z, w = _quat(m[:3, :3])
            stamped.append(T["geometry_msgs/msg/TransformStamped"](
                header=self._header(t_ns, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=float(m[0, 3]), y=float(m[1, 3]),
                                                              z=float(m[2, 3])),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))))
        self._write("/tf_static", "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=stamped),
                    t_ns, latched=True)
        if self.extrinsics_topic and not self.depth_only and self.info.color_intrinsics is not None:
            e = self.info.depth_to_color
            fields = {"rotation": np.asarray(e.R.T.ravel(), dtype=np.float64),  # column-major
                      "translation": np.asarray(e.t, dtype=np.float64)}
            if self.ros == 1:
                fields["header"] = self._header(t_ns, "depth_to_color_extrinsics")
            msg = T[self.ext_type](**fields)
            self._write(self.ns + "extrinsics/depth_to_color", self.ext_type, msg, t_ns, latched=True)

    def write_frames(self, frames: Iterable[FrameSet]) -> int:
        n = 0
        for fs in frames:
            if n == 0:
                self.write_static(fs.timestamp_ns)
            self.seq = n
            self.write_frame(fs)
            n += 1
        return n

    def write_frame(self, fs: FrameSet) -> None:
        info = self.info
        p = self.prefix
        t = fs.timestamp_ns
        assert fs.depth is not None
        depth: np.ndarray = fs.depth
        enc = "16UC1"
        if self.depth_float:
            depth = fs.depth.astype(np.float32) * np.float32(info.depth_units_m)
            depth[fs.depth == 0] = np.nan
            enc = "32FC1"
        frame = f"{p}_color_optical_frame" if self.aligned else f"{p}_depth_optical_frame"
        mt, msg = self._image(depth, enc, t, frame)
        self._write(self._topic("depth"), mt, msg, t)
        self._write(self._topic("depth", "info"), "sensor_msgs/msg/CameraInfo",
                    self._camera_info(info.depth_intrinsics, t, frame), t)
        if self.aligned and info.stereo_intrinsics is not None:  # the wrapper's depth/camera_info beside
            self._write(self.ns + "depth/camera_info", "sensor_msgs/msg/CameraInfo",
                        self._camera_info(info.stereo_intrinsics, t, f"{p}_depth_optical_frame"), t)
        if self.depth_only:
            return
        if fs.color is not None and info.color_intrinsics is not None:
            tc = t + self.color_offset_ns
            frame = f"{p}_color_optical_frame"
            color = fs.color if self.color_encoding == "rgb8" else yuyv_bt601(fs.color)
            mt, msg = self._image(color, self.color_encoding, tc, frame)
            self._write(self._topic("color"), mt, msg, tc)
            self._write(self._topic("color", "info"), "sensor_msgs/msg/CameraInfo",
                        self._camera_info(info.color_intrinsics, tc, frame), tc)
        if fs.infrared is not None and info.infrared_intrinsics is not None:
            frame = f"{p}_infra1_optical_frame"
            mt, msg = self._image(fs.infrared, "mono8", t, frame)
            self._write(self._topic("infra1"), mt, msg, t)
            self._write(self._topic("infra1", "info"), "sensor_msgs/msg/CameraInfo",
                        self._camera_info(info.infrared_intrinsics, t, frame), t)


def yuyv_bt601(rgb: np.ndarray) -> np.ndarray:
    """RGB -> YUYV as a D4xx sends it (ITU-R BT.601, video range), written here from the standard's
    equations, not with the station's encoder."""
    x = rgb.astype(np.float64)
    m = np.array([[65.481, 128.553, 24.966], [-37.797, -74.203, 112.0], [112.0, -93.786, -18.214]]) / 255
    ycc = x @ m.T + np.array([16.0, 128.0, 128.0])
    pair = 0.5 * (ycc[:, 0::2, 1:] + ycc[:, 1::2, 1:])  # chroma of each pixel pair
    out = np.empty((*rgb.shape[:2], 2), np.float64)
    out[..., 0] = ycc[..., 0]
    out[:, 0::2, 1] = pair[..., 0]
    out[:, 1::2, 1] = pair[..., 1]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def write_bag(path: Path, info: StreamInfo, frames: Iterable[FrameSet], **kwargs: Any) -> int:
    """Write a whole realsense-ros-style recording; returns the number of depth frames."""
    with BagWriter(path, info, **kwargs) as w:
        return w.write_frames(frames)


def rewrite(src: Path, dst: Path, storage: str = "mcap") -> Path:
    """Copy every message of a recording into a new rosbag2 with rosbags (what `ros2 bag convert`
    or any ROS tool leaves: topics and messages, none of the MCAP's metadata records)."""
    from rosbags.highlevel import AnyReader

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with AnyReader([src], default_typestore=ts) as reader, \
            Writer2(dst, version=8, storage_plugin=plugin) as w:
        conns = {}
        for c in reader.connections:
            qos = list(getattr(c.ext, "offered_qos_profiles", []) or [])
            conns[c.id] = w.add_connection(c.topic, c.msgtype, typestore=ts, offered_qos_profiles=qos)
        for c, t, raw in reader.messages():
            w.write(conns[c.id], t, raw)
    return dst
