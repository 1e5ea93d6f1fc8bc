"""Importing a realsense-ros recording at full size (run by hand, not by pytest).

    .venv/bin/python benchmarks/bench_ros_import.py [--frames 150] [--storage mcap|sqlite3|both]

Writes a 150-frame 1280x720 `ros2 bag record` of the realsense-ros wrapper with rosbags' own
writer (depth 16UC1 + colour rgb8, CameraInfo with every image, /tf_static), then times, in one
run: reading its frame sets through the station's ROS reader (what `capture import`, `evaluate`
and `explain` do first), `capture import` as a whole (read + write our MCAP) uncompressed and with
lz4 chunks (the command's default), and, as the baseline, reading the same frames from our own
MCAP. Goal: >= 300 frames/s for the import.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from depthstation.core.capture.importer import import_recordings
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.sample_recordings import sample_info

W, H = 1280, 720
T0 = 1_700_000_000_000_000_000
LATCHED = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
              QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


def scene(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane with noise and holes, a textured colour image (compresses like real data)."""
    rng = np.random.default_rng(k)
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    z_mm = 1500 + 0.6 * (u - W / 2) + 0.2 * v + rng.normal(0, 4, (H, W))
    depth = np.clip(z_mm, 0, 65535).astype(np.uint16)
    depth[rng.random((H, W)) < 0.03] = 0
    color = np.empty((H, W, 3), np.uint8)
    color[..., 0] = ((u // 40 + v // 40 + k) % 2 * 200).astype(np.uint8)
    color[..., 1] = color[..., 0]
    color[..., 2] = (v / H * 255).astype(np.uint8)
    return depth, color


def write_wrapper_bag(path: Path, frames: int, storage: str) -> Path:
    """What `ros2 bag record` of realsense2_camera (ROS 2, default namespace) leaves."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    info = sample_info(W, H)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    ns = "/camera/camera/"
    images = [scene(k) for k in range(8)]

    def header(t: int, frame: str) -> object:
        stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def cam_info(intr: object, t: int, frame: str) -> object:
        i = intr  # type: ignore[assignment]
        k = np.array([i.fx, 0, i.ppx, 0, i.fy, i.ppy, 0, 0, 1.0])  # type: ignore[attr-defined]
        p = np.array([i.fx, 0, i.ppx, 0, 0, i.fy, i.ppy, 0, 0, 0, 1.0, 0])  # type: ignore[attr-defined]
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](header=header(t, frame), height=H, width=W,
                                               distortion_model="plumb_bob", d=np.zeros(5), k=k,
                                               r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0, roi=roi)

    with Writer(path, version=8, storage_plugin=plugin) as w:
        image, cinfo = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
        c = {name: w.add_connection(ns + name, typ, typestore=ts) for name, typ in (
            ("depth/image_rect_raw", image), ("depth/camera_info", cinfo),
            ("color/image_raw", image), ("color/camera_info", cinfo))}
        tf = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts,
                              offered_qos_profiles=[LATCHED])
        def transform(parent: str, child: str, y: float, q: tuple[float, ...]) -> object:
            return T["geometry_msgs/msg/TransformStamped"](
                header=header(T0, parent), child_frame_id=child, transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=y, z=0.0),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))

        tree = [transform("camera_link", f"camera_{s}_frame", -0.059 if s == "color" else 0.0, (0, 0, 0, 1.0))
                for s in ("depth", "color")]
        tree += [transform(f"camera_{s}_frame", f"camera_{s}_optical_frame", 0.0, (-0.5, 0.5, -0.5, 0.5))
                 for s in ("depth", "color")]
        msg = T["tf2_msgs/msg/TFMessage"](transforms=tree)
        w.write(tf, T0, ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
        for n in range(frames):
            t = T0 + n * 33_333_333
            depth, color = images[n % len(images)]
            for kind, a, enc, intr in (("depth", depth, "16UC1", info.depth_intrinsics),
                                       ("color", color, "rgb8", info.color_intrinsics)):
                frame = f"camera_{kind}_optical_frame"
                img = T[image](header=header(t, frame), height=H, width=W, encoding=enc, is_bigendian=0,
                               step=a.strides[0], data=a.reshape(-1).view(np.uint8))
                topic = "depth/image_rect_raw" if kind == "depth" else "color/image_raw"
                w.write(c[topic], t, ts.serialize_cdr(img, image))
                w.write(c[f"{kind}/camera_info"], t, ts.serialize_cdr(cam_info(intr, t, frame), cinfo))
    return path


def timed_read(path: Path) -> tuple[int, float]:
    t = time.perf_counter()
    rec = open_recording(path)
    n = 0
    for fs in rec.frames():
        assert fs.depth is not None and fs.color is not None
        n += 1
    return n, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--storage", default="both", choices=["mcap", "sqlite3", "both"])
    ap.add_argument("--repeat", type=int, default=3, help="best of N (the machine is shared)")
    ap.add_argument("--dir", type=Path, default=None, help="where to write (default: a temporary folder)")
    args = ap.parse_args()
    storages = ["mcap", "sqlite3"] if args.storage == "both" else [args.storage]
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        for storage in storages:
            bag = write_wrapper_bag(root / f"bag_{storage}", args.frames, storage)
            size = sum(p.stat().st_size for p in bag.iterdir()) / 1e9
            reads: list[tuple[int, float]] = []
            imports: dict[str, list[float]] = {"lz4": [], "none": []}  # the uncompressed one is read last
            ours_path = None
            for k in range(args.repeat):
                reads.append(timed_read(bag))
                for comp, times in imports.items():
                    t = time.perf_counter()
                    out = root / f"import_{storage}_{comp}_{k}"
                    session = import_recordings([bag], out, compression=comp)
                    times.append(time.perf_counter() - t)
                    if ours_path is not None:  # one import kept for the reader; the machine's
                        shutil.rmtree(ours_path.parent)  # state stays that of the first run
                    ours_path = session.dir / session.standpoints[0]["file"]
            assert ours_path is not None
            ours = [timed_read(ours_path) for _ in range(args.repeat)]
            shutil.rmtree(ours_path.parent)
            shutil.rmtree(bag)
            n, r = min(reads, key=lambda x: x[1])
            i, z = min(imports["none"]), min(imports["lz4"])
            _, o = min(ours, key=lambda x: x[1])
            print(f"[{storage}] {n} frames of {W}x{H} depth + colour ({size:.2f} GB), best of {args.repeat}:")
            print(f"  ROS reader (open + all frame sets): {n / r:6.0f} frames/s  ({r:.2f} s)")
            print(f"  capture import (read + write MCAP): {n / i:6.0f} frames/s  ({i:.2f} s)")
            print(f"  the same with lz4 chunks:           {n / z:6.0f} frames/s  ({z:.2f} s)")
            print(f"  our MCAP reader, same frames:       {n / o:6.0f} frames/s  ({o:.2f} s)  "
                  f"ROS reader / ours = {o / r:.2f}")
            print(f"  goal >= 300 frames/s: reader {n / r >= 300}, import {n / i >= 300}, lz4 {n / z >= 300}")


if __name__ == "__main__":
    main()
