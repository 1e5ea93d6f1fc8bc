"""ROS 2 message building and parsing (cdr through rosbags' typestore), shared by writer and readers.

rosbags' generated serializers copy the image buffer once and deserialize it zero-copy, which is
what lets the writer keep up with 30 fps and the reader exceed 300 depth frames/s.
"""

from __future__ import annotations

import struct
from functools import cache, lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.typesys import Stores, get_typestore

from depthstation.core.camera_model import Extrinsics, Intrinsics, model_name
from depthstation.core.capture import yuv
from depthstation.core.geometry import matrix_to_quaternion, quaternion_to_matrix

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TEMPERATURE = "sensor_msgs/msg/Temperature"
STRING = "std_msgs/msg/String"

# librealsense distortion model (our Intrinsics.model) -> ROS CameraInfo distortion_model.
_TO_ROS_MODEL = {
    "none": "plumb_bob",
    "brown_conrady": "plumb_bob",
    "modified_brown_conrady": "plumb_bob",
    "inverse_brown_conrady": "plumb_bob",
    "kannala_brandt4": "equidistant",
    "ftheta": "equidistant",
}


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The ROS 2 Humble typestore (has every message type the format uses)."""

    return get_typestore(Stores.ROS2_HUMBLE)


@cache
def msgdef(msgtype: str) -> str:
    """ros2msg schema text (with dependencies) as MCAP's ros2 profile wants it."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return str(text)


def serialize(msg: Any, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    return typestore().deserialize_cdr(data, msgtype)


def _header(t_ns: int, frame_id: str) -> Any:
    ts = typestore().types
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return ts["std_msgs/msg/Header"](
        stamp=ts["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_msg_parts(array: NDArray[Any], encoding: str, t_ns: int,
                    frame_id: str) -> tuple[bytes, memoryview]:
    """sensor_msgs/Image as (CDR prefix, the pixels' own buffer): their concatenation is
    `image_msg(...)`, without copying the pixels (the writer hands both to the file).

    The prefix is the message serialized with empty data, its final sequence length (a uint32,
    the last field) replaced by the pixels' byte count: uint8 sequences need no alignment.
    """
    a = np.ascontiguousarray(array)
    h, w = a.shape[:2]
    msg = typestore().types[IMAGE](
        header=_header(t_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=a.strides[0],
        data=np.empty(0, np.uint8),
    )
    empty = serialize(msg, IMAGE)
    return empty[:-4] + struct.pack("<I", a.nbytes), a.reshape(-1).view(np.uint8).data


def image_msg(array: NDArray[Any], encoding: str, t_ns: int, frame_id: str) -> bytes:
    """Serialize an HxW or HxWxC array as sensor_msgs/Image (little endian, tight rows)."""
    prefix, pixels = image_msg_parts(array, encoding, t_ns, frame_id)
    return prefix + pixels.tobytes()


_ENCODINGS: dict[str, tuple[Any, int]] = {
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
    "mono16": (np.uint16, 1),
    "z16": (np.uint16, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "y8": (np.uint8, 1),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    **{name: (np.uint8, 2) for name in yuv.ALIASES},  # YUYV / UYVY 4:2:2, decoded to RGB
}


def image_array(msg: Any) -> NDArray[Any]:
    """The pixels of a deserialized sensor_msgs/Image as an array (RGB order for colour)."""
    enc = str(msg.encoding)
    if enc not in _ENCODINGS:
        raise ValueError(f"unsupported image encoding {enc!r}")
    dtype, channels = _ENCODINGS[enc]
    itemsize = np.dtype(dtype).itemsize
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    raw = np.asarray(msg.data, dtype=np.uint8)
    row = w * channels * itemsize
    if step < row or raw.size < h * step:  # a cut or mislabelled message: say its sizes, not numpy's
        raise ValueError(f"{enc} image of {w}x{h} needs {h} rows of {max(step, row)} bytes "
                         f"({h * max(step, row)} bytes; step {step}), its data holds {raw.size}")
    rows = raw[: h * step].reshape(h, step)[:, :row]
    a = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    a = a.astype(dtype, copy=False)
    a = a.reshape(h, w, channels) if channels > 1 else a.reshape(h, w)
    if enc in ("bgr8", "bgra8"):
        a = a[..., [2, 1, 0]]
    elif enc == "rgba8":
        a = a[..., :3]
    elif enc in yuv.ALIASES:
        return yuv.yuv422_to_rgb(a, enc)
    return np.ascontiguousarray(a)


_CDEPTH_HEADER = struct.Struct("<iff")  # compressed_depth_image_transport ConfigHeader


def compressed_image_array(msg: Any) -> NDArray[Any]:
    """The pixels of a sensor_msgs/CompressedImage as `image_array` gives them for an Image.

    `format` is '<encoding>; compressedDepth [png]' (a 12-byte header, then a PNG of 16-bit
    millimetres or, for 32FC1, of quantised inverse depth) or '<encoding>; jpeg|png compressed
    bgr8|mono8' (OpenCV decodes to BGR; converted back to what the encoding names). A format with
    no ';' is an older recorder's: a plain JPEG/PNG in BGR order.
    """
    fmt = str(msg.format)
    enc, _, rest = fmt.partition(";")
    enc = enc.strip()
    data = np.asarray(msg.data, dtype=np.uint8)
    if "compressedDepth" in fmt:
        if "rvl" in rest:
            raise ValueError("compressedDepth RVL is not supported (record with format png)")
        _, depth_a, depth_b = _CDEPTH_HEADER.unpack_from(data.tobytes()[: _CDEPTH_HEADER.size])
        img = cv2.imdecode(data[_CDEPTH_HEADER.size :], cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"cannot decode compressed depth ({fmt})")
        if enc == "32FC1":  # inverse-depth quantisation: z = A / (q - B); 0 = no depth
            out = np.full(img.shape, np.nan, np.float32)
            nz = img > 0
            out[nz] = np.float32(depth_a) / (img[nz].astype(np.float32) - np.float32(depth_b))
            return out
        return np.ascontiguousarray(img.astype(np.uint16, copy=False))
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot decode compressed image ({fmt})")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim == 3 and enc in ("mono8", "8UC1", "y8", "mono16"):
        img = img[..., 0]
    elif img.ndim == 3 and not enc.startswith("bgr"):
        img = img[..., [2, 1, 0]]  # OpenCV decoded BGR; everything but bgr8 is delivered as RGB
    return np.ascontiguousarray(img)


def depth_to_units(depth: NDArray[Any], depth_units_m: float) -> NDArray[np.uint16]:
    """z16 counts of a depth image: 16-bit images as they are, float metres (32FC1, NaN or 0 =
    none) rounded to `depth_units_m` (0 where invalid or beyond the 16-bit range)."""
    if depth.dtype == np.uint16:
        return depth
    z = np.asarray(depth, dtype=np.float64) / depth_units_m
    ok = np.isfinite(z) & (z > 0) & (z < 65535.5)
    out = np.zeros(z.shape, np.uint16)
    out[ok] = np.rint(z[ok]).astype(np.uint16)
    return out


def camera_info_msg(intr: Intrinsics, t_ns: int, frame_id: str) -> bytes:
    """CameraInfo with D, K, R = I, P = [K|0]; the exact librealsense model lives in metadata."""
    ts = typestore().types
    k = intr.K.ravel()
    p = np.zeros(12)
    p[[0, 1, 2, 4, 5, 6, 10]] = [intr.fx, 0.0, intr.ppx, 0.0, intr.fy, intr.ppy, 1.0]
    coeffs = np.asarray(intr.coeffs if intr.model != "none" else [0.0] * 5, dtype=np.float64)
    msg = ts[CAMERA_INFO](
        header=_header(t_ns, frame_id),
        height=intr.height,
        width=intr.width,
        distortion_model=_TO_ROS_MODEL.get(intr.model, intr.model),
        d=coeffs,
        k=k,
        r=np.eye(3).ravel(),
        p=p,
        binning_x=0,
        binning_y=0,
        roi=ts["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return serialize(msg, CAMERA_INFO)


def intrinsics_from_camera_info(msg: Any, model: str | None = None, rectified: bool = False) -> Intrinsics:
    """Intrinsics from a ROS 1 or ROS 2 CameraInfo (field names K/k, D/d, P/p differ by version).

    `rectified`: the images are image_proc's rectified ones (`image_rect*`), whose camera is P's
    left 3x3 without the distortion D (which describes the raw images): REP 104.
    """
    k = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=np.float64)
    d = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, dtype=np.float64)
    if rectified:
        p = np.asarray(getattr(msg, "p", None) if hasattr(msg, "p") else msg.P, dtype=np.float64)
        cam = p[[0, 5, 2, 6]] if p.size == 12 and p[0] > 0 and p[5] > 0 else k[[0, 4, 2, 5]]
        return Intrinsics(int(msg.width), int(msg.height), float(cam[0]), float(cam[1]), float(cam[2]),
                          float(cam[3]))
    name = model_name(model if model is not None else str(msg.distortion_model))
    coeffs = tuple(float(x) for x in d) if len(d) else (0.0,) * 5
    return Intrinsics(
        int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]), name, coeffs
    )


def is_rectified_topic(image_topic: str) -> bool:
    """image_proc's rectified outputs ('.../image_rect', '.../image_rect_color'). realsense-ros'
    '.../image_rect_raw' are rectified on the device and carry a zero D: read as they are."""
    return image_topic.rstrip("/").rsplit("/", 1)[-1] in ("image_rect", "image_rect_color")


def transform(ext: Extrinsics) -> Any:
    """geometry_msgs/Transform of a rigid transform."""
    ts = typestore().types
    q = matrix_to_quaternion(ext.R)
    t = ext.t
    return ts["geometry_msgs/msg/Transform"](
        translation=ts["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=ts["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )


def extrinsics_from_transform(tf: Any) -> Extrinsics:
    """The rigid transform a geometry_msgs/Transform describes (p_parent = R p_child + t)."""
    q = np.array([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(q)
    m[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    return Extrinsics.from_matrix(m)


def tf_static_msg(parent: str, child: str, child_to_parent: Extrinsics, t_ns: int = 0) -> bytes:
    """/tf_static with one transform: ROS convention, the pose of `child` in `parent`."""
    return tf_message([(parent, child, child_to_parent)], t_ns)


def tf_message(transforms: list[tuple[str, str, Extrinsics]], t_ns: int) -> bytes:
    """A TFMessage of (parent, child, pose of the child in the parent) transforms stamped `t_ns`."""
    ts = typestore().types
    stamped = [
        ts["geometry_msgs/msg/TransformStamped"](
            header=_header(t_ns, parent), child_frame_id=child, transform=transform(pose)
        )
        for parent, child, pose in transforms
    ]
    return serialize(ts[TF_MESSAGE](transforms=stamped), TF_MESSAGE)


# Optical frame (x right, y down, z forward) in its body frame (x forward, y left, z up): the
# rotation realsense-ros publishes as setRPY(-pi/2, 0, -pi/2), q = (-0.5, 0.5, -0.5, 0.5).
OPTICAL_IN_BODY = Extrinsics((0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0))


def realsense_tf_tree(depth_to_color: Extrinsics | None, baseline_m: float | None,
                      prefix: str = "camera") -> list[tuple[str, str, Extrinsics]]:
    """The static TF tree of the realsense-ros wrapper: `<prefix>_link` (= the depth frame) with
    `<s>_frame` and `<s>_optical_frame` per stream: depth, colour (from the depth-to-colour
    extrinsics), infra1 (the depth imager) and infra2 (the baseline to its right)."""
    o = OPTICAL_IN_BODY
    link = f"{prefix}_link"
    out: list[tuple[str, str, Extrinsics]] = []

    def stream(name: str, body: Extrinsics) -> None:
        out.append((link, f"{prefix}_{name}_frame", body))
        out.append((f"{prefix}_{name}_frame", f"{prefix}_{name}_optical_frame", o))

    stream("depth", Extrinsics())
    if depth_to_color is not None:
        # pose of the colour optical frame in the link: O inv(E); its body frame: O inv(E) inv(O)
        body = o.matrix @ depth_to_color.inverse().matrix @ o.inverse().matrix
        stream("color", Extrinsics.from_matrix(body))
    stream("infra1", Extrinsics())
    if baseline_m:
        stream("infra2", Extrinsics(translation=(0.0, -float(baseline_m), 0.0)))
    return out


def temperature_msg(t_ns: int, sensor: str, celsius: float) -> bytes:
    msg = typestore().types[TEMPERATURE](
        header=_header(t_ns, sensor), temperature=float(celsius), variance=0.0
    )
    return serialize(msg, TEMPERATURE)


def string_msg(text: str) -> bytes:
    return serialize(typestore().types[STRING](data=text), STRING)
