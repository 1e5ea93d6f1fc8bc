"""A periodic disparity bias along an image axis: a ripple fixed in the imager's pixels."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class PeriodicBias(DisparityShift):
    """d_meas = d + amplitude_px sin(2 pi c / period_px + phase_rad), c = u (axis 0) or v (axis 1).

    A ripple of tens of pixels fixed to the sensor: the sub-pixel interpolation's error repeating
    with the projector's dot pitch or a rectification-table interpolation grid, a readout pattern of
    one imager. Zero mean over whole periods, below the per-pixel noise: the per-column and per-row
    means of explain's locate (`fine.ripple`) find it, bins of a coarse image grid do not.
    """

    name: ClassVar[str] = "periodic_bias"
    meaning: ClassVar[str] = "a disparity ripple along an image axis (px), fixed in the imager's pixels"
    source: ClassVar[str] = ("sub-pixel interpolation error repeating with the dot pitch or a rectification "
                             "grid; found by explain's per-column / per-row spectrum")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "amplitude_px": (0.0, "px", "amplitude of the ripple (+ = depth too near at its crest)"),
        "period_px": (32.0, "px", "period along the axis, imager pixels"),
        "phase_rad": (0.0, "rad", "phase at pixel 0"),
        "axis": (0.0, "1", "0: along u (columns), 1: along v (rows)"),
    }

    def validate(self) -> None:
        p = self.params
        if p["period_px"] <= 0 or p["axis"] not in (0.0, 1.0) or not np.isfinite(p["amplitude_px"]):
            raise ValueError("period_px > 0, axis 0 (u) or 1 (v) and a finite amplitude_px required")

    def shift_px(self, ctx: PixelContext) -> Array:
        p = self.params
        c = np.asarray(ctx.u if p["axis"] == 0 else ctx.v, dtype=np.float64)
        return np.asarray(p["amplitude_px"] * np.sin(2 * np.pi * c / p["period_px"] + p["phase_rad"]))
