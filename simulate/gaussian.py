"""Standard normal float32 draws for whole images: a 256-layer ziggurat fed by a numpy Generator.

Why: every simulated depth frame draws two images of Gaussian noise (white matching noise and the
window-correlated field, ~620 k values at 640x480), and numpy's `standard_normal(dtype=float32)`
takes ~12 ns per value on our 2-core machines, ~8 ms of a ~60 ms frame. Here the Generator only
supplies raw 64-bit words (two 32-bit draws each) and a compiled ziggurat turns them into normals
at a few ns each. The randomness still comes from the caller's Generator, so a frame depends on
its seed only, never on threads.

Method: Marsaglia & Tsang (2000), "The ziggurat method for generating random variables", 256
layers (r = 3.6541528853610088, v = 4.92867323399e-3). A 32-bit draw gives the layer (8 bits),
the sign (1 bit) and a 23-bit uniform, the resolution of numpy's own float32 ziggurat. About 1 %
of draws land in a wedge or the tail; their exact rejection tests use 53-bit uniforms from a pool
of further raw words. Tail: Marsaglia (1964).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

LAYERS = 256
R = 3.6541528853610088  # right edge of the base layer
V = 4.92867323399e-3  # area of each layer


@lru_cache(maxsize=1)
def tables() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(x, f): x[0] the base layer's equivalent width v / f(r), x[i] the right edge of layer i
    (x[1] = r, decreasing, x[256] = 0), f = exp(-x^2 / 2) at each."""
    x = np.zeros(LAYERS + 1)
    x[1] = R
    for i in range(1, LAYERS - 1):
        x[i + 1] = math.sqrt(-2.0 * math.log(V / x[i] + math.exp(-0.5 * x[i] * x[i])))
    x[0] = V / math.exp(-0.5 * R * R)
    x[LAYERS] = 0.0
    return x, np.exp(-0.5 * x * x)


@njit(cache=True, nogil=True)
def _uniform(pool: Any, k: int) -> float:  # pragma: no cover - compiled
    """A uniform in (0, 1] from pool word k (53 bits)."""
    return ((pool[k] >> np.uint64(11)) + 1) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True)
def _ziggurat(words: Any, pool: Any, x: Any, f: Any, out: Any, start: int) -> int:  # pragma: no cover
    """Fill out[start:] from 32-bit words (one each, on the fast path) and the pool (wedges, tail,
    retries). Returns the index reached: len(out) when done, else the pool ran dry there."""
    n = out.shape[0]
    k = 0  # next pool word
    m = pool.shape[0]
    scale = 1.0 / 8388608.0  # 2^-23
    for i in range(start, n):
        w = np.uint64(words[i])
        while True:
            layer = int(w & np.uint64(0xFF))
            neg = (w >> np.uint64(8)) & np.uint64(1)
            u = float(w >> np.uint64(9)) * scale  # [0, 1), 23 bits
            v = u * x[layer]
            if v < x[layer + 1]:
                break  # inside the layer's rectangle under the curve
            if layer == 0:  # the tail beyond r
                while True:
                    if k + 2 > m:
                        return i
                    t = -math.log(_uniform(pool, k)) / x[1]
                    s = -math.log(_uniform(pool, k + 1))
                    k += 2
                    if s + s > t * t:
                        break
                v = x[1] + t
                break
            if k + 2 > m:
                return i
            y = f[layer] + (1.0 - _uniform(pool, k)) * (f[layer + 1] - f[layer])
            k += 1
            if y < math.exp(-0.5 * v * v):
                break  # the wedge's point lies under the curve
            w = pool[k] & np.uint64(0xFFFFFFFF)  # rejected: a new 32-bit draw
            k += 1
        out[i] = np.float32(-v if neg else v)
    return n


def standard_normal(rng: np.random.Generator, shape: int | tuple[int, ...]) -> NDArray[np.float32]:
    """float32 standard normals of `shape` from the Generator's raw words."""
    size = int(np.prod(shape))
    out = np.empty(size, np.float32)
    words = rng.bit_generator.random_raw((size + 1) // 2).view(np.uint32)[:size]
    x, f = tables()
    done = 0
    while done < size:
        pool = rng.bit_generator.random_raw(max(256, (size - done) // 16))
        done = _ziggurat(words, pool, x, f, out, done)
    return out.reshape(shape)
