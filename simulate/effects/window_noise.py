"""Window noise: the block matcher's window makes neighbouring pixels share their disparity error."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, CorrelatedJitter, PixelContext


class WindowNoise(CorrelatedJitter):
    """Gaussian disparity noise of RMS `sigma_px` smoothed by a `window_px` x `window_px` box.

    Every depth pixel of a D4xx comes from a matching window (census 9 x 9 in Intel's presets, plus
    cost aggregation), so the noise of neighbours is shared: two pixels k_u, k_v apart correlate by
    (1 - |k_u|/w)(1 - |k_v|/w) (Keselman et al. 2017; Intel D400 visual presets). The mean over a
    region of N pixels therefore varies like N / w^2 independent pixels, not N: per-frame board
    means, plane-fit noise of small patches and explain's standard errors depend on it. Per pixel
    the variance is that of `disparity_noise` with the same sigma.
    """

    name: ClassVar[str] = "window_noise"
    meaning: ClassVar[str] = "disparity noise shared by neighbouring pixels through the matching window"
    source: ClassVar[str] = ("Keselman et al. 2017 (census + box aggregation); Intel D400 visual "
                             "presets (9 x 9 census window)")
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "sigma_px": (0.0, "px", "RMS of the window-correlated disparity noise"),
        "window_px": (9.0, "px", "width of the matching window (census 9 x 9 on the D4)"),
    }

    def validate(self) -> None:
        if self.params["sigma_px"] < 0 or not 1 <= self.params["window_px"] <= 64:
            raise ValueError("sigma_px >= 0 and window_px, the matching window's width, in 1..64 px required "
                             f"(got {self.params['window_px']:g})")

    def sigma_px(self, ctx: PixelContext) -> Array:
        return np.asarray(self.params["sigma_px"])
