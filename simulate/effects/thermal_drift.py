"""Thermal drift: the stereo head bends as it warms up; offset following temperature."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class ThermalDrift(DisparityShift):
    """d_meas = d + coeff_px_per_c (T - reference_c): the imagers' relative yaw changes with T.

    The reason the paper warms the camera up for an hour before measuring. The yaw is an angle, but
    unlike the unit's offset `coeff_px_per_c` stays in px of the rendered image: explain fits thermal
    drift with its own column form (-z^2 / (f B) per px of the data's mode), and a parameter it writes
    must render as it was fitted.
    """

    name: ClassVar[str] = "thermal_drift"
    time_dependent: ClassVar[bool] = True
    meaning: ClassVar[str] = "disparity offset proportional to the temperature change since calibration"
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "coeff_px_per_c": (0.0, "px/degC", "disparity offset per degree of temperature change"),
        "reference_c": (40.0, "degC", "temperature at which the device was calibrated"),
    }

    def shift_px(self, ctx: PixelContext) -> Array:
        t = np.asarray(ctx.temperature_c, dtype=np.float64)
        return np.asarray(self.params["coeff_px_per_c"] * (t - self.params["reference_c"]))
