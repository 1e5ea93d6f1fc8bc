"""The colour image as a real RGB camera forms it (the `color_camera` effect's parameters).

Per pose (`develop`): vignetting, auto exposure, Bayer mosaic and bilinear demosaicing of the
linear image (already blurred by the lens PSF in `render_color_linear`), the gamma response, and
the map of each pixel's noise RMS in 8-bit counts. Per frame (`ColorNoise.apply`): shot plus read
noise, drawn as a demosaiced raw field from a small bank read at random even offsets (the Bayer
phase is kept), scaled by the pose's map, in one compiled pass.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from depthstation.simulate.effects.color_camera import ColorCamera
from depthstation.simulate.scene_render import encode_srgb

F32 = NDArray[np.float32]
FIELD_SCALE = 16.0   # a bank field holds 16 x a unit normal in int8 (+-7.9 sigma)
_GAMMA = 1.0 / 2.2   # the camera response of `encode_srgb`
_K_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], np.float32) / 4.0
_K_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32) / 4.0


def bayer_masks(h: int, w: int) -> tuple[F32, F32, F32]:
    """RGGB site masks (R at even row, even column; B at odd, odd; G elsewhere)."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = ((yy % 2 == 0) & (xx % 2 == 0)).astype(np.float32)
    b = ((yy % 2 == 1) & (xx % 2 == 1)).astype(np.float32)
    return r, 1.0 - r - b, b


def demosaic(raw: F32) -> F32:
    """Bilinear demosaicing of an RGGB raw image (HxW) into HxWx3."""
    h, w = raw.shape
    mr, mg, mb = bayer_masks(h, w)
    out = np.empty((h, w, 3), np.float32)
    for k, (m, ker) in enumerate(((mr, _K_RB), (mg, _K_G), (mb, _K_RB))):
        out[..., k] = cv2.filter2D(raw * m, -1, ker, borderType=cv2.BORDER_REFLECT_101)
    return out


def mosaic(rgb: F32) -> F32:
    """The raw RGGB image a Bayer sensor records of a full-colour image."""
    h, w = rgb.shape[:2]
    mr, mg, mb = bayer_masks(h, w)
    return np.asarray(rgb[..., 0] * mr + rgb[..., 1] * mg + rgb[..., 2] * mb, dtype=np.float32)


def vignetting_map(h: int, w: int, corner: float) -> F32:
    """Relative illumination 1 / (1 + a rho^2)^2 (rho = radius / corner radius), `corner` at rho = 1."""
    if corner >= 1.0:
        return np.ones((h, w), np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rho2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    a = corner ** -0.5 - 1.0
    return np.asarray(1.0 / (1.0 + a * rho2) ** 2, dtype=np.float32)


def develop(linear: F32, cam: ColorCamera) -> tuple[NDArray[np.uint8], NDArray[np.int16]]:
    """The noiseless 8-bit image of a pose and each pixel's noise RMS per bank unit (counts / 16, in
    1/256 counts: `fixed_scale`)."""
    p = cam.params
    h, w = linear.shape[:2]
    sig = linear * vignetting_map(h, w, p["vignetting"])[..., None]
    mean = float(sig.mean())
    if mean > 0:   # auto exposure: a still scene, the exposure settles on the target
        sig *= np.float32(p["ae_target"] / mean)
    np.clip(sig, 0.0, 1.0, out=sig)
    if p["demosaic"]:
        sig = demosaic(mosaic(sig))
        np.clip(sig, 0.0, 1.0, out=sig)
    base = encode_srgb(sig)
    k = p["full_well_e"]
    if k <= 0:
        return base, np.zeros(sig.shape, np.int16)
    sigma_lin = np.sqrt(sig * np.float32(k) + np.float32(p["read_noise_e"] ** 2)) / np.float32(k)
    slope = np.float32(255.0 * _GAMMA) * np.maximum(sig, np.float32(1e-3)) ** np.float32(_GAMMA - 1.0)
    scale = np.minimum(slope * sigma_lin, np.float32(60.0)) / np.float32(FIELD_SCALE)
    return base, fixed_scale(np.asarray(scale, dtype=np.float32))


class ColorNoise:
    """Shot + read noise of a Bayer camera: demosaiced unit raw fields, read at random even offsets."""

    def __init__(self, shape: tuple[int, int, int], demosaiced: bool, rng: np.random.Generator,
                 fields: int = 4, pad: int = 64) -> None:
        h, w, _ = shape
        self.shape = shape
        self.pad = pad
        self.fields: list[NDArray[np.int8]] = []
        for _ in range(fields):
            if demosaiced:
                f = demosaic(rng.standard_normal((h + pad, w + pad), dtype=np.float32))
            else:
                f = rng.standard_normal((h + pad, w + pad, 3), dtype=np.float32)
            self.fields.append(np.clip(np.rint(f * FIELD_SCALE), -127, 127).astype(np.int8))

    def apply(self, base: NDArray[np.uint8], scale: NDArray[np.int16],
              rng: np.random.Generator) -> NDArray[np.uint8]:
        """One noisy frame: `scale` is `develop`'s map in fixed point (`fixed_scale`)."""
        f = self.fields[int(rng.integers(len(self.fields)))]
        r = 2 * int(rng.integers(self.pad // 2))
        c = 2 * int(rng.integers(self.pad // 2))
        h, w, ch = base.shape
        out = np.empty_like(base)
        _add_noise(base.reshape(h, w * ch), f.reshape(f.shape[0], -1), r, c * ch, scale.reshape(h, w * ch),
                   out.reshape(h, w * ch))
        return out


def fixed_scale(scale: F32) -> NDArray[np.int16]:
    """The noise map in 1/256 of a count per bank unit (integer arithmetic in the per-frame pass)."""
    return np.asarray(np.clip(np.rint(scale * 256.0), 0, 32767), dtype=np.int16)


@njit(cache=True, nogil=True)
def _add_noise(base: Any, field: Any, r: int, c: int, scale: Any, out: Any) -> None:  # pragma: no cover
    """out = clip(base + floor((field[r:, c:] x scale + 128) / 256), 0, 255), rows of interleaved RGB."""
    h, n = base.shape
    for y in range(h):
        b = base[y]
        f = field[y + r, c:c + n]
        s = scale[y]
        o = out[y]
        for i in range(n):
            v = np.int32(b[i]) + ((np.int32(f[i]) * np.int32(s[i]) + 128) >> 8)
            o[i] = 0 if v < 0 else (255 if v > 255 else v)
