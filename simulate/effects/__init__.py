"""The sensor-effect catalogue (DESIGN §4): one module per effect, registered by catalogue name."""

from __future__ import annotations

from simulate.effects.albedo_bias import AlbedoBias
from simulate.effects.albedo_noise import AlbedoNoise
from simulate.effects.base import Effect, PixelContext
from simulate.effects.depth_scale import DepthScale
from simulate.effects.disparity_noise import DisparityNoise
from simulate.effects.disparity_offset import DisparityOffset
from simulate.effects.distortion_residual import DistortionResidual
from simulate.effects.dropout import Dropout
from simulate.effects.flying_pixels import FlyingPixels
from simulate.effects.lr_focal_mismatch import LrFocalMismatch
from simulate.effects.pixel_locking import PixelLocking
from simulate.effects.quantization import Quantization
from simulate.effects.reference_pose_noise import ReferencePoseNoise
from simulate.effects.slant_bias import SlantBias
from simulate.effects.slant_noise import SlantNoise
from simulate.effects.thermal_drift import ThermalDrift

EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    DisparityNoise, Quantization, Dropout, DisparityOffset, DepthScale, LrFocalMismatch,
    DistortionResidual, PixelLocking, ThermalDrift, SlantNoise, SlantBias, AlbedoBias, AlbedoNoise,
    FlyingPixels, ReferencePoseNoise,
)}

__all__ = ["EFFECTS", "Effect", "PixelContext"]
