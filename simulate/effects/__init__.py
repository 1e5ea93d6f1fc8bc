"""The sensor-effect catalogue (DESIGN §4): one module per effect, registered by catalogue name."""

from __future__ import annotations

from depthstation.simulate.effects.albedo_bias import AlbedoBias
from depthstation.simulate.effects.albedo_noise import AlbedoNoise
from depthstation.simulate.effects.base import Effect, PixelContext
from depthstation.simulate.effects.color_camera import ColorCamera
from depthstation.simulate.effects.depth_scale import DepthScale
from depthstation.simulate.effects.disparity_noise import DisparityNoise
from depthstation.simulate.effects.disparity_offset import DisparityOffset
from depthstation.simulate.effects.distortion_residual import DistortionResidual
from depthstation.simulate.effects.dropout import Dropout
from depthstation.simulate.effects.flying_pixels import FlyingPixels
from depthstation.simulate.effects.incidence_noise import IncidenceNoise
from depthstation.simulate.effects.lr_focal_mismatch import LrFocalMismatch
from depthstation.simulate.effects.periodic_bias import PeriodicBias
from depthstation.simulate.effects.pixel_locking import PixelLocking
from depthstation.simulate.effects.quantization import Quantization
from depthstation.simulate.effects.reference_pose_noise import ReferencePoseNoise
from depthstation.simulate.effects.slant_bias import SlantBias
from depthstation.simulate.effects.slant_noise import SlantNoise
from depthstation.simulate.effects.slant_scale import SlantScale
from depthstation.simulate.effects.spline_bias import SplineBias
from depthstation.simulate.effects.static_pattern import StaticPattern
from depthstation.simulate.effects.thermal_drift import ThermalDrift
from depthstation.simulate.effects.window_noise import WindowNoise

EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    DisparityNoise, Quantization, Dropout, DisparityOffset, DepthScale, LrFocalMismatch,
    DistortionResidual, PixelLocking, ThermalDrift, SlantNoise, SlantBias, AlbedoBias, AlbedoNoise,
    FlyingPixels, ReferencePoseNoise, WindowNoise, IncidenceNoise, StaticPattern, ColorCamera, SlantScale,
    PeriodicBias, SplineBias,
)}

__all__ = ["EFFECTS", "Effect", "PixelContext"]
