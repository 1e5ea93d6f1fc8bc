"""The D455 unit's effects written into a clean simulated session by this module's own code.

Independent of the simulator's effect modules and of explain's bases (no `simulate.effects` or
`evaluate.explain` import): each effect is written here in its own physical parameterisation, from
the true board pose in truth.json (the per-pixel ray, the board plane, the incidence angle between
them), onto the depth and colour frames of a session simulated with the clean camera (`d455-ideal`):

- calibration: depth f B off by a ratio (z scaled by 1 + s) and a disparity offset (px);
- slant_scale: z longer by k z (1/cos(theta) - 1), theta clipped at 75 deg;
- slant_bias: a disparity offset c tan^2(theta), theta clipped at 65 deg;
- incidence_noise: white disparity noise of RMS sigma tan(theta) (the 1/cos growth of a head-on
  sigma, written as the added part: sigma^2 (1/cos^2 - 1));
- static_pattern: a fixed disparity field over the normalised image, a sum of random plane waves
  with a Gaussian spectrum (one field per unit seed, the same in every frame and standpoint);
- color_camera: the colour image blurred by a Gaussian PSF, vignetted (cos^4-like), scaled to
  electrons and given Poisson shot noise and Gaussian read noise, back through the sRGB curve
  (the board pose found in it scatters more, most at long range and steep angles).

Depth is written in 0.1 mm units with uniform dither (as the concealed cases of `explain_cases`), so
sub-millimetre effects survive the rounding.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.registry import open_inputs
from depthstation.core.frames import FrameSet

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Unit:
    """A D455 unit's effects (0 = absent), in this module's own parameterisation."""

    scale: float = 0.0              # z (1 + scale)
    offset_px: float = 0.0          # disparity + offset (+ = nearer)
    slant_k: float = 0.0            # z (1 + k (1/cos - 1)), theta <= 75 deg
    slant_c_px: float = 0.0         # disparity + c tan^2(theta), theta <= 65 deg
    incidence_px: float = 0.0       # white disparity noise sigma tan(theta), theta <= 80 deg
    pattern_px: float = 0.0         # RMS of the fixed disparity field
    pattern_length: float = 0.12    # its correlation length, normalised image units
    pattern_seed: int = 7
    color_psf_px: float = 0.0       # colour: Gaussian blur sigma (0 = colour untouched)
    color_full_well_e: float = 200.0
    color_read_e: float = 4.0
    color_vignetting: float = 0.6   # relative illumination at the image corner

    @property
    def colour(self) -> bool:
        return self.color_psf_px > 0


# The d455 preset's unit in this module's terms. Offsets and the field are written in px of the mode
# rendered (the simulator states the unit's offset and pattern in px of the 1280-wide mode, scaled by
# fx / fx_ref): at 640x360 these are twice the preset's angle, and explain reports offset_px in px of
# the 1280-wide mode, so -0.10 px written here reads -0.20 px there
PAPER_UNIT = Unit(scale=0.006, offset_px=-0.10, slant_k=0.02, slant_c_px=-0.05, incidence_px=0.08,
                  pattern_px=0.03, pattern_length=0.12, pattern_seed=7, color_psf_px=0.8)


def plane_waves(seed: int, length: float, n: int = 160) -> tuple[F64, F64, F64]:
    """Wave vectors (rad per normalised unit), phases and amplitudes of a unit-RMS random field whose
    covariance is Gaussian with correlation length `length`: k ~ N(0, 1/length^2) per axis."""
    rng = np.random.default_rng([seed, 4551])
    k = rng.normal(0.0, 1.0 / length, size=(n, 2))
    phase = rng.uniform(0.0, 2 * np.pi, size=n)
    amp = np.full(n, np.sqrt(2.0 / n))
    return k, phase, amp


def pattern(x: F64, y: F64, seed: int, length: float) -> F64:
    """The unit's fixed field (unit RMS in expectation) at normalised image coordinates x, y."""
    k, phase, amp = plane_waves(seed, length)
    out = np.zeros(np.broadcast(x, y).shape)
    for (kx, ky), p, a in zip(k, phase, amp, strict=True):
        out += a * np.cos(kx * x + ky * y + p)
    return out


def incidence(cam_to_board: F64, fx: float, fy: float, ppx: float, ppy: float,
              shape: tuple[int, int]) -> tuple[F64, F64]:
    """Per pixel: the angle (rad) between its ray and the board normal, and the board's z-depth."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    rays = np.stack([(u - ppx) / fx, (v - ppy) / fy, np.ones_like(u)], axis=-1)
    to_cam = np.linalg.inv(cam_to_board)
    n, t = to_cam[:3, 2], to_cam[:3, 3]
    dot = rays @ n
    cos = np.abs(dot) / np.linalg.norm(rays, axis=-1)
    return np.arccos(np.clip(cos, 0.0, 1.0)), (n @ t) / dot


def _srgb_to_linear(c: F64) -> F64:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: F64) -> F64:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def degrade_colour(rgb: NDArray[np.uint8], unit: Unit, rng: np.random.Generator) -> NDArray[np.uint8]:
    """Blur, vignetting, shot and read noise on an 8-bit sRGB image (this module's camera)."""
    lin = _srgb_to_linear(rgb.astype(np.float64) / 255.0)
    lin = cv2.GaussianBlur(lin, (0, 0), unit.color_psf_px)
    h, w = lin.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    lin = lin * (1.0 - (1.0 - unit.color_vignetting) * r2)[..., None]
    e = lin * unit.color_full_well_e
    e = rng.poisson(np.clip(e, 0.0, None)).astype(np.float64) + rng.normal(0.0, unit.color_read_e, e.shape)
    return np.asarray(np.rint(255.0 * _linear_to_srgb(e / unit.color_full_well_e)), dtype=np.uint8)


def write_unit(sim_dir: Path, out_dir: Path, unit: Unit, seed: int = 0) -> Path:
    """Copy a clean simulated session into `out_dir` (plain MCAP) with `unit`'s effects written in."""
    truth = json.loads((sim_dir / "truth.json").read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    for k, rec in enumerate(open_inputs([sim_dir])):
        sp = next(s for s in truth["standpoints"] if s["name"] == rec.name)
        intr = rec.info.depth_intrinsics
        units = rec.info.depth_units_m
        fb = intr.fx * float(rec.info.baseline_m)
        theta, _ = incidence(np.asarray(sp["depth_camera_to_board"]), intr.fx, intr.fy, intr.ppx, intr.ppy,
                             (intr.height, intr.width))
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        # the pattern is fixed to the imager: normalised coordinates at the 1280-wide mode's scale
        field = unit.pattern_px * pattern((u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fx,
                                          unit.pattern_seed, unit.pattern_length) if unit.pattern_px else 0.0
        shift = unit.offset_px + unit.slant_c_px * np.tan(np.minimum(theta, np.radians(65.0))) ** 2 + field
        slant = 1.0 / np.cos(np.minimum(theta, np.radians(75.0))) - 1.0
        stretch = (1.0 + unit.scale) * (1.0 + unit.slant_k * slant)
        noise_px = unit.incidence_px * np.tan(np.minimum(theta, np.radians(80.0)))
        out_units = units / 10
        frames: list[FrameSet] = []
        for i, fs in enumerate(rec.frames()):
            assert fs.depth is not None
            rng = np.random.default_rng([seed, k, i])
            z = fs.depth.astype(np.float64) * units
            valid = fs.depth > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                d = fb / z + shift + noise_px * rng.standard_normal(z.shape)
                z = stretch * fb / d + out_units * (rng.random(z.shape) - 0.5)
            counts = np.rint(z / out_units)
            ok = valid & np.isfinite(counts) & (counts > 0) & (counts < 65535)
            depth = np.where(ok, counts, 0).astype(np.uint16)
            color = fs.color
            if unit.colour and color is not None:
                color = degrade_colour(np.asarray(color), unit, rng)
            frames.append(FrameSet(fs.index, fs.timestamp_ns, depth, color, fs.infrared, dict(fs.metadata)))
        meta: dict[str, Any] = dict(rec.metadata)
        meta["device"] = {**(meta.get("device") or {}), "depth_units_m": out_units}
        write_mcap(out_dir / f"{rec.name}.mcap", replace(rec.info, depth_units_m=out_units), frames, meta)
    return out_dir
