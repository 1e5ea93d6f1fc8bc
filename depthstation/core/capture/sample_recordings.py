"""Small deterministic recordings (random content, realistic geometry) for tests and benchmarks."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.frames import FrameSet
from depthstation.core.geometry import rodrigues


def sample_info(
    width: int = 64, height: int = 48, *, color: bool = True, infrared: bool = False, fps: float = 30.0
) -> StreamInfo:
    """D455-like geometry scaled to `width` x `height`; values are float32-representable like the SDK's."""

    def f32(x: float) -> float:
        return float(np.float32(x))

    s = width / 1280.0
    depth = Intrinsics(
        width,
        height,
        f32(634.123 * s),
        f32(633.871 * s),
        f32(639.47 * s),
        f32(359.13 * s),
        "brown_conrady",
        (0.0, 0.0, 0.0, 0.0, 0.0),
    )
    col = Intrinsics(
        width,
        height,
        f32(641.55 * s),
        f32(640.93 * s),
        f32(637.2 * s),
        f32(361.8 * s),
        "inverse_brown_conrady",
        (f32(-0.0551), f32(0.0632), f32(-0.0007), f32(0.0011), f32(-0.0203)),
    )
    r = rodrigues(np.array([0.0031, -0.0042, 0.0019]))
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = [-0.05917, 0.00012, 0.00043]
    d2c = Extrinsics.from_matrix(m)
    return StreamInfo(
        depth_intrinsics=depth,
        color_intrinsics=col if color else None,
        depth_to_color=d2c,
        depth_units_m=0.001,
        infrared_intrinsics=depth if infrared else None,
        baseline_m=0.095,
        fps=fps,
        device={
            "name": "Intel RealSense D455",
            "serial_number": "000000000001",
            "firmware_version": "5.16.0.1",
        },
    )


def sample_frames(
    info: StreamInfo,
    n: int,
    *,
    seed: int = 0,
    start_ns: int = 1_700_000_000_000_000_000,
    first_index: int = 0,
) -> Iterator[FrameSet]:
    """`n` frame sets with random depth (with zeros = no depth), colour and infrared."""
    rng = np.random.default_rng(seed)
    h, w = info.depth_intrinsics.height, info.depth_intrinsics.width
    period = round(1e9 / (info.fps or 30.0))
    for k in range(n):
        depth = rng.integers(0, 65535, size=(h, w), dtype=np.uint16)
        depth[rng.random((h, w)) < 0.05] = 0
        color = None
        if info.color_intrinsics is not None:
            ci = info.color_intrinsics
            color = rng.integers(0, 256, size=(ci.height, ci.width, 3), dtype=np.uint8)
        infrared = None
        if info.infrared_intrinsics is not None:
            infrared = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
        yield FrameSet(
            index=first_index + k,
            timestamp_ns=start_ns + k * period,
            depth=depth,
            color=color,
            infrared=infrared,
            metadata={"exposure_us": 8500 + k},
        )
