"""Flying pixels: near depth edges the matching window mixes foreground and background."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from depthstation.simulate.effects.base import Array, Effect, PixelContext


class FlyingPixels(Effect):
    """With probability p = p_edge exp(-(e - 0.5) / width_px) (e = distance to the edge, 0.5 next to it)
    a pixel's depth is displaced by a uniform fraction in [-spread, +spread] of z.

    The displacement is symmetric (foreground pulled back, background pulled forward), so the
    signature is zero bias and variance p (spread z)^2 / 3.
    """

    name: ClassVar[str] = "flying_pixels"
    meaning: ClassVar[str] = "depth mixed across a depth edge within a few pixels of it"
    stage: ClassVar[int] = 50
    PARAMS: ClassVar[dict[str, tuple[float, str, str]]] = {
        "edge_probability": (0.3, "1", "probability for a pixel next to a depth edge"),
        "width_px": (1.0, "px", "decay length of the probability away from the edge"),
        "spread_ratio": (0.05, "1", "largest displacement as a fraction of z"),
    }

    def validate(self) -> None:
        if not 0 <= self.params["edge_probability"] <= 1 or self.params["width_px"] <= 0:
            raise ValueError("edge_probability in [0, 1] and width_px > 0 required")

    def probability(self, ctx: PixelContext) -> Array:
        e = np.asarray(ctx.edge_distance_px, dtype=np.float64)
        p = self.params["edge_probability"] * np.exp(-np.maximum(e - 0.5, 0.0) / self.params["width_px"])
        return np.broadcast_to(p, ctx.shape()).copy()

    def variance_m2(self, ctx: PixelContext) -> Array:
        z = np.asarray(ctx.z_m, dtype=np.float64)
        return np.broadcast_to(self.probability(ctx) * (self.params["spread_ratio"] * z) ** 2 / 3.0,
                               ctx.shape()).copy()

    def apply(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator) -> Array:
        def near() -> Array:
            p = np.broadcast_to(self.probability(ctx), z_m.shape).ravel()
            idx = np.flatnonzero(p > 1e-4)
            return np.stack([idx.astype(np.float64), p[idx]])
        table = self.cached(ctx, "near", near)
        if table.shape[1] == 0:
            return z_m
        idx = table[0].astype(np.int64)
        hit = rng.random(idx.size) < table[1]
        sel = idx[hit]
        flat = z_m.reshape(-1)
        flat[sel] *= (1.0 + self.params["spread_ratio"] * rng.uniform(-1.0, 1.0, sel.size)).astype(z_m.dtype)
        return z_m
