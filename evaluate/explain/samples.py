"""Per-pixel error samples of one session (real or simulated), the common input of locate and attribute.

Explain never looks at images: it compares two tables of pixels seen on the board, one from the
real capture and one from the simulation of the same standpoints, evaluated the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from itertools import pairwise
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class Samples:
    """One row per (frame, pixel) on the board; `err_m` = measured - reference z-depth (+ = too far).

    `standpoint` indexes `names`. `albedo` is the reflectance of the square (the print's
    albedo as the simulator renders it: low on black squares, high on white ones; >= 0.5 = white). Time is
    seconds since the start of the session (so drift across standpoints shows); temperature is NaN
    where the source has none; `edge_px` is the distance to the nearest depth edge (inf if none).
    """

    standpoint: IntArray
    frame: IntArray
    u: FloatArray
    v: FloatArray
    z_ref_m: FloatArray
    err_m: FloatArray
    inclination_deg: FloatArray
    albedo: FloatArray
    time_s: FloatArray
    temperature_c: FloatArray
    edge_px: FloatArray
    ref_err_m: FloatArray            # simulated side only: estimated minus true reference z (else 0)
    u_px: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # depth-image pixel
    v_px: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    names: list[str] = field(default_factory=list)
    fx: float = 640.0
    ppx: float = 320.0
    ppy: float = 180.0
    baseline_m: float = 0.095
    px_scale: float = 1.0            # stereo-imager pixels per depth-image pixel (aligned depth: < 1)
    time_stamps: bool = True         # False: the frames carry no clock of the session (time_s is 0)

    ARRAYS = ("standpoint", "frame", "u", "v", "z_ref_m", "err_m", "inclination_deg", "albedo",
              "time_s", "temperature_c", "edge_px", "ref_err_m", "u_px", "v_px")

    def __post_init__(self) -> None:
        # the depth image's own pixel lattice (neighbours for the spatial correlation of the noise)
        if self.u_px.size != self.err_m.size:
            self.u_px = np.round(self.u).astype(np.int64)
        if self.v_px.size != self.err_m.size:
            self.v_px = np.round(self.v).astype(np.int64)

    def __len__(self) -> int:
        return int(self.err_m.size)

    @classmethod
    def build(cls, *, names: Sequence[str], fx: float, ppx: float, ppy: float, baseline_m: float,
              standpoint: Any, frame: Any, u: Any, v: Any, z_ref_m: Any, err_m: Any,
              inclination_deg: Any, albedo: Any, time_s: Any = None, temperature_c: Any = None,
              edge_px: Any = None, ref_err_m: Any = None, u_px: Any = None, v_px: Any = None,
              px_scale: float = 1.0) -> Samples:
        """Arrays of any dtype in, float64/int64 out; optional axes default to 0, NaN and inf;
        depth-image pixels default to the rounded u, v (no alignment: the same lattice)."""
        n = int(np.asarray(err_m).size)

        def f(a: Any, default: float) -> FloatArray:
            if a is None:
                return np.full(n, default)
            return np.broadcast_to(np.asarray(a, dtype=np.float64).ravel(), (n,)).copy()

        return cls(
            standpoint=np.broadcast_to(np.asarray(standpoint, dtype=np.int64).ravel(), (n,)).copy(),
            frame=np.broadcast_to(np.asarray(frame, dtype=np.int64).ravel(), (n,)).copy(),
            u=f(u, 0.0), v=f(v, 0.0), z_ref_m=f(z_ref_m, np.nan), err_m=f(err_m, np.nan),
            inclination_deg=f(inclination_deg, 0.0), albedo=f(albedo, 1.0), time_s=f(time_s, 0.0),
            temperature_c=f(temperature_c, np.nan), edge_px=f(edge_px, np.inf),
            ref_err_m=f(ref_err_m, 0.0),
            u_px=np.rint(f(u_px if u_px is not None else u, 0.0)).astype(np.int64),
            v_px=np.rint(f(v_px if v_px is not None else v, 0.0)).astype(np.int64),
            names=list(names), fx=float(fx), ppx=float(ppx), ppy=float(ppy), baseline_m=float(baseline_m),
            px_scale=float(px_scale),
        )

    def subset(self, mask: NDArray[Any]) -> Samples:
        """The rows where `mask` holds (bool mask or index array), same names and camera."""
        return replace(self, **{k: getattr(self, k)[mask] for k in self.ARRAYS})

    @property
    def disparity_px(self) -> FloatArray:
        """True disparity f*B/z of every sample (px)."""
        return self.fx * self.baseline_m / self.z_ref_m

    @property
    def k_m_per_px(self) -> FloatArray:
        """dz/dd = z^2/(f B): metres of z-depth per pixel of disparity at each sample."""
        return self.z_ref_m ** 2 / (self.fx * self.baseline_m)

    @property
    def frame_key(self) -> IntArray:
        """A unique id per (standpoint, frame): the unit of independence for standard errors."""
        return self.standpoint * 1_000_000 + self.frame

    def frame_index(self) -> tuple[IntArray, IntArray]:
        """Per sample its frame's index 0..F-1 (frames of all standpoints), and each frame's standpoint.

        Kept once per table (the locate tests group by frame hundreds of times).
        """
        cached = self.__dict__.get("_frame_index")
        if cached is None or cached[0].size != self.err_m.size:
            _, first, inv = np.unique(self.frame_key, return_index=True, return_inverse=True)
            cached = (inv.ravel().astype(np.int64), self.standpoint[first])
            self.__dict__["_frame_index"] = cached
        return cached

    def context(self) -> dict[str, Any]:
        """Keyword arguments of a `simulate.effects.base.PixelContext` for these samples."""
        return {
            "z_m": self.z_ref_m, "inclination_deg": self.inclination_deg, "u": self.u, "v": self.v,
            "albedo": self.albedo, "time_s": self.time_s, "temperature_c": self.temperature_c,
            "edge_distance_px": self.edge_px, "fx": self.fx, "ppx": self.ppx, "ppy": self.ppy,
            "baseline_m": self.baseline_m,
        }


def concat(parts: Sequence[Samples]) -> Samples:
    """Join samples of several standpoints; standpoint indices are remapped onto the joined names."""
    if not parts:
        raise ValueError("no samples to join")
    names: list[str] = []
    arrays: dict[str, list[Any]] = {k: [] for k in Samples.ARRAYS}
    for p in parts:
        remap = np.empty(max(len(p.names), 1), dtype=np.int64)
        for i, nm in enumerate(p.names):
            if nm not in names:
                names.append(nm)
            remap[i] = names.index(nm)
        for k in Samples.ARRAYS:
            a = getattr(p, k)
            arrays[k].append(remap[a] if k == "standpoint" and len(p.names) else a)
    first = parts[0]
    kw = {k: np.concatenate(v) for k, v in arrays.items()}
    return Samples(**kw, names=names, fx=first.fx, ppx=first.ppx, ppy=first.ppy,
                   baseline_m=first.baseline_m, px_scale=first.px_scale,
                   time_stamps=all(p.time_stamps for p in parts))


def session_clock(spans_ns: Sequence[Sequence[int]]) -> bool:
    """Whether the frames' time stamps (one list per standpoint) are a clock of the session:
    standpoints recorded one after another never share an instant, and a camera's clock never reads
    exactly 0 (a PNG folder's nominal stamps k / fps start at 0 in every standpoint). Without one,
    no test or term runs along time: time within a standpoint would only repeat the frame's position."""
    spans = sorted((min(ts), max(ts)) for ts in spans_ns if len(ts))
    if not spans or any(lo == 0 for lo, _ in spans):
        return False
    return all(b[0] > a[1] for a, b in pairwise(spans))


def without_clock(s: Samples) -> Samples:
    """`s` with no time axis (time_s 0, `time_stamps` False): the inputs carry no session clock."""
    return replace(s, time_s=np.zeros_like(s.time_s), time_stamps=False)


def align_standpoints(real: Samples, sim: Samples) -> IntArray:
    """Per sim sample its standpoint's index in the real side's `names` (-1 where real lacks it).

    Why: each side numbers only the standpoints that gave board pixels, so when one side loses a
    standpoint (the board not found in its frames) the same index names different standpoints on
    the two sides. Every comparison pairs standpoints by name through this map.
    """
    return standpoint_map(real, sim)[sim.standpoint]


def standpoint_map(real: Samples, sim: Samples) -> IntArray:
    """Per index of `sim.names` the index of the same standpoint in `real.names` (-1: none)."""
    idx = {n: i for i, n in enumerate(real.names)}
    return np.array([idx.get(n, -1) for n in sim.names] or [-1], dtype=np.int64)


def frame_positions(s: Samples, like: Samples | None = None) -> tuple[IntArray, IntArray]:
    """Per sample: the position of its frame among its standpoint's frames, and how many there are.

    With `like` (the real side), the frames of each standpoint are `like`'s (matched by name): the
    simulation renders the real frames' own indices, but a simulated frame that lost its board would
    otherwise move every later frame one place earlier on that side only.
    """
    ref = s if like is None else like
    sp = s.standpoint if like is None else align_standpoints(like, s)
    pos = np.zeros(len(s), dtype=np.int64)
    count = np.ones(len(s), dtype=np.int64)
    for k in np.unique(sp):
        m = sp == k
        frames = np.unique(ref.frame[ref.standpoint == k]) if k >= 0 else np.zeros(0, dtype=np.int64)
        if frames.size == 0:   # a standpoint the reference lacks: its own frames
            frames = np.unique(s.frame[m])
        pos[m] = np.clip(np.searchsorted(frames, s.frame[m]), 0, frames.size - 1)
        count[m] = frames.size
    return pos, count


def unpaired_standpoints(real: Samples, sim: Samples) -> tuple[list[str], list[str]]:
    """(standpoints only the real side has, only the simulated side has): left out of every test."""
    return ([n for n in real.names if n not in sim.names], [n for n in sim.names if n not in real.names])


def thin(s: Samples, max_per_frame: int) -> Samples:
    """Keep a fixed sub-lattice of pixels so each frame has at most `max_per_frame` samples.

    The same pixels are kept in every frame of a standpoint, so per-pixel temporal variances stay
    computable; a lattice (not a random draw) keeps the thinning reproducible.
    """
    if len(s) == 0:
        return s
    counts = np.bincount(np.unique(s.frame_key, return_inverse=True)[1])
    worst = int(counts.max())
    if worst <= max_per_frame:
        return s
    step = int(np.ceil(np.sqrt(worst / max_per_frame)))
    keep = (s.u_px % step == 0) & (s.v_px % step == 0)
    return s.subset(keep)


def board_edge_px(u_px: IntArray, v_px: IntArray, shape: tuple[int, int]) -> FloatArray:
    """Distance (depth-image px) of each pixel to the outline of the board region they span.

    The region is the convex hull of the pixels (the board is a convex quadrilateral; square edges
    and ChArUco markers left out of the samples would otherwise count as edges).
    """
    if u_px.size < 3:
        return np.full(u_px.size, np.inf)
    h, w = shape
    pts = np.stack([np.clip(u_px, 0, w - 1), np.clip(v_px, 0, h - 1)], axis=1).astype(np.int32)
    hull = cv2.convexHull(pts)
    mask = np.zeros((h + 2, w + 2), dtype=np.uint8)
    cv2.fillConvexPoly(mask, hull + 1, 1)
    dist = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
    return np.asarray(dist[pts[:, 1] + 1, pts[:, 0] + 1], dtype=np.float64)


def samples_field_names() -> list[str]:
    return [f.name for f in fields(Samples)]
