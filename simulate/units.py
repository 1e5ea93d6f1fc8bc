"""Units of a camera model: each D4xx leaves the factory (and its on-chip calibration) with its own
residual calibration errors; `draw_unit` gives another unit of the same model.

The population (per preset, 1 sigma over units, after on-chip self-calibration):
- depth scale (f B off by a ratio; `depth_scale.scale_error`) and disparity offset (the imagers'
  relative yaw; `disparity_offset.offset_px`): Intel's D400 datasheet specifies the absolute depth
  error within +-2 % at 4 m for the D455 (within +-2 % at 2 m for the D435/D415), after on-chip
  calibration; read as two standard deviations of the combined error, split evenly between the two
  terms. The paper's unit (its registration scale 0.98288, Section 3.2.2: depth 1.7 % long) lies
  inside that population: it is the `d455` preset's draw.
- the static pattern (`static_pattern.pattern_seed`): every unit has its own emitter and lens
  residuals, so its own field.
The matcher's slant behaviour and the noise are properties of the design, the same for all units.
"""

from __future__ import annotations

import numpy as np

from depthstation.core.errors import InputError
from depthstation.simulate.model import SensorModel

# preset -> (reference distance of the spec (m), spec as a fraction of z at that distance)
SPEC: dict[str, tuple[float, float]] = {"d455": (4.0, 0.02), "d435": (2.0, 0.02), "d415": (2.0, 0.02)}


def unit_spread(model: SensorModel) -> tuple[float, float]:
    """1-sigma spread over units of (scale_error, offset_px): half the spec at its distance, split
    evenly between a scale error and a disparity offset (whose error at z_ref is z_ref offset / (f B));
    the offset in px of the 1280-wide mode, where `disparity_offset.offset_px` is stated."""
    z_ref, frac = SPEC.get(model.camera.name, SPEC["d455"])
    sigma_rel = frac / 2.0 / np.sqrt(2.0)
    fb = model.camera.reference_fx * model.camera.baseline_m
    return float(sigma_rel), float(sigma_rel * fb / z_ref)


def draw_unit(model: SensorModel, unit_seed: int) -> SensorModel:
    """The same model for another unit: its depth scale, disparity offset and static pattern drawn
    from the population (`unit_spread`); effects the model lacks are left out as they were."""
    if unit_seed < 0:
        raise InputError(None, f"--unit-seed must be 0 or more, not {unit_seed}")
    rng = np.random.default_rng([unit_seed, 0xD455])
    s_scale, s_offset = unit_spread(model)
    scale, offset = float(rng.normal(0.0, s_scale)), float(rng.normal(0.0, s_offset))
    out = model
    if out.effect("depth_scale") is not None:
        out = out.with_effect("depth_scale", scale_error=scale)
    if out.effect("disparity_offset") is not None:
        out = out.with_effect("disparity_offset", offset_px=offset)
    if out.effect("static_pattern") is not None:
        out = out.with_effect("static_pattern", pattern_seed=float(unit_seed + 1))
    out.name = f"{model.name}-unit{unit_seed}"
    return out
