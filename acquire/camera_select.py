"""`--camera live|PATH|sim[:MODEL]`: which camera backend a command talks to.

Backends load lazily: the live camera imports pyrealsense2 on start, playback the capture reader,
the simulated camera the simulator (DESIGN §1: acquire loads the simulated camera lazily).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from depthstation.acquire.live_camera import LiveCamera
from depthstation.acquire.playback_camera import PlaybackCamera
from depthstation.core.device import realsense
from depthstation.core.errors import InputError
from depthstation.simulate.simulated_camera import SimulatedCamera

RECORDING_SUFFIXES = (".db3", ".bag", ".mcap")


@dataclass(frozen=True)
class CameraSpec:
    kind: str  # 'live', 'file' or 'sim'
    path: Path | None = None
    model: str | None = None
    serial: str | None = None

    def describe(self) -> str:
        if self.kind == "live":
            return "live RealSense" + ("" if self.serial is None else f" {self.serial}")
        if self.kind == "file":
            return f"playback of {self.path}"
        return f"simulated camera (model {self.model})"


def parse_camera(spec: str) -> CameraSpec:
    """'live', 'live:SERIAL', 'sim', 'sim:d435', 'sim:path/model.toml' or the path of a recording."""
    s = spec.strip()
    if s == "live" or s.startswith("live:"):
        serial = s[5:] or None if s.startswith("live:") else None
        return CameraSpec("live", serial=serial)
    if s == "sim" or s.startswith("sim:"):
        model = s[4:] if s.startswith("sim:") and s[4:] else "d455"
        return CameraSpec("sim", model=model)
    p = Path(s)
    if p.exists() and (p.suffix.lower() in RECORDING_SUFFIXES or p.is_dir()):
        return CameraSpec("file", path=p)
    if not p.exists() and (p.suffix.lower() in RECORDING_SUFFIXES or "/" in s):
        raise InputError(p, "recording not found")
    raise InputError(None, f"--camera must be 'live', 'sim[:MODEL]' or a recording "
                           f"({', '.join(RECORDING_SUFFIXES)}), got {spec!r}")


def open_camera(spec: CameraSpec, **options: Any) -> Any:
    """The camera object for a spec (not started); `options` go to the live or simulated camera."""
    if spec.kind == "live":
        realsense()  # the one line saying how to install it, before anything starts
        return LiveCamera(spec.serial, **options)
    if spec.kind == "file":
        assert spec.path is not None
        cam = PlaybackCamera(spec.path)  # a bad path first, then whether librealsense is there
        realsense()
        return cam
    return SimulatedCamera(spec.model or "d455", **options)
