"""Slant bias: a foreshortened window biases the match; disparity offset growing with tan^2(inclination)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class SlantBias(DisparityShift):
    """d_meas = d + offset_px_at_45 * tan^2(min(theta, max_deg)) (empirical; the second-order window term).

    A fronto-parallel matching window on a slanted surface sees the two views foreshortened
    differently; the match drifts with the slant's square (a symmetric window cancels the first
    order). `max_deg` stops the growth where the grazing pixels drop out anyway (tan^2 would reach
    30 at 80 deg).
    """

    name: ClassVar[str] = "slant_bias"
    meaning: ClassVar[str] = "disparity offset growing with tan^2 of the inclination"
    source: ClassVar[str] = ("fronto-parallel matching bias on slanted surfaces (Bleyer et al. 2011; "
                             "Intel 'Tuning depth cameras'); magnitude from the paper's Section 5.1 "
                             "(accuracy worsens with inclination)")
    OPTIONAL: ClassVar[frozenset[str]] = frozenset({"max_deg"})
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "offset_px_at_45": (0.0, "px", "disparity offset at 45 degrees (+ = too near)"),
        "max_deg": (89.0, "deg", "inclination beyond which the offset stops growing"),
    }

    def validate(self) -> None:
        if not 0 < self.params["max_deg"] < 90:
            raise ValueError(f"max_deg must lie in (0, 90) deg, got {self.params['max_deg']:g}")

    def shift_px(self, ctx: PixelContext) -> Array:
        inc = np.asarray(ctx.inclination_deg, dtype=np.float64)
        inc = np.radians(np.clip(inc, 0.0, self.params["max_deg"]))
        return np.asarray(self.params["offset_px_at_45"] * np.tan(inc) ** 2)
