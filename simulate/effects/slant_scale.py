"""Slant scale: the depth of a slanted surface reads long in proportion to z (1/cos(theta) - 1)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityShift, PixelContext


class SlantScale(DisparityShift):
    """z_meas = z (1 + k (1/cos(min(theta, max_deg)) - 1)): d_meas = d / (1 + g), g = k (1/cos - 1).

    A fronto-parallel matching window on a slanted surface covers a patch 1/cos(theta) longer along
    the slant than head-on; with the dot pattern's weight spread unevenly over it the match drifts,
    in proportion to the patch's depth range, i.e. to z (1/cos(theta) - 1) (the form explain's
    `slant_bias` candidate fits: "window foreshortening on slanted surfaces: bias z (1/cos - 1)").
    The sign and size are empirical: k = +2 % (too far) reproduces the paper's finding that accuracy
    worsens with inclination at every distance (Section 5.1) where the unit's depth scale,
    foreshortened by cos(theta) in the orthogonal deviation, would otherwise make it improve.
    `max_deg` stops the growth where grazing pixels drop out anyway.
    """

    name: ClassVar[str] = "slant_scale"
    meaning: ClassVar[str] = "depth bias k z (1/cos(inclination) - 1): the slanted window's drift"
    source: ClassVar[str] = ("fronto-parallel matching on slanted surfaces (Bleyer et al. 2011, "
                             "PatchMatch stereo); size from the paper's Section 5.1 (accuracy worsens "
                             "with inclination)")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "k": (0.0, "1", "relative depth error per unit of (1/cos(theta) - 1); + = too far"),
        "max_deg": (75.0, "deg", "inclination beyond which the error stops growing"),
    }

    def validate(self) -> None:
        if not -0.5 < self.params["k"] < 0.5 or not 0 < self.params["max_deg"] < 90:
            raise ValueError("k relative (-0.5 to 0.5) and max_deg in (0, 90) deg required")

    def growth(self, ctx: PixelContext) -> Array:
        inc = np.nan_to_num(np.asarray(ctx.inclination_deg, dtype=np.float64), nan=0.0)
        inc = np.radians(np.clip(inc, 0.0, self.params["max_deg"]))
        return np.asarray(self.params["k"] * (1.0 / np.cos(inc) - 1.0))

    def shift_px(self, ctx: PixelContext) -> Array:
        g = self.growth(ctx)
        return np.asarray(ctx.disparity_px() * (1.0 / (1.0 + g) - 1.0))
