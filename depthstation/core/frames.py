"""The frame record every camera, reader and simulator yields."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import StreamInfo


@dataclass
class FrameSet:
    """One time step: depth (z16 counts), colour (RGB), optional infrared, with its frame number.

    `depth` is uint16 HxW in units of `StreamInfo.depth_units_m`; 0 means no depth.
    `timestamp_ns` is Unix epoch nanoseconds. `metadata` carries per-frame values such as
    temperatures or exposure where the source has them.
    """

    index: int
    timestamp_ns: int
    depth: NDArray[np.uint16] | None = None
    color: NDArray[np.uint8] | None = None
    infrared: NDArray[np.uint8] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def depth_m(self, depth_units_m: float) -> NDArray[np.float32]:
        """Depth in metres as float32, NaN where the camera gave no value."""
        if self.depth is None:
            raise ValueError("frame has no depth")
        d = self.depth.astype(np.float32) * np.float32(depth_units_m)
        d[self.depth == 0] = np.nan
        return d


class FrameSource(Protocol):
    """What a study reads: stream geometry and frame sets in order.

    Every recording reader (`depthstation.core.capture.recording.Recording`) is one; so are the
    in-memory sources of the simulator and the tests (a rendered walk, a synthetic room).
    """

    name: str
    info: StreamInfo

    @property
    def frame_count(self) -> int | None: ...

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]: ...
