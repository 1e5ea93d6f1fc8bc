"""Flying pixels: near depth edges the matching window mixes foreground and background."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class FlyingPixels(Effect):
    """With probability p = p_edge exp(-(e - 0.5) / width_px) (e = distance to the edge, 0.5 next to it)
    a pixel's depth is displaced by a uniform fraction in [-spread, +spread] of z.

    The displacement is symmetric (foreground pulled back, background pulled forward), so the
    signature is zero bias and variance p (spread z)^2 / 3.
    """

    name: ClassVar[str] = "flying_pixels"
    meaning: ClassVar[str] = "depth mixed across a depth edge within a few pixels of it"
    source: ClassVar[str] = ("matching window straddling a depth edge (Intel depth post-processing "
                             "white paper; edge pixels mixed)")
    stage: ClassVar[int] = 50
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "edge_probability": (0.3, "1", "probability for a pixel next to a depth edge"),
        "width_px": (1.0, "px", "decay length of the probability away from the edge"),
        "spread_ratio": (0.05, "1", "largest displacement as a fraction of z"),
    }

    def validate(self) -> None:
        if not 0 <= self.params["edge_probability"] <= 1 or self.params["width_px"] <= 0:
            raise ValueError("edge_probability in [0, 1] and width_px > 0 required")
        if not 0 <= self.params["spread_ratio"] <= 1:  # 5 (per cent as a ratio) threw pixels to 7.8 m
            raise ValueError(f"spread_ratio is a fraction of z (0 to 1), got {self.params['spread_ratio']:g}")

    def probability(self, ctx: PixelContext) -> Array:
        return np.broadcast_to(self.probability_of_distance(ctx.edge_distance_px), ctx.shape()).copy()

    def variance_m2(self, ctx: PixelContext) -> Array:
        z = np.asarray(ctx.z_m, dtype=np.float64)
        return np.broadcast_to(self.probability(ctx) * (self.params["spread_ratio"] * z) ** 2 / 3.0,
                               ctx.shape()).copy()

    def near_table(self, ctx: PixelContext, shape: tuple[int, ...]) -> tuple[NDArray[np.int64], Array]:
        """(flat pixel index, probability) of the pixels with p > 1e-4: the few near an edge.

        Only pixels within the distance where p can exceed 1e-4 are evaluated (the probability
        falls with the distance), which gives the same table as evaluating every pixel."""
        e = np.asarray(ctx.edge_distance_px)
        pe, width = self.params["edge_probability"], self.params["width_px"]
        if e.ndim == 0 or pe <= 1e-4:
            p = np.broadcast_to(self.probability_of_distance(e), shape).ravel()
            idx = np.flatnonzero(p > 1e-4)
            return idx, p[idx]
        reach = 0.5 + width * float(np.log(pe / 1e-4)) + 1.0  # beyond it p < 1e-4 (margin of 1 px)
        flat = np.broadcast_to(e, shape).ravel()
        cand = np.flatnonzero(flat < reach)
        p = self.probability_of_distance(flat[cand])
        keep = p > 1e-4
        return cand[keep], p[keep]

    def probability_of_distance(self, edge_distance_px: Any) -> Array:
        """The probability at these distances to the nearest depth edge (px)."""
        e = np.asarray(edge_distance_px, dtype=np.float64)
        return np.asarray(self.params["edge_probability"]
                          * np.exp(-np.maximum(e - 0.5, 0.0) / self.params["width_px"]))

    def displace(self, table: tuple[NDArray[np.int64], Array], z_m: Array, rng: np.random.Generator) -> Array:
        """Draw this frame's flying pixels from a `near_table` and displace them in z_m (in place)."""
        idx, p = table
        if idx.size == 0:
            return z_m
        hit = rng.random(idx.size) < p
        sel = idx[hit]
        flat = z_m.reshape(-1)
        flat[sel] *= (1.0 + self.params["spread_ratio"] * rng.uniform(-1.0, 1.0, sel.size)).astype(z_m.dtype)
        return z_m

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        table = self.cached(ctx, "near", lambda: self.near_table(ctx, z_m.shape))
        return self.displace(table, z_m, rng)
