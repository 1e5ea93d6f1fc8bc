"""The camera interface every backend implements (live D455, file playback, simulated camera), its
calibration result, the faults a device reports, and what we know of each RealSense model.

The per-model facts are Intel's: the product IDs from librealsense (`src/ds/d400/d400-private.h`),
the depth origin's distance behind the front glass from Intel support (librealsense issues #10928
and #14870). Depth is measured from the depth origin, the left imager's optical centre; a tape
measure reads from the glass, so a tare ground truth is the glass distance plus this offset.
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from depthstation.core.camera_model import StreamInfo
from depthstation.core.errors import CameraDisconnected, CameraError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import MODEL_NAME, Streams

# depth origin behind the front cover glass (mm), cased cameras (Intel support, issues #10928, #14870)
DEPTH_ORIGIN_BEHIND_GLASS_MM: dict[str, float] = {
    "D455": 4.55, "D456": 4.55, "D455F": 5.05, "D435": 4.2, "D435I": 4.2, "D435F": 4.7,
    "D415": 1.1, "D405": 3.7,
}
# USB product IDs as librealsense names them (upper-case hex); only those the sources give
# (the D455F and D456 are D455 units renamed by an IR-filter / IP65 flag, d400-device.cpp:1277-1287)
PRODUCT_IDS: dict[str, tuple[str, ...]] = {
    "D455": ("0B5C",), "D455F": ("0B5C",), "D456": ("0B5C",), "D435": ("0B07",), "D435I": ("0B3A",),
    "D415": ("0AD3",), "D405": ("0B5B",),
}
_MODEL_RE = re.compile(rf"\b({MODEL_NAME.pattern})\s*$")  # a name ending in a model: "RealSense D455"


def device_model(name: str) -> str | None:
    """The model in a camera name: 'RealSense D455' (SDK >= 2.58) and 'Intel RealSense D455' (older)
    both give 'D455'; 'RealSense D455F' gives 'D455F'."""
    m = _MODEL_RE.search(name.strip().upper())
    return None if m is None else m.group(1)


def depth_origin_offset_m(model: str | None) -> float | None:
    """Metres from the front glass back to the depth origin of a model, None where Intel gives none."""
    mm = DEPTH_ORIGIN_BEHIND_GLASS_MM.get((model or "").upper())
    return None if mm is None else mm / 1000.0


class CameraStalled(CameraDisconnected):
    """Frames stopped while the device stays listed (a known D4xx fault): a hardware reset recovers it."""


class CameraUnsuitable(CameraError):
    """The attached device cannot serve the protocol as it is: another model, USB 2, advanced mode off.
    The message says what to change; retrying without that change does not help."""


class CalibrationUnavailable(CameraError):
    """The device cannot enter Intel's self-calibration mode (depth 256x144 at 90 fps), e.g. on USB 2."""


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
    """Outcome of an on-chip or tare run: the new table and its health values on the device's scale.

    On-chip: `health = (h,)`, Intel's health check of the current calibration ([0, 0.25) good,
    [0.25, 0.75) can be improved, [0.75, inf) requires calibration). Tare: `health = (before, after)`,
    the relative depth error at the ground truth as a fraction (Z / GT - 1), before and after.
    """

    kind: str  # "on_chip" or "tare"
    table: bytes
    health: tuple[float, ...] = ()
    details: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class CalibratableCamera(Protocol):
    """On-device self-calibration (pyrealsense2 `auto_calibrated_device`).

    `calibration_table` reads the table in flash; `set_calibration_table` makes a table active
    in the device's RAM (lost on a reset or replug), `write_calibration` burns the last one set.
    """

    def calibration_table(self) -> bytes: ...
    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult: ...
    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult: ...
    def set_calibration_table(self, table: bytes) -> None: ...
    def write_calibration(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    """A source of FrameSets with the same life cycle as an rs.pipeline.

    `wait_for_frames` raises `CameraDisconnected` when the device drops off (`CameraStalled` when
    frames stop while it stays listed) and `CameraError` on timeout; playback cameras raise
    `EOFError` at the end of the file. `start` with the streams already running keeps them running.
    """

    def start(self, streams: Streams) -> StreamInfo: ...
    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet: ...
    def stop(self) -> None: ...
    def temperatures(self) -> dict[str, float]: ...
    def device_info(self) -> dict[str, str]: ...
    def options(self) -> dict[str, float]: ...
