"""The camera interface every backend implements: live D455, file playback, simulated camera."""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from depthstation.core.camera_model import StreamInfo
from depthstation.core.errors import CameraError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Streams

REALSENSE_HINT = ("pyrealsense2 is not installed: pip install -e '.[camera]' (wheels for Linux x86_64 and "
                  "Windows; on macOS or a Jetson build librealsense with its Python bindings)")


def realsense() -> Any:
    """pyrealsense2 (an optional extra: offline evaluation, simulation and explain run without
    it), imported on first use; a one-line CameraError saying how to get it when it is missing."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise CameraError(REALSENSE_HINT) from exc


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of an on-chip or tare run: the new table (not yet applied) and its health values."""

    kind: str  # "on_chip" or "tare"
    table: bytes
    health: tuple[float, ...] = ()
    details: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class CalibratableCamera(Protocol):
    """On-device self-calibration (pyrealsense2 `auto_calibrated_device`)."""

    def calibration_table(self) -> bytes: ...
    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult: ...
    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult: ...
    def set_calibration_table(self, table: bytes) -> None: ...
    def write_calibration(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    """A source of FrameSets with the same life cycle as an rs.pipeline.

    `wait_for_frames` raises `CameraDisconnected` when the device drops off and
    `CameraError` on timeout; playback cameras raise `EOFError` at the end of the file.
    """

    def start(self, streams: Streams) -> StreamInfo: ...
    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet: ...
    def stop(self) -> None: ...
    def temperatures(self) -> dict[str, float]: ...
    def device_info(self) -> dict[str, str]: ...
    def options(self) -> dict[str, float]: ...
