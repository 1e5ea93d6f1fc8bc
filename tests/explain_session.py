"""A D455-like checkerboard session written pixel by pixel here, not by the simulator, for explain's
end-to-end tests at the size a user captures.

Geometry comes from `checkerboard_render` (colour by homography, depth by ray-plane intersection,
a wall 0.30 m behind the plate); the sensor is written in this file's own forms, the physics the
clean model (`d455-ideal`) assumes: disparity d = f B / z with white noise 0.04 px per pixel plus
0.07 px shared over the 9 x 9 matching window (a box filter of white noise), the ASIC's 1/32 px
disparity step, 1 mm depth units, pixels next to a depth edge thrown by up to 5 % of z, and random
dropouts (1.5 % everywhere, 4 % on black print). A concealed effect is a function of the pixel
arrays that adds to the disparity (bias) or draws extra disparity noise; nothing in
`simulate.effects` or `evaluate.explain` is used to write it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from checkerboard_render import pose_for, render_color, render_depth_m
from explain_cases import board_black

from depthstation.core.board import Board
from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.frames import FrameSet

WHITE_PX, SHARED_PX, WINDOW = 0.04, 0.07, 9
STEP_PX = 1.0 / 32.0
DROP, DROP_BLACK = 0.015, 0.04
EDGE_P, SPREAD = 0.3, 0.05
T0_NS = 1_700_000_000_000_000_000


@dataclass
class Pixels:
    """What a concealed effect sees of one frame: pixel grids, true depth, print, standpoint, frame."""

    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    black: np.ndarray
    standpoint: int
    frame: int
    fx: float
    ppx: float
    ppy: float
    rng: np.random.Generator


# a concealed effect: disparity added to the frame (px), same shape as the image
Hidden = Callable[[Pixels], Any]


def protocol_info(width: int = 640, height: int = 480) -> tuple[Board, StreamInfo]:
    """The demo board and a D455-like stream at this size (intrinsics only; nothing rendered)."""
    from depthstation.core.protocol import load_protocol
    from depthstation.simulate.checkerboard_session import stream_info_for
    from depthstation.simulate.model import load_model

    p = load_protocol("demo-d455")
    p = replace(p, streams=replace(p.streams, width=width, height=height))
    info = stream_info_for(p, load_model("d455-ideal"))
    return p.board, replace(info, device={**info.device, "simulated": False, "name": "Intel RealSense D455"})


def standpoints(n_distances: int = 6, inclinations: tuple[float, ...] = (0.0, 25.0, 45.0),
                near: float = 1.0, far: float = 4.0) -> list[tuple[str, float, float]]:
    """(name, distance, inclination) over near..far x inclinations: the issue's session layout."""
    out = []
    for i, z in enumerate(np.linspace(near, far, n_distances)):
        for j, a in enumerate(inclinations):
            out.append((f"sp{i:02d}_{j}", float(z), float(a)))
    return out


def _edge_distance(z: np.ndarray) -> np.ndarray:
    """Pixels from the nearest depth jump (> 3 % of the nearer z between 4-neighbours), 0.5 next to it."""
    jump = np.zeros(z.shape, dtype=bool)
    dz = np.abs(np.diff(z, axis=1)) > 0.03 * np.minimum(z[:, 1:], z[:, :-1])
    jump[:, 1:] |= dz
    jump[:, :-1] |= dz
    dz = np.abs(np.diff(z, axis=0)) > 0.03 * np.minimum(z[1:, :], z[:-1, :])
    jump[1:, :] |= dz
    jump[:-1, :] |= dz
    dist = cv2.distanceTransform((~jump).astype(np.uint8), cv2.DIST_L2, 5)
    return np.asarray(dist, dtype=np.float64) + 0.5


def write_session(out: Path, hidden: Hidden | None = None, *, extra_noise: Hidden | None = None,
                  frames: int = 15, width: int = 640, height: int = 480, seed: int = 0,
                  layout: list[tuple[str, float, float]] | None = None) -> Path:
    """Write one MCAP per standpoint into `out`. `hidden` adds a disparity bias (px) per frame,
    `extra_noise` returns an extra disparity noise draw (px) per frame (it gets `Pixels.rng`)."""
    board, info = protocol_info(width, height)
    assert info.color_intrinsics is not None and info.baseline_m is not None
    d_in = info.depth_intrinsics
    fb = d_in.fx * info.baseline_m
    d2c = info.depth_to_color.matrix
    v, u = np.mgrid[0:d_in.height, 0:d_in.width].astype(np.float64)
    out.mkdir(parents=True, exist_ok=True)
    for k, (name, dist, incl) in enumerate(layout or standpoints()):
        pose_c = pose_for(board, dist, incl, azimuth_deg=0.0)
        pose_d = np.linalg.inv(d2c) @ pose_c
        color = render_color(board, pose_c, info.color_intrinsics).astype(np.float64)
        z, _ = render_depth_m(board, pose_d, d_in, wall_offset_m=0.30)
        black = board_black(board, np.linalg.inv(pose_d), d_in.fx, d_in.fy, d_in.ppx, d_in.ppy, z.shape)
        p_fly = EDGE_P * np.exp(-np.maximum(_edge_distance(z) - 0.5, 0.0))
        fsets = []
        for i in range(frames):
            rng = np.random.default_rng([seed, k, i])
            px = Pixels(u, v, z, black, k, i, d_in.fx, d_in.ppx, d_in.ppy,
                        np.random.default_rng([seed, 99, k, i]))
            d = fb / z
            d = d + WHITE_PX * rng.standard_normal(z.shape)
            d = d + cv2.blur(rng.standard_normal(z.shape), (WINDOW, WINDOW),
                             borderType=cv2.BORDER_REFLECT) * WINDOW * SHARED_PX
            if hidden is not None:
                d = d + hidden(px)
            if extra_noise is not None:
                d = d + extra_noise(px)
            d = np.rint(d / STEP_PX) * STEP_PX
            zm = fb / np.where(d > 0, d, np.nan)
            fly = rng.random(z.shape) < p_fly
            zm = np.where(fly, zm * (1.0 + SPREAD * rng.uniform(-1.0, 1.0, z.shape)), zm)
            drop = rng.random(z.shape) < np.where(black, DROP_BLACK, DROP)
            counts = np.rint(zm / info.depth_units_m)
            ok = np.isfinite(counts) & ~drop & (counts > 0) & (counts < 65535)
            depth = np.where(ok, counts, 0).astype(np.uint16)
            col = np.clip(color + 1.5 * rng.standard_normal(color.shape), 0, 255).astype(np.uint8)
            ts = T0_NS + int((k * 40.0 + i / 30.0) * 1e9)
            fsets.append(FrameSet(i, ts, depth, col, metadata={"temperature_c": 40.0}))
        write_mcap(out / f"{name}.mcap", info, fsets, {"standpoint": {"name": name, "distance_m": dist,
                                                                      "inclination_deg": incl}})
    return out
