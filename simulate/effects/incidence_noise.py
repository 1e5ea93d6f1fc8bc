"""Incidence noise: the pattern comes back weaker from a slanted surface; matching noise grows as 1/cos."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, DisparityJitter, PixelContext


class IncidenceNoise(DisparityJitter):
    """Matching noise of RMS sigma_px / cos(theta)^exponent in all: adds sigma_px^2 (cos^-2p - 1).

    The D4's emitter sits between the imagers, so its dot pattern meets a surface at the same
    incidence theta as the rays: the irradiance falls as cos(theta), a Lambertian surface returns
    that fraction, and the dots are stretched over more pixels. The matcher's subpixel noise goes as
    the inverse of the texture's contrast-to-noise ratio (Grunnet-Jepsen et al., Intel white paper
    "Tuning depth cameras for best performance", 2018: RMS error ~ subpixel / texture SNR;
    Keselman et al. 2017), so in the read-noise-limited regime (exponent 1) the disparity noise
    grows as 1/cos(theta). Seen orthogonally to the surface (a plane fit's residual) the depth
    noise along the rays is foreshortened by cos(theta): the two cancel, which is why the paper
    finds "no apparent increase in noise with inclination" (Section 5.1), where a noise that did
    not grow would fall as cos(theta) (0.5 of head-on at 60 deg). `sigma_px` is the head-on
    matching noise this scales (the model's white + window noise, 0.08 px on the D455).
    """

    name: ClassVar[str] = "incidence_noise"
    meaning: ClassVar[str] = "matching noise grows as 1/cos(inclination)^exponent (less pattern light back)"
    source: ClassVar[str] = ("Intel 'Tuning depth cameras for best performance' (RMS ~ 1/texture SNR); "
                             "Lambertian return of the emitter's pattern; paper Section 5.1 (no "
                             "increase of noise with inclination)")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px": (0.0, "px", "head-on matching noise that grows with the incidence"),
        "exponent": (1.0, "1", "1: read-noise limited (contrast), 0.5: shot-noise limited"),
        "max_deg": (80.0, "deg", "inclination beyond which the growth stops (grazing pixels drop out)"),
    }

    def validate(self) -> None:
        if self.params["sigma_px"] < 0 or not 0 <= self.params["exponent"] <= 4 \
                or not 0 < self.params["max_deg"] < 90:
            raise ValueError("sigma_px >= 0, exponent in 0..4 and max_deg in (0, 90) required")

    def sigma_px(self, ctx: PixelContext) -> Array:
        inc = np.radians(np.clip(np.nan_to_num(np.asarray(ctx.inclination_deg, dtype=np.float64), nan=0.0),
                                 0.0, self.params["max_deg"]))
        grow = np.cos(inc) ** (-2.0 * self.params["exponent"]) - 1.0
        return np.asarray(self.params["sigma_px"] * np.sqrt(np.maximum(grow, 0.0)))
