"""The colour camera as a real RGB camera delivers it: lens blur, vignetting, auto exposure, a Bayer
mosaic with demosaicing, and shot plus read noise. It changes the colour image, not the depth."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class ColorCamera(Effect):
    """How the colour image is formed (rendered by `simulate.color_pipeline`; depth passes unchanged).

    The checkerboard study's reference pose comes from corners found in this image, so its noise is
    what spreads the per-frame reference distance (paper Fig. 4: well below 5 mm for most
    standpoints, up to 2 cm far and steep). Per pose (a still camera): the linear image is blurred
    by the lens's PSF (Gaussian `psf_sigma_px`, lens plus the sensor's optical low-pass filter),
    darkened towards the corners (`vignetting`: relative illumination at the image corner, the
    cos^4 law softened by the lens design), scaled by auto exposure so the frame's mean reaches
    `ae_target` (a still scene: the exposure settles), sampled through an RGGB Bayer mosaic and
    demosaiced bilinearly (the neighbouring sites' mix blurs edges and correlates the noise of
    neighbours and channels). Per frame: shot noise (Poisson, `full_well_e` electrons at full
    scale) and read noise (`read_noise_e`) on each raw site, demosaiced like the signal, through
    the camera's gamma response. Corners of 6-12 px squares then scatter by ~0.05-0.1 px per frame
    (EMVA 1288 sensor model; the D455's RGB imager, OmniVision OV9782, 3 um pixels; small
    effective full well at indoor exposure and gain).
    """

    name: ClassVar[str] = "color_camera"
    meaning: ClassVar[str] = ("colour image formation: PSF, vignetting, auto exposure, Bayer demosaicing, "
                              "shot + read noise")
    source: ClassVar[str] = ("EMVA 1288 (photon transfer: shot + read noise); Bayer CFA with bilinear "
                             "demosaicing; D455 RGB imager OV9782 (global shutter, 3 um); paper Fig. 4 "
                             "/ Section 5.1 (reference-distance spread)")
    stage: ClassVar[int] = 90
    image_only: ClassVar[bool] = True
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "psf_sigma_px": (0.0, "px", "Gaussian sigma of the lens + optical low-pass blur"),
        "vignetting": (1.0, "1", "relative illumination at the image corner (1 = none)"),
        "ae_target": (0.18, "1", "auto exposure: the frame's mean linear signal (full scale 1)"),
        "full_well_e": (0.0, "e-", "electrons at full scale (shot noise); 0 = no noise"),
        "read_noise_e": (0.0, "e-", "read noise per raw site (electrons RMS)"),
        "demosaic": (1.0, "1", "1: RGGB Bayer mosaic, demosaiced bilinearly; 0: full colour per pixel"),
    }

    def validate(self) -> None:
        p = self.params
        if not (0 <= p["psf_sigma_px"] <= 5 and 0.05 <= p["vignetting"] <= 1 and 0.01 <= p["ae_target"] <= 0.9
                and p["full_well_e"] >= 0 and p["read_noise_e"] >= 0 and p["demosaic"] in (0.0, 1.0)):
            raise ValueError("psf_sigma_px in 0..5 px, vignetting in 0.05..1, ae_target in 0.01..0.9, "
                             "full_well_e and read_noise_e >= 0, demosaic 0 or 1 required")

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        return z_m   # the depth is not touched: the renderer forms the colour image with these parameters
