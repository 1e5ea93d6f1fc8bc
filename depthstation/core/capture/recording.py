"""The recording model every reader yields: stream geometry, metadata and frame sets in order.

Every format (our MCAP, RealSense and ROS bags, PNG standpoint folders, TUM RGB-D folders) maps its
source into a `Recording`, so later stages never special-case a file format.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet

log = logging.getLogger("depthstation.core.capture")


def size_problem(image: Any, intr: Intrinsics | None, says: str) -> str | None:
    """What is wrong when an image is not the size its stream's intrinsics give (None when it is):
    every pixel would sit on the wrong ray, or past the image in a kernel. One check for every
    reader (PNG sets, TUM folders, ROS bags), each naming its own file."""
    if intr is None or tuple(image.shape[:2]) == (intr.height, intr.width):
        return None
    return f"is {image.shape[1]}x{image.shape[0]} pixels, but {says} {intr.width}x{intr.height}"


class NotThisFormat(InputError):
    """A reader's own layout is missing; the registry tries the next reader of the same suffix."""


class Recording:
    """One standpoint or sequence: stream geometry, metadata and an iterator over its frame sets."""

    name: str
    path: Path
    info: StreamInfo
    metadata: dict[str, Any]
    frame_count: int | None
    stream_counts: dict[str, int]
    topics: TopicChoice | None = None  # the topic choice it was opened with (ROS recordings)

    def __init__(
        self,
        name: str,
        path: Path,
        info: StreamInfo,
        metadata: dict[str, Any],
        frame_count: int | None,
        stream_counts: dict[str, int] | None = None,
    ) -> None:
        self.name = name
        self.path = Path(path)
        self.info = info
        self.metadata = metadata
        self.frame_count = frame_count
        self.stream_counts = dict(stream_counts or {})

    def _iter(self, start: int) -> Iterator[FrameSet]:
        raise NotImplementedError

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        """Frame sets in recording order, skipping `start` of them and yielding at most `limit`."""
        if limit is not None and limit <= 0:
            return
        for n, fs in enumerate(self._iter(start), start=1):
            yield fs
            if limit is not None and n >= limit:
                return

    def temperatures(self) -> dict[str, tuple[list[int], list[float]]]:
        """Device temperatures over time per sensor: name -> (timestamps ns, degrees C)."""
        return {}

    def summary(self) -> dict[str, Any]:
        """What `capture info` shows: streams, sizes, counts, geometry, device."""
        return {
            "name": self.name,
            "path": str(self.path),
            "frame_count": self.frame_count,
            "stream_counts": self.stream_counts,
            "info": self.info.to_dict(),
            "metadata": self.metadata,
        }

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {str(self.path)!r}, frames={self.frame_count})"
