"""Frames of one view: geometry ray cast once per pose, sensor effects and image noise drawn per frame."""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from depthstation.core.camera_model import StreamInfo
from depthstation.core.frames import FrameSet
from depthstation.simulate.color_pipeline import ColorNoise, develop
from depthstation.simulate.effects.base import PixelContext
from depthstation.simulate.effects.color_camera import ColorCamera
from depthstation.simulate.model import SensorModel
from depthstation.simulate.scene import Scene
from depthstation.simulate.scene_render import (
    GeometryMaps,
    NoiseBank,
    SceneRaster,
    encode_srgb,
    render_color_linear,
    render_geometry,
)

COLOR_NOISE_DN = 2.0  # read + shot noise of the colour imager, 8-bit counts (RMS)
IR_NOISE_DN = 3.0
PSF_SIGMA_PX = 0.0  # optical blur of the colour camera (Gaussian sigma, px); 0 = ideal lens


def depth_to_z16(z_m: NDArray[Any], depth_units_m: float) -> NDArray[np.uint16]:
    """Metres (NaN = none) to z16 counts; 0 where no depth or beyond the 16-bit range."""
    z = np.asarray(z_m)
    if z.dtype not in (np.float32, np.float64):
        z = z.astype(np.float64)
    out = np.empty(z.shape, np.uint16)
    _z16(np.ascontiguousarray(z).reshape(-1), np.float32(1.0 / depth_units_m), out.reshape(-1))
    return out


@njit(cache=True, nogil=True)
def _z16(z: Any, scale: Any, out: Any) -> None:  # pragma: no cover
    """out = rint(z * scale) (ties to even; float32 for float32 z), 0 for NaN and outside [0, 65535]."""
    for i in range(z.shape[0]):
        c = np.rint(z[i] * scale)
        out[i] = np.uint16(c) if c >= 0 and c <= 65535 else 0


class ViewRenderer:
    """Renders FrameSets of a camera (depth camera pose `cam_to_world`) in a scene with a model.

    Geometry, albedo and the noiseless colour image are computed once per pose (`set_pose`); each
    `frame()` then only samples the effects and the image noise, which keeps a static standpoint
    of 150 frames at 1280x720 within seconds.
    """

    def __init__(self, scene: Scene, model: SensorModel, info: StreamInfo, *, seed: int = 0,
                 color: bool = True, infrared: bool = False, rc: Any = None,
                 color_noise_dn: float = COLOR_NOISE_DN, psf_sigma_px: float = PSF_SIGMA_PX,
                 vectors: bool = True) -> None:
        self.scene = scene
        self.model = model
        self.info = info
        self.rng = np.random.default_rng(seed)
        self.want_color = color and info.color_intrinsics is not None
        self.want_ir = infrared
        # the scene rasterised (the hits Open3D's ray casting gives, ~2x faster for a board; views
        # with lens distortion are ray cast by it)
        self.rc = rc if rc is not None else SceneRaster(scene)
        self.psf_sigma_px = psf_sigma_px
        self.vectors = vectors  # False: the geometry's normal and points_world maps are not filled
        self.geometry: GeometryMaps | None = None
        self.color_base: NDArray[np.uint8] | None = None
        self.ir_base: NDArray[np.float32] | None = None
        self._ctx: PixelContext | None = None
        self._ctx_key: tuple[float, float] | None = None
        self._pose: NDArray[np.float64] | None = None
        ci = info.color_intrinsics
        # a model with a `color_camera` effect forms its colour image as a real RGB camera does
        # (color_pipeline); without one, the ideal camera: box-filtered pixels, gamma, Gaussian noise
        cam = model.effect("color_camera")
        self.color_camera = cam if isinstance(cam, ColorCamera) else None
        self._color_scale: NDArray[np.int16] | None = None
        self._camera_noise = (ColorNoise((ci.height, ci.width, 3), bool(self.color_camera.params["demosaic"]),
                                         self.rng)
                              if self.want_color and ci is not None and self.color_camera is not None
                              and self.color_camera.params["full_well_e"] > 0 else None)
        if self.color_camera is not None:
            self.psf_sigma_px = self.color_camera.params["psf_sigma_px"]
        self._color_noise = (NoiseBank((ci.height, ci.width, 3), color_noise_dn, self.rng)
                             if self.want_color and ci is not None and color_noise_dn > 0
                             and self.color_camera is None else None)
        di = info.depth_intrinsics
        self._ir_noise = NoiseBank((di.height, di.width), IR_NOISE_DN, self.rng) if infrared else None

    def set_pose(self, cam_to_world: NDArray[Any]) -> None:
        """Move the depth camera; re-renders geometry (and colour) only when the pose changed."""
        pose = np.asarray(cam_to_world, dtype=np.float64)
        if self._pose is not None and np.array_equal(pose, self._pose):
            return
        self._pose = pose.copy()
        self.geometry = render_geometry(self.scene, self.info.depth_intrinsics, pose, self.rc,
                                        vectors=self.vectors)
        self._ctx = None
        if self.want_color:
            assert self.info.color_intrinsics is not None
            color_pose = pose @ np.linalg.inv(self.info.depth_to_color.matrix)
            lin = render_color_linear(self.scene, self.info.color_intrinsics, color_pose, self.rc,
                                      psf_sigma_px=self.psf_sigma_px)
            if self.color_camera is not None:
                self.color_base, self._color_scale = develop(lin, self.color_camera)
            else:
                self.color_base = encode_srgb(lin)
        if self.want_ir:
            g = self.geometry
            cos = np.cos(np.radians(np.nan_to_num(g.inclination_deg, nan=90.0)))
            # active IR: the projector lights the scene with 1/z^2 fall-off, plus ambient
            z = np.nan_to_num(g.z_m, nan=50.0)
            self.ir_base = (np.nan_to_num(g.albedo) * (0.25 + 0.75 * cos * np.minimum(1.0, 1.0 / (z * z)))
                            * 200.0).astype(np.float32)

    def context(self, time_s: float = 0.0, temperature_c: float = 40.0) -> PixelContext:
        """Effect context of the current pose (rebuilt when time-dependent inputs change)."""
        if self.geometry is None:
            raise RuntimeError("set_pose() first")
        needs_time = any(e.time_dependent for e in self.model.effects)
        key = (round(time_s, 3) if needs_time else 0.0, round(temperature_c, 3) if needs_time else 0.0)
        if self._ctx is None or key != self._ctx_key:
            self._ctx = self.geometry.context(self.info.baseline_m or self.model.camera.baseline_m,
                                              time_s, temperature_c, stereo=self.info.stereo_intrinsics,
                                              fx_ref=self.model.camera.reference_fx)
            self._ctx_key = key
        return self._ctx

    def measured_depth_m(self, time_s: float = 0.0, temperature_c: float = 40.0,
                         rng: np.random.Generator | None = None) -> NDArray[np.float32]:
        """One sample of the measured z map (float32, NaN = no depth)."""
        ctx = self.context(time_s, temperature_c)
        assert self.geometry is not None
        return self.model.sample(ctx, self.geometry.z_m, rng or self.rng)

    def frame(self, index: int, timestamp_ns: int, time_s: float = 0.0,
              temperature_c: float = 40.0, rng: np.random.Generator | None = None) -> FrameSet:
        """One FrameSet at the current pose (noise from `rng`, else the renderer's own generator)."""
        z = self.measured_depth_m(time_s, temperature_c, rng)
        depth = depth_to_z16(z, self.info.depth_units_m)
        color = None
        if self.color_base is not None:
            noise = self._color_noise
            if self._camera_noise is not None and self._color_scale is not None:
                color = self._camera_noise.apply(self.color_base, self._color_scale, rng or self.rng)
            else:
                color = noise.apply(self.color_base, rng) if noise else self.color_base.copy()
        ir = None
        if self.ir_base is not None and self._ir_noise is not None:
            ir = self._ir_noise.apply(np.clip(self.ir_base, 0, 255).astype(np.uint8), rng)
        return FrameSet(index=index, timestamp_ns=int(timestamp_ns), depth=depth, color=color,
                        infrared=ir, metadata={"simulated": True, "temperature_c": temperature_c})
