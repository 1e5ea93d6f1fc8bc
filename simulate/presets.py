"""Camera presets of the D4xx family: baseline, fields of view, intrinsics per resolution, extrinsics.

Focal lengths follow from the horizontal field of view of the full-width mode:
fx = (W / 2) / tan(HFOV / 2), e.g. D455 depth at 1280x720: 640 / tan(43.5 deg) = 674.4 px.
Pixels are square (fy = fx). The 16:9 modes (848x480, 640x360, ...) scale the 1280x720 image;
640x480 is the 4:3 mode cut from the 1280x800 imager scaled by 0.6, as on the device.
min-z = fx * B / max_disparity (126 px search range of the D4 ASIC), so it shrinks with resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.errors import SimulationError

# resolution -> scale of the 1280-wide focal length (4:3 and 16:10 modes come from the 1280x800 imager)
_SCALE = {(1280, 720): 1.0, (1280, 800): 1.0, (848, 480): 848 / 1280, (640, 480): 0.6,
          (640, 360): 0.5, (480, 270): 0.375, (424, 240): 424 / 1280, (320, 240): 0.3,
          (320, 180): 0.25, (256, 144): 0.2}


@dataclass(frozen=True)
class CameraPreset:
    """One D4xx model. Angles in degrees, lengths in metres, principal-point offsets in px at 1280 wide."""

    name: str
    product: str
    baseline_m: float
    depth_hfov_deg: float
    color_hfov_deg: float
    depth_to_color_translation_m: tuple[float, float, float]
    depth_pp_offset_px: tuple[float, float] = (0.0, 0.0)
    color_pp_offset_px: tuple[float, float] = (0.0, 0.0)
    max_disparity_px: float = 126.0
    max_range_m: float = 6.0
    depth_units_m: float = 0.001
    serial: str = "000000000000"
    firmware: str = "5.16.0.1"

    def _intrinsics(self, hfov_deg: float, pp_offset: tuple[float, float], width: int,
                    height: int) -> Intrinsics:
        if (width, height) in _SCALE:
            scale = _SCALE[(width, height)]
        elif abs(width * 9 - height * 16) <= 16:
            scale = width / 1280.0
        else:
            known = ", ".join(f"{w}x{h}" for w, h in _SCALE)
            raise SimulationError(f"{self.name}: no {width}x{height} mode (known: {known}, or any 16:9)")
        fx = 640.0 / float(np.tan(np.radians(hfov_deg) / 2.0)) * scale
        return Intrinsics(width, height, fx, fx, (width - 1) / 2.0 + pp_offset[0] * scale,
                          (height - 1) / 2.0 + pp_offset[1] * scale, "brown_conrady",
                          (0.0, 0.0, 0.0, 0.0, 0.0))

    def depth_intrinsics(self, width: int = 1280, height: int = 720) -> Intrinsics:
        """Depth (= left IR) intrinsics at a resolution; the depth stream has no distortion."""
        return self._intrinsics(self.depth_hfov_deg, self.depth_pp_offset_px, width, height)

    @property
    def reference_fx(self) -> float:
        """Depth focal length (px) of the 1280-wide mode: the unit's geometric errors (disparity
        offset, static pattern, ...) are stated in its px and scaled by fx / reference_fx elsewhere."""
        return self.depth_intrinsics(1280, 720).fx

    def color_intrinsics(self, width: int = 1280, height: int = 720) -> Intrinsics:
        """Colour intrinsics (rendered without lens distortion)."""
        return self._intrinsics(self.color_hfov_deg, self.color_pp_offset_px, width, height)

    @property
    def depth_to_color(self) -> Extrinsics:
        """p_color = p_depth + t (the imagers are mounted parallel)."""
        return Extrinsics(translation=self.depth_to_color_translation_m)

    def min_z_m(self, width: int = 1280, height: int = 720) -> float:
        """Nearest z with depth: f B / max disparity."""
        return self.depth_intrinsics(width, height).fx * self.baseline_m / self.max_disparity_px

    def device_info(self) -> dict[str, Any]:
        """Device description with librealsense's camera_info keys (what rsrecord registers)."""
        return {"name": f"Intel RealSense {self.product}", "product_line": "D400",
                "serial_number": self.serial, "firmware_version": self.firmware,
                "simulated": True, "model": self.name, "baseline_m": self.baseline_m,
                "depth_units_m": self.depth_units_m}

    def stream_info(self, width: int = 1280, height: int = 720, fps: float = 30.0,
                    color_size: tuple[int, int] | None = None, infrared: bool = False) -> StreamInfo:
        """What a camera of this model delivers at a resolution (colour at the same size unless given)."""
        cw, ch = color_size or (width, height)
        di = self.depth_intrinsics(width, height)
        return StreamInfo(
            depth_intrinsics=di, color_intrinsics=self.color_intrinsics(cw, ch),
            depth_to_color=self.depth_to_color, depth_units_m=self.depth_units_m,
            depth_aligned_to_color=False, infrared_intrinsics=di if infrared else None,
            baseline_m=self.baseline_m, fps=fps, device=self.device_info())

    def with_overrides(self, overrides: dict[str, Any]) -> CameraPreset:
        """A copy with some fields replaced (the [camera] table of a model TOML)."""
        conv: dict[str, Any] = {}
        for k, v in overrides.items():
            if k not in self.__dataclass_fields__ or k == "name":
                raise KeyError(k)
            cur = getattr(self, k)
            conv[k] = _converted(k, cur, v)
        return replace(self, **conv)

    def check(self) -> CameraPreset:
        """Raise ValueError naming the field when a value has no physical meaning."""
        if not 0.005 < self.baseline_m < 1.0:
            raise ValueError(f"baseline_m must be the stereo baseline in metres (0.005 to 1), "
                             f"got {self.baseline_m}")
        for name in ("depth_hfov_deg", "color_hfov_deg"):
            v = getattr(self, name)
            if not 1.0 < v < 179.0:
                raise ValueError(f"{name} must be a field of view in degrees (1 to 179), got {v}")
        t = self.depth_to_color_translation_m
        if not all(np.isfinite(t)) or float(np.linalg.norm(t)) > 1.0:   # millimetres typed as metres
            raise ValueError(f"depth_to_color_translation_m must be in metres (at most 1 m between the "
                             f"imagers), got {list(t)}")
        for name in ("max_range_m", "max_disparity_px", "depth_units_m"):
            if not (getattr(self, name) > 0 and np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} must be positive and finite, got {getattr(self, name)}")
        if not 1e-6 <= self.depth_units_m <= 0.01:  # a D4xx's range (1 um to 1 cm); 1.0: mm as m
            raise ValueError(f"depth_units_m must be metres per depth count (1e-6 to 0.01 on a D4xx), "
                             f"got {self.depth_units_m}")
        for name in ("depth_pp_offset_px", "color_pp_offset_px"):
            v = getattr(self, name)
            if not all(np.isfinite(v)) or max(abs(x) for x in v) > 640.0:
                raise ValueError(f"{name} must be finite pixels at 1280 wide (within 640 of the centre), "
                                 f"got {list(v)}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v)
                for k, v in self.__dict__.items()}


def _converted(key: str, current: Any, value: Any) -> Any:
    """A [camera] value in the preset field's type; ValueError naming the key when it is not one
    (a list of the wrong length, a string for a number)."""
    if isinstance(current, tuple):
        if (not isinstance(value, (list, tuple)) or len(value) != len(current)
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)):
            raise ValueError(f"{key} must be a list of {len(current)} numbers, got {value!r}")
        return tuple(float(x) for x in value)
    if isinstance(current, float):
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise ValueError(f"{key} must be a number, got {value!r}")
        return float(value)
    if isinstance(value, int) and not isinstance(value, bool):   # a serial number written as a number
        return str(value)
    if not isinstance(value, str):
        raise ValueError(f"{key} must be a string, got {value!r}")
    return value


PRESETS: dict[str, CameraPreset] = {
    # D455: 95 mm baseline, depth 87 x 58 deg, RGB 90 x 65 deg (Intel D400 datasheet rev. 0.9+).
    "d455": CameraPreset("d455", "D455", 0.095, 87.0, 90.0, (-0.059, 0.0, 0.0),
                         depth_pp_offset_px=(2.3, -1.4), color_pp_offset_px=(-3.1, 2.2),
                         max_range_m=6.0, serial="213622070001"),
    # D435: 50 mm baseline, depth 87 x 58 deg, RGB 69 x 42 deg, RGB 15 mm right of the left imager.
    "d435": CameraPreset("d435", "D435", 0.050, 87.0, 69.0, (0.015, 0.0, 0.0),
                         depth_pp_offset_px=(1.6, 0.9), color_pp_offset_px=(-2.0, 1.5),
                         max_range_m=3.0, serial="819612070001"),
    # D415: 55 mm baseline, depth 65 x 40 deg (rolling shutter, narrow), RGB 69 x 42 deg.
    "d415": CameraPreset("d415", "D415", 0.055, 65.0, 69.0, (0.015, 0.0, 0.0),
                         depth_pp_offset_px=(-1.2, 0.8), color_pp_offset_px=(1.0, -1.3),
                         max_range_m=3.0, serial="822512070001"),
}
