"""The structure of the noise, not only its size: frame-common part, within-frame part, neighbours.

Each sample's error is split as e_fp = mean_p + K_p c_f + w_fp (Searle's two-way decomposition,
research note §3.4): mean_p the pixel's mean over the frames (static: bias and frozen pattern),
c_f the frame's common part in disparity units (px; K = z^2/(fB) converts it to metres, so a
disparity shift common to the frame is removed exactly on a slanted board) and w_fp the rest, the
within-frame noise. Neighbouring pixels share w_fp when a matching window makes them (window
noise); the correlation along u and v at a few lags gives the window's width and the design factor
D of a regional mean: Var(mean of N pixels) = sigma^2 D / N, N / D its effective sample size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from depthstation.evaluate.explain.samples import FloatArray, IntArray, Samples

LAGS_U = (1, 2, 3, 5, 8, 13, 21)              # multiples of the horizontal sample spacing
LAGS_V = (1, 2, 3, 5, 8, 13, 21, 34)           # depth-image rows
PAIR_FRAMES = 6                                # frames per standpoint the correlation is measured on
MIN_PAIRS = 200
WINDOWS = np.arange(1.0, 64.01, 0.5)           # stereo px tried for the window's width


@dataclass
class Correlation:
    """Neighbour correlation of the within-frame noise along u and v and its box-window model.

    rho(k_u, k_v) = fraction (1 - |k_u|/w)+ (1 - |k_v|/w)+ for k != 0 (1 at k = 0): a share
    `fraction` of the variance is window-correlated, the rest white.
    """

    lags: dict[str, FloatArray] = field(default_factory=dict)     # axis -> lags (stereo px)
    rho: dict[str, FloatArray] = field(default_factory=dict)      # axis -> correlation per lag
    pairs: dict[str, IntArray] = field(default_factory=dict)
    fraction: float = 0.0
    window_px: float = 1.0

    def model(self, k: FloatArray) -> FloatArray:
        return np.asarray(self.fraction * np.clip(1.0 - np.abs(k) / self.window_px, 0.0, None))

    def design_factor(self, density: FloatArray | float, n: FloatArray | float) -> FloatArray:
        """D of the mean of n samples per frame at `density` samples per stereo px^2 (<= n)."""
        corr = np.minimum(1.0 + np.asarray(density) * (self.window_px ** 2 - 1.0), np.asarray(n, dtype=float))
        return np.asarray(np.maximum(1.0 - self.fraction + self.fraction * corr, 1.0))

    def to_dict(self) -> dict[str, object]:
        return {"window_px": self.window_px, "correlated_fraction": self.fraction,
                "rho": {a: {f"{k:.3g}": float(r) for k, r in zip(self.lags[a], self.rho[a], strict=True)}
                        for a in self.lags}}


@dataclass
class Structure:
    """One side's decomposition: per-sample within-frame deviation and frame-common part."""

    within: FloatArray        # w_fp (m); NaN where the pixel is seen in one frame only
    dev2: FloatArray          # unbiased w_fp^2 (m^2)
    common_px: FloatArray     # c_f of the sample's frame (px; + = too far)
    frame_id: IntArray        # index into the frame table
    frame_sp: IntArray        # per frame: standpoint
    frame_c: FloatArray       # per frame: c_f (px)
    frame_mean_m: FloatArray  # per frame: mean of e - mean_p over its pixels (m)
    frame_n: FloatArray       # per frame: pixels
    frame_k: FloatArray       # per frame: mean K (m/px)
    frame_halves: FloatArray  # per frame: c_f of the two interleaved halves of the board (F, 2)
    density: FloatArray       # per standpoint: samples per frame per stereo px^2
    corr: Correlation
    pairs: dict[tuple[str, float], tuple[IntArray, IntArray]] = field(default_factory=dict)


def _pixel_groups(s: Samples) -> tuple[IntArray, IntArray]:
    key = (s.standpoint * 100_000 + s.v_px) * 100_000 + s.u_px
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    return inv.ravel(), cnt


def _frames(s: Samples) -> tuple[IntArray, IntArray]:
    """Frame index (0..F-1 over the session) of every sample and the standpoint of each frame."""
    _, first, inv = np.unique(s.frame_key, return_index=True, return_inverse=True)
    return inv.ravel(), s.standpoint[first]


def _pair_frames(s: Samples, per_standpoint: int) -> np.ndarray:
    """Samples of at most `per_standpoint` frames of each standpoint, evenly spread (cost bound)."""
    keep = np.zeros(len(s), dtype=bool)
    for sp in np.unique(s.standpoint):
        m = np.flatnonzero(s.standpoint == sp)
        frames = np.unique(s.frame[m])
        picks = np.linspace(0, len(frames) - 1, min(per_standpoint, len(frames))).astype(int)
        chosen = frames[np.unique(picks)]
        keep[m[np.isin(s.frame[m], chosen)]] = True
    return keep


def neighbour_pairs(s: Samples, per_standpoint: int = PAIR_FRAMES
                    ) -> dict[tuple[str, float], tuple[IntArray, IntArray]]:
    """Sample pairs of the same frame a few depth-image pixels apart along u or v (key: axis and the
    lag in stereo px). Along u the lags are multiples of the samples' own spacing (a strided raster)."""
    use = np.flatnonzero(_pair_frames(s, per_standpoint))
    if use.size < 2:
        return {}
    key = (s.frame_key[use] * 100_000 + s.v_px[use]) * 100_000 + s.u_px[use]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    du = np.diff(ks)
    du = du[(du > 0) & (du < 100)]
    step = int(np.median(du)) if du.size else 1
    out: dict[tuple[str, float], tuple[IntArray, IntArray]] = {}
    for axis, lags, unit in (("u", [step * k for k in LAGS_U], 1), ("v", list(LAGS_V), 100_000)):
        for lag in lags:
            q = key + lag * unit
            pos = np.clip(np.searchsorted(ks, q), 0, len(ks) - 1)
            hit = ks[pos] == q
            if hit.sum() >= MIN_PAIRS:
                out[(axis, float(lag * s.px_scale))] = (use[hit], use[order[pos[hit]]])
    return out


def fit_window(lags: FloatArray, rho: FloatArray, weights: FloatArray) -> tuple[float, float]:
    """Least-squares fraction and width of rho(k) = fraction (1 - k/w)+ over a grid of widths."""
    if lags.size == 0 or not np.isfinite(rho).any() or float(np.nanmax(rho)) < 0.03:
        return 0.0, 1.0
    ok = np.isfinite(rho)
    k, r, wt = lags[ok], rho[ok], weights[ok]
    best = (np.inf, 0.0, 1.0)
    for w in WINDOWS:
        t = np.clip(1.0 - k / w, 0.0, None)
        den = float((wt * t * t).sum())
        frac = float(np.clip((wt * t * r).sum() / den, 0.0, 1.0)) if den > 0 else 0.0
        sse = float((wt * (r - frac * t) ** 2).sum())
        if sse < best[0] - 1e-15:
            best = (sse, frac, float(w))
    return best[1], best[2]


def decompose(s: Samples) -> Structure:
    """Split every sample's error into pixel mean, frame-common part and within-frame noise."""
    n_s = len(s)
    pix, cnt = _pixel_groups(s)
    mean = np.bincount(pix, weights=s.err_m, minlength=len(cnt)) / np.maximum(cnt, 1)
    r = s.err_m - mean[pix]
    n = cnt[pix].astype(np.float64)
    seen = n >= 2
    k = s.k_m_per_px
    fid, fsp = _frames(s)
    nf = len(fsp)
    wts = seen.astype(np.float64)
    fn = np.bincount(fid, weights=wts, minlength=nf)
    fc = np.bincount(fid, weights=np.where(seen, r / k, 0.0), minlength=nf) / np.maximum(fn, 1)
    fmean = np.bincount(fid, weights=np.where(seen, r, 0.0), minlength=nf) / np.maximum(fn, 1)
    fk = np.bincount(fid, weights=np.where(seen, k, 0.0), minlength=nf) / np.maximum(fn, 1)
    within = np.where(seen, r - k * fc[fid], np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        dev2 = np.where(seen, within ** 2 * n / (n - 1), np.nan)
    # sampling density per standpoint: samples per frame over the board's area (stereo px^2)
    n_sp = max(int(s.standpoint.max()) + 1, 1) if n_s else 1
    density = np.zeros(n_sp)
    for sp in np.unique(s.standpoint):
        m = s.standpoint == sp
        pts = np.stack([s.u_px[m], s.v_px[m]], axis=1).astype(np.int32)
        area = float(cv2.contourArea(cv2.convexHull(pts))) if len(pts) >= 3 else 0.0
        frames = len(np.unique(s.frame[m]))
        density[sp] = (m.sum() / max(frames, 1)) / max(area * s.px_scale ** 2, 1.0)
    pairs = neighbour_pairs(s)
    corr = Correlation()
    for axis in ("u", "v"):
        items = sorted((lag, ij) for (a, lag), ij in pairs.items() if a == axis)
        lags = np.array([lag for lag, _ in items])
        rho = np.array([_corr(within, i, j) for _, (i, j) in items])
        npairs = np.array([len(i) for _, (i, _) in items], dtype=np.int64)
        corr.lags[axis], corr.rho[axis], corr.pairs[axis] = lags, rho, npairs
    all_l = np.concatenate([corr.lags[a] for a in corr.lags]) if corr.lags else np.zeros(0)
    all_r = np.concatenate([corr.rho[a] for a in corr.rho]) if corr.rho else np.zeros(0)
    all_n = np.concatenate([corr.pairs[a] for a in corr.pairs]) if corr.pairs else np.zeros(0)
    corr.fraction, corr.window_px = fit_window(all_l, all_r, np.sqrt(all_n.astype(np.float64)))
    # two halves of the board interleaved as a checkerboard of tiles three windows wide: the
    # frame-common part is in both halves' means, the within-frame noise (nearly) in one only
    tile = max(3.0 * corr.window_px, 8.0)
    half = ((np.floor(s.u / tile) + np.floor(s.v / tile)) % 2).astype(np.int64)
    halves = np.zeros((nf, 2))
    for h in (0, 1):
        m = seen & (half == h)
        cnt_h = np.bincount(fid[m], minlength=nf)
        halves[:, h] = np.bincount(fid[m], weights=(r / k)[m], minlength=nf) / np.maximum(cnt_h, 1)
        halves[cnt_h == 0, h] = np.nan
    return Structure(within, dev2, fc[fid], fid, fsp, fc, fmean, fn.astype(np.float64), fk, halves, density,
                     corr, pairs)


def _corr(x: FloatArray, i: IntArray, j: IntArray) -> float:
    a, b = x[i], x[j]
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < MIN_PAIRS:
        return float("nan")
    den = float(np.sqrt((a[ok] ** 2).sum() * (b[ok] ** 2).sum()))
    return float((a[ok] * b[ok]).sum() / den) if den > 0 else float("nan")


@dataclass
class FrameCommon:
    """Per standpoint: variance of the part common to all pixels of a frame (px^2).

    Estimated as the covariance over frames of the two interleaved halves' means (Searle's
    split-half moment): the frame-common part is in both, the within-frame noise, correlated only
    over a window, in one. No model of the correlation is needed, and it is unbiased (zero when
    nothing is common).
    """

    standpoint: IntArray
    frames: IntArray
    excess_px2: FloatArray     # the frame-common variance sigma_a^2 (px^2), may be < 0 by chance
    var_px2: FloatArray        # variance of the frames' mean over the whole board (px^2)
    se_px2_: FloatArray        # standard error of excess_px2
    k_m: FloatArray            # mean K (m/px) of the standpoint
    half_px2: FloatArray = field(default_factory=lambda: np.zeros(0))  # each half's own noise (px^2)

    def se_null(self, common_px2: FloatArray) -> FloatArray:
        """SE of `excess_px2` when the true common variance is `common_px2` (0: nothing common)."""
        c = np.clip(common_px2, 0.0, None)
        return np.asarray(np.sqrt(((self.half_px2 + c) ** 2 + c ** 2) / np.maximum(self.frames - 1, 1)))

    def se_px2(self) -> FloatArray:
        return self.se_px2_


def frame_common(s: Samples, st: Structure) -> FrameCommon:
    """The frame-common variance of every standpoint with at least three frames."""
    sps, frames, excess, var, ses, kk, se0 = [], [], [], [], [], [], []
    for sp in np.unique(st.frame_sp):
        f = np.flatnonzero((st.frame_sp == sp) & (st.frame_n > 0) & np.isfinite(st.frame_halves).all(axis=1))
        if len(f) < 3:
            continue
        a, b = st.frame_halves[f, 0], st.frame_halves[f, 1]
        c = float(np.cov(a, b, ddof=1)[0, 1])
        va, vb = float(np.var(a, ddof=1)), float(np.var(b, ddof=1))
        sps.append(sp)
        frames.append(len(f))
        excess.append(c)
        var.append(float(np.var(st.frame_c[f], ddof=1)))
        ses.append(float(np.sqrt((va * vb + c * c) / (len(f) - 1))))
        # the halves' difference has no common part: half its variance is each half's own noise,
        # which sets the spread of the covariance when nothing is common (the test's null)
        se0.append(float(np.var(a - b, ddof=1)) / 2)
        kk.append(float(np.mean(st.frame_k[f])))
    arr = np.asarray
    return FrameCommon(arr(sps, dtype=np.int64), arr(frames, dtype=np.int64), arr(excess, dtype=float),
                       arr(var, dtype=float), arr(ses, dtype=float), arr(kk, dtype=float),
                       arr(se0, dtype=float))
