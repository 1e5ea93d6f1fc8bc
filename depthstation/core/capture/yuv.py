"""YUYV 4:2:2 colour (ROS `yuv422_yuy2`), the form in which a D4xx colour sensor sends its images.

Why: a RealSense colour stream crosses USB as YUYV (BT.601, video range) and librealsense makes
RGB8 of it on the host, so an RGB8 recording holds 24 bits per pixel of which 16 are information.
Simulated sequences are recorded as the camera sends them (2 bytes per pixel; with the sensor's
noise they compress to ~0.55 of RGB8), and every reader gives back RGB (OpenCV's BT.601
video-range decoding, within 1 DN of librealsense's integer one).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

ENCODING = "yuv422_yuy2"  # sensor_msgs/image_encodings.h; byte order Y0 U Y1 V
UYVY_ENCODING = "yuv422"  # the older ROS name, byte order U Y0 V Y1
ALIASES = {ENCODING: ENCODING, "yuyv": ENCODING, UYVY_ENCODING: UYVY_ENCODING, "uyvy": UYVY_ENCODING}


@njit(cache=True, nogil=True)
def _encode(rgb: Any, out: Any) -> None:  # pragma: no cover - compiled
    h, w = rgb.shape[0], rgb.shape[1]
    for v in range(h):
        for u in range(0, w, 2):
            r0, g0, b0 = float(rgb[v, u, 0]), float(rgb[v, u, 1]), float(rgb[v, u, 2])
            r1, g1, b1 = float(rgb[v, u + 1, 0]), float(rgb[v, u + 1, 1]), float(rgb[v, u + 1, 2])
            y0 = 16.0 + (65.481 * r0 + 128.553 * g0 + 24.966 * b0) / 255.0
            y1 = 16.0 + (65.481 * r1 + 128.553 * g1 + 24.966 * b1) / 255.0
            r, g, b = 0.5 * (r0 + r1), 0.5 * (g0 + g1), 0.5 * (b0 + b1)
            cb = 128.0 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255.0
            cr = 128.0 + (112.0 * r - 93.786 * g - 18.214 * b) / 255.0
            out[v, u, 0] = np.uint8(min(max(y0 + 0.5, 0.0), 255.0))
            out[v, u, 1] = np.uint8(min(max(cb + 0.5, 0.0), 255.0))
            out[v, u + 1, 0] = np.uint8(min(max(y1 + 0.5, 0.0), 255.0))
            out[v, u + 1, 1] = np.uint8(min(max(cr + 0.5, 0.0), 255.0))


def rgb_to_yuy2(rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """HxWx3 RGB -> HxWx2 YUYV (BT.601 video range, chroma of each pixel pair averaged)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[1] % 2:
        raise ValueError(f"YUYV needs an RGB image of even width, not shape {rgb.shape}")
    out = np.empty((rgb.shape[0], rgb.shape[1], 2), np.uint8)
    _encode(np.ascontiguousarray(rgb, dtype=np.uint8), out)
    return out


def yuv422_to_rgb(packed: NDArray[np.uint8], encoding: str) -> NDArray[np.uint8]:
    """HxWx2 YUYV or UYVY -> HxWx3 RGB."""
    code = cv2.COLOR_YUV2RGB_YUY2 if ALIASES[encoding] == ENCODING else cv2.COLOR_YUV2RGB_UYVY
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(packed), code), dtype=np.uint8)
