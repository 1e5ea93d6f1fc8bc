"""A ChArUco standpoint seen through a real lens, written with numpy and OpenCV only.

Independent of the code under test (no depthstation import): the board's pose, OpenCV's
k1 k2 p1 p2 k3 lens inverted by its own fixed-point iteration (checked to 1e-10), depth by
ray-plane intersection on each pixel's true ray, and the truth computed from those rays. The
writers give the shapes users bring: a PNG folder with camera.json, and a ROS 2 bag in
realsense-ros layout written with rosbags.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

D455_COLOUR_LENS = (-0.0557, 0.0668, -0.0004, 0.0007, -0.0214)  # a D455 colour camera's, as reported
BOARD = {"type": "charuco", "squares_x": 7, "squares_y": 5, "square_length_m": 0.075,
         "marker_length_m": 0.05625, "dictionary": "DICT_4X4_50"}


def rays(k: NDArray[np.float64], dist: NDArray[np.float64], w: int, h: int,
         offset: tuple[float, float] = (0.0, 0.0)) -> NDArray[np.float64]:
    """h x w x 3 rays (z = 1) of the pixel centres shifted by `offset`, through the lens (OpenCV's
    k1 k2 p1 p2 k3 [k4 k5 k6])."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xd = (u + offset[0] - k[0, 2]) / k[0, 0]
    yd = (v + offset[1] - k[1, 2]) / k[1, 1]
    x, y = xd.copy(), yd.copy()
    k1, k2, p1, p2, k3, k4, k5, k6 = (*dist, 0.0, 0.0, 0.0)[:8]

    def radial(r2: NDArray[np.float64]) -> NDArray[np.float64]:  # OpenCV's rational model (k4-k6 = 0: 5)
        return (1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) / (1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3)

    for _ in range(200):
        r2 = x * x + y * y
        rad = radial(r2)
        x_new = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / rad
        y_new = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / rad
        step = max(np.abs(x_new - x).max(), np.abs(y_new - y).max())
        x, y = x_new, y_new
        if step < 1e-15:
            break
    r2 = x * x + y * y
    rad = radial(r2)
    assert np.abs(x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd).max() < 1e-10
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def render(out: Path, *, lens: tuple[float, ...] = D455_COLOUR_LENS, width: int = 640, height: int = 360,
           focal_px: float = 320.0, distance_m: float = 1.0, inclination_deg: float = 50.0,
           shift_m: tuple[float, float] = (0.5, 0.15), frames: int = 3, noise_m: float = 0.001,
           units_m: float = 0.001, seed: int = 0) -> dict[str, Any]:
    """Colour and depth aligned to colour (one camera) as `out/sp/frameK_{color,depth}.png` plus
    `out/board.json`; returns the truth and the camera for the writers."""
    rng = np.random.default_rng(seed)
    k = np.array([[focal_px, 0, (width - 1) / 2], [0, focal_px, (height - 1) / 2], [0, 0, 1.0]])
    dist = np.asarray(lens, dtype=np.float64)
    sq, nx, ny = BOARD["square_length_m"], BOARD["squares_x"], BOARD["squares_y"]
    bw, bh = nx * sq, ny * sq
    cb = cv2.aruco.CharucoBoard((nx, ny), sq, BOARD["marker_length_m"],
                                cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    pps = 120
    tex = np.asarray(cb.generateImage((nx * pps, ny * pps), marginSize=0, borderBits=1), dtype=np.float32)
    th = np.radians(inclination_deg)
    r = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
    t = np.array([shift_m[0], shift_m[1], distance_m]) - r @ np.array([bw / 2, bh / 2, 0])
    n = r[:, 2]

    def hit(rr: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        s = (n @ t) / (rr @ n)
        return s, (rr * s[..., None] - t) @ r

    grey = np.zeros((height, width), np.float32)
    for ox in (-0.25, 0.25):  # 2 x 2 samples per pixel
        for oy in (-0.25, 0.25):
            _, loc = hit(rays(k, dist, width, height, (ox, oy)))
            near = _near(loc, bw, bh)
            img = cv2.remap(tex, (loc[..., 0] / sq * pps - 0.5).astype(np.float32),
                            (loc[..., 1] / sq * pps - 0.5).astype(np.float32), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=255)
            grey += np.where(near, img, 110.0) / 4
    grey = 30 + grey / 255.0 * 190
    rr = rays(k, dist, width, height)
    z_board, loc = hit(rr)
    near = _near(loc, bw, bh)
    z_true = np.where(near & (z_board > 0), z_board, distance_m + 0.4)  # a wall behind
    (out / "sp").mkdir(parents=True, exist_ok=True)
    on = (loc[..., 0] > 0.01) & (loc[..., 0] < bw - 0.01) & (loc[..., 1] > 0.01) & (loc[..., 1] < bh - 0.01)
    accuracy, noise = [], []
    counts = []
    for i in range(frames):
        c = np.clip(grey + rng.normal(0, 2.0, grey.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(out / "sp" / f"frame{i}_color.png"), np.repeat(c[..., None], 3, axis=2))
        z = z_true + rng.normal(0, noise_m, z_true.shape)
        cnt = np.clip(np.round(z / units_m), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(out / "sp" / f"frame{i}_depth.png"), cnt)
        counts.append(cnt)
        p = rr[on] * (cnt[on] * units_m)[:, None]
        accuracy.append(float(np.mean(p @ n - n @ t)))
        noise.append(float(np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(p))))
    (out / "board.json").write_text(json.dumps(BOARD))
    centre = r @ np.array([bw / 2, bh / 2, 0]) + t
    return {"distance_m": float(centre[2]), "accuracy_m": float(np.mean(accuracy)),
            "noise_m": float(np.mean(noise)), "k": k, "lens": dist, "units_m": units_m,
            "counts": counts, "width": width, "height": height}


def _near(loc: NDArray[np.float64], bw: float, bh: float) -> NDArray[np.bool_]:
    """Board-plane points on the plate (the board and its 3 cm white margin)."""
    x, y = loc[..., 0], loc[..., 1]
    return (x > -0.03) & (x < bw + 0.03) & (y > -0.03) & (y < bh + 0.03)


def _info_topic(image_topic: str) -> str:
    return image_topic.rsplit("/", 1)[0] + "/camera_info"


def write_camera_json(out: Path, truth: dict[str, Any], **colour_keys: Any) -> None:
    """camera.json of an aligned set; `colour_keys` replace or add keys of its colour camera
    (`model=None` leaves the model out)."""
    k = truth["k"]
    colour: dict[str, Any] = {"width": truth["width"], "height": truth["height"], "fx": k[0, 0],
                              "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2],
                              "distortion": list(truth["lens"]), "model": "brown_conrady"}
    colour.update(colour_keys)
    colour = {key: value for key, value in colour.items() if value is not None}
    cam = {"depth_units_m": truth["units_m"], "depth_aligned_to_color": True, "color": colour,
           "stereo_baseline_m": 0.095}
    (out / "camera.json").write_text(json.dumps(cam, default=float))


def write_ros2_bag(src: Path, bag: Path, truth: dict[str, Any], *, encoding: str = "16UC1",
                   colour_topic: str = "/camera/camera/color/image_raw",
                   depth_topic: str = "/camera/camera/aligned_depth_to_color/image_raw",
                   distortion_model: str = "plumb_bob", d: tuple[float, ...] | None = None,
                   k_info: NDArray[np.float64] | None = None) -> None:
    """The rendered frames as a realsense-ros ROS 2 bag (rosbags' writer): colour rgb8, depth
    16UC1 millimetres or 32FC1 metres, one CameraInfo per image topic (K, D, P = [K'|0] with K'
    the rendered camera; `k_info`: another K, the raw camera of rectified images)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    image, info_t = ts.types["sensor_msgs/msg/Image"], ts.types["sensor_msgs/msg/CameraInfo"]
    header_t, time_t = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"]
    k = truth["k"]
    coeffs = np.asarray(d if d is not None else truth["lens"], dtype=np.float64)
    p = np.array([k[0, 0], 0, k[0, 2], 0, 0, k[1, 1], k[1, 2], 0, 0, 0, 1, 0.0])
    frame_id = "camera_color_optical_frame"

    def header(t_ns: int) -> Any:
        return header_t(stamp=time_t(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame_id)

    def info(t_ns: int) -> Any:
        return info_t(header=header(t_ns), height=truth["height"], width=truth["width"],
                      distortion_model=distortion_model, d=coeffs,
                      k=(k if k_info is None else k_info).ravel(),
                      r=np.eye(3).ravel(), p=p,
                      binning_x=0, binning_y=0,
                      roi=roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

    with Writer(bag, version=8) as w:
        cd = w.add_connection(depth_topic, image.__msgtype__, typestore=ts)
        cdi = w.add_connection(_info_topic(depth_topic), info_t.__msgtype__, typestore=ts)
        cc = w.add_connection(colour_topic, image.__msgtype__, typestore=ts)
        cci = w.add_connection(_info_topic(colour_topic), info_t.__msgtype__, typestore=ts)
        for i, cnt in enumerate(truth["counts"]):
            t_ns = 10**9 + i * 33_333_333
            if encoding == "32FC1":
                z = (cnt.astype(np.float64) * truth["units_m"]).astype(np.float32)
                z[cnt == 0] = np.nan
                data, step = z.tobytes(), 4 * z.shape[1]
            else:
                mm = np.rint(cnt.astype(np.float64) * truth["units_m"] / 0.001).astype("<u2")
                data, step = mm.tobytes(), 2 * mm.shape[1]
            m = image(header=header(t_ns), height=cnt.shape[0], width=cnt.shape[1], encoding=encoding,
                      is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))
            w.write(cd, t_ns, ts.serialize_cdr(m, image.__msgtype__))
            w.write(cdi, t_ns, ts.serialize_cdr(info(t_ns), info_t.__msgtype__))
            rgb = cv2.imread(str(src / "sp" / f"frame{i}_color.png"))[..., ::-1].copy()
            mc = image(header=header(t_ns), height=rgb.shape[0], width=rgb.shape[1], encoding="rgb8",
                       is_bigendian=0, step=3 * rgb.shape[1], data=rgb.reshape(-1))
            w.write(cc, t_ns, ts.serialize_cdr(mc, image.__msgtype__))
            w.write(cci, t_ns, ts.serialize_cdr(info(t_ns), info_t.__msgtype__))
