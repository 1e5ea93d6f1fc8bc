"""Locate what the bins average away: periodic structure along u and v, a static per-pixel field
that repeats over the frames of a standpoint, and zero-mean gradients across the image.

The families of `locate` average a group's pixels; a ripple of a few tens of pixels, a frozen
speckle pattern of a standpoint, or a roll (delta ~ -f roll y, zero mean over the rows) cancel in
those means. Each test here works on the disparity residual delta = -err / K (px; + = nearer) at the
samples' own pixel lattice, real minus simulated, and takes its standard error from what is
independent: standpoints (one estimate each, their scatter) or, within a standpoint, tiles at least
2.5 matching windows wide (window-correlated noise stays inside a tile).

- periodic_u, periodic_v: per standpoint the column (row) profile of the residual, a quadratic
  removed (pose planes, focal mismatch); at each trial period a sine and cosine fitted per
  standpoint; their mean over standpoints tested against their scatter (Hotelling T^2, F with 2 and
  n - 2 dof); Bonferroni over the independent periods of the grid. A ripple fixed in the image adds
  the same phase in every standpoint; noise and pose errors do not.
- static: per standpoint the covariance over pixels of the mean residual of the even frames with
  that of the odd frames, a plane removed from each: a pattern that repeats in every frame is in
  both halves, temporal noise of any correlation in one. Real minus sim per standpoint (t from the
  scatter over tiles) and pooled (t over standpoints). Its correlation length comes from the same
  cross-covariance at pixel lags.
- gradient_u, gradient_v: the per-standpoint slope of the residual along u (v), real minus sim,
  pooled over standpoints (t with n - 1 dof). The reference pose's tilt error is random per
  standpoint and enters the scatter; what a session of n standpoints can detect is said
  (`detectable_px_per_px`: 2.8 SE, 80 % power at 5 %).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import fdtrc, stdtr

from depthstation.evaluate.explain.samples import FloatArray, Samples, standpoint_map
from depthstation.simulate.effects.base import PixelContext

MIN_PERIOD_PX = 6.0  # shortest trial period (px of the stereo imager)
MIN_LINES = 12  # columns (rows) a standpoint's profile needs
MIN_STANDPOINTS = 4
TILE_WINDOWS = 2.5  # a tile of the static test spans this many matching windows
DETECT = 2.8  # SE multiple a true effect needs for 80 % power at 5 % (two-sided)


def disparity_residual(s: Samples) -> FloatArray:
    """delta (px, + = nearer) of every sample: -err / K."""
    return np.asarray(-s.err_m / s.k_m_per_px, dtype=np.float64)


def _profiles(s: Samples, axis: str) -> dict[int, tuple[FloatArray, FloatArray, FloatArray]]:
    """Per standpoint: the lines' positions (px), mean delta per line and its sample count."""
    d = disparity_residual(s)
    line = s.u_px if axis == "u" else s.v_px
    pos = s.u if axis == "u" else s.v
    out = {}
    for k in np.unique(s.standpoint):
        m = (s.standpoint == k) & np.isfinite(d)
        if not m.any():
            continue
        keys, inv = np.unique(line[m], return_inverse=True)
        n = np.bincount(inv).astype(np.float64)
        out[int(k)] = (np.bincount(inv, weights=pos[m]) / n, np.bincount(inv, weights=d[m]) / n, n)
        del keys
    return out


def _paired_profiles(real: Samples, sim: Samples, axis: str) -> list[tuple[FloatArray, FloatArray]]:
    """(positions, real - sim mean delta) per standpoint both sides have, on the lines both see."""
    pr, ps = _profiles(real, axis), _profiles(sim, axis)
    to_real = standpoint_map(real, sim)
    sim_by_real = {int(to_real[k]): v for k, v in ps.items() if to_real[k] >= 0}
    out = []
    for k, (x, y, _) in pr.items():
        if k not in sim_by_real:
            continue
        xs, ys, _ = sim_by_real[k]
        common, ir, is_ = np.intersect1d(np.round(x, 3), np.round(xs, 3), return_indices=True)
        if common.size >= MIN_LINES:
            out.append((x[ir], y[ir] - ys[is_]))
    return out


@dataclass
class Ripple:
    period_px: float
    amplitude_px: float
    phase_rad: float
    amplitude_se_px: float
    p: float
    p_family: float
    standpoints: int
    periods_tried: int
    heldout_rmse_before_px: float = float("nan")
    heldout_rmse_after_px: float = float("nan")


def _detrend(x: FloatArray, y: FloatArray) -> FloatArray:
    xc = (x - x.mean()) / max(float(np.ptp(x)), 1.0)
    X = np.stack([np.ones_like(x), xc, xc**2], axis=1)
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return np.asarray(y - X @ beta)


def heldout(profiles: list[tuple[FloatArray, FloatArray]], period: float) -> tuple[float, float]:
    """RMS of each standpoint's profile (a quadratic removed) without and with the ripple fitted on
    the OTHER standpoints (leave one standpoint out), px."""
    fit = [(_ripple_fit([pr], period, 1), pr) for pr in profiles]
    ab = np.array([f[0][0][0] if f[0] is not None else (np.nan, np.nan) for f in fit])
    ok = np.isfinite(ab[:, 0])
    before, after, n = 0.0, 0.0, 0
    for i, (x, y) in enumerate(profiles):
        others = ok.copy()
        others[i] = False
        if others.sum() < 2:
            continue
        a, b = ab[others].mean(axis=0)
        w = 2 * np.pi * x / period
        before += float((_detrend(x, y) ** 2).sum())
        after += float((_detrend(x, y - a * np.cos(w) - b * np.sin(w)) ** 2).sum())
        n += x.size
    return (float(np.sqrt(before / n)), float(np.sqrt(after / n))) if n else (float("nan"), float("nan"))


def _ripple_fit(
    profiles: list[tuple[FloatArray, FloatArray]], period: float, min_n: int = MIN_STANDPOINTS
) -> tuple[FloatArray, int] | None:
    """Per standpoint (a, b) of a cos + b sin at `period`, beside a quadratic (pose, focal terms)."""
    ab = []
    for x, y in profiles:
        if np.ptp(x) < 2 * period:
            continue
        xc = (x - x.mean()) / max(float(np.ptp(x)), 1.0)
        w = 2 * np.pi * x / period
        X = np.stack([np.cos(w), np.sin(w), np.ones_like(x), xc, xc**2], axis=1)
        beta, *_ = np.linalg.lstsq(X, y, rcond=None)
        ab.append(beta[:2])
    if len(ab) < min_n:
        return None
    return np.array(ab), len(ab)


def ripple(real: Samples, sim: Samples, axis: str) -> Ripple | None:
    """The strongest periodic residual along `axis` common to the standpoints, and its p-value."""
    profiles = _paired_profiles(real, sim, axis)
    if len(profiles) < MIN_STANDPOINTS:
        return None
    span = float(np.median([np.ptp(x) for x, _ in profiles]))
    step = float(np.median([np.median(np.diff(np.sort(x))) for x, _ in profiles if x.size > 1]))
    lo = max(MIN_PERIOD_PX, 3 * step)
    if span / 2 <= lo:
        return None
    # frequencies oversampled 2x over the independent ones (1 / span apart)
    freqs = np.arange(1.0 / (span / 2), 1.0 / lo, 0.5 / span)
    independent = max(1, round((1.0 / lo - 2.0 / span) * span))
    best: Ripple | None = None
    for f in freqs:
        fit = _ripple_fit(profiles, 1.0 / f)
        if fit is None:
            continue
        ab, n = fit
        mean = ab.mean(axis=0)
        cov = np.cov(ab.T) / n
        try:
            t2 = float(mean @ np.linalg.solve(cov, mean))
        except np.linalg.LinAlgError:
            continue
        fstat = t2 * (n - 2) / (2 * (n - 1))
        p = float(fdtrc(2, n - 2, fstat))
        if best is None or p < best.p:
            amp = float(np.hypot(*mean))
            grad = mean / amp if amp > 0 else np.array([1.0, 0.0])
            se = float(np.sqrt(grad @ cov @ grad))
            best = Ripple(
                1.0 / f,
                amp,
                float(np.arctan2(mean[0], mean[1])),  # a cos + b sin = A sin(w x + phase)
                se,
                p,
                min(1.0, p * independent),
                n,
                independent,
            )
    if best is not None:
        best.heldout_rmse_before_px, best.heldout_rmse_after_px = heldout(profiles, best.period_px)
    return best


@dataclass
class StaticField:
    standpoint: str
    real_px2: float
    sim_px2: float
    diff_px2: float
    se_px2: float
    tiles: int
    correlation_px: float


def _half_means(s: Samples, k: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
    """Per pixel of standpoint k seen in both halves: u, v, mean delta of even and of odd frames,
    a plane in (u, v) removed from each half (the pose's static error, common drifts)."""
    m = s.standpoint == k
    d = disparity_residual(s)[m]
    odd = (s.frame[m] % 2).astype(np.int64)
    key = s.v_px[m].astype(np.int64) * 100_000 + s.u_px[m].astype(np.int64)
    means = []
    for h in (0, 1):
        sel = (odd == h) & np.isfinite(d)
        keys, inv = np.unique(key[sel], return_inverse=True)
        n = np.bincount(inv).astype(np.float64)
        means.append((keys, np.bincount(inv, weights=d[sel]) / n))
    common, i0, i1 = np.intersect1d(means[0][0], means[1][0], return_indices=True)
    if common.size < 50:
        return None
    uu = (common % 100_000).astype(np.float64) * s.px_scale
    vv = (common // 100_000).astype(np.float64) * s.px_scale
    X = np.stack([np.ones_like(uu), uu - uu.mean(), vv - vv.mean()], axis=1)
    out = []
    for y in (means[0][1][i0], means[1][1][i1]):
        beta, *_ = np.linalg.lstsq(X, y, rcond=None)
        out.append(y - X @ beta)
    return uu, vv, out[0], out[1]


def _cross_cov(
    uu: FloatArray, vv: FloatArray, a: FloatArray, b: FloatArray, tile_px: float
) -> tuple[float, float, int]:
    """Mean of a * b and its SE from the scatter over tiles (window-correlated noise stays in one)."""
    tile = np.floor(uu / tile_px).astype(np.int64) * 10_000 + np.floor(vv / tile_px).astype(np.int64)
    _, inv = np.unique(tile, return_inverse=True)
    n = np.bincount(inv).astype(np.float64)
    tm = np.bincount(inv, weights=a * b) / n
    mean = float((n * tm).sum() / n.sum())
    g = n.size
    if g < 3:
        return mean, float("inf"), g
    var = float((n**2 * (tm - mean) ** 2).sum() / n.sum() ** 2) * g / (g - 1)
    return mean, float(np.sqrt(var)), g


def _correlation_length(uu: FloatArray, vv: FloatArray, a: FloatArray, b: FloatArray) -> float:
    """Lag (px) at which the even/odd cross-covariance along u falls to 1/e of its value at 0."""
    c0 = float(np.mean(a * b))
    if c0 <= 0 or uu.size < 2:
        return float("nan")
    step = float(np.median(np.diff(np.unique(np.round(uu, 3))))) or 1.0
    iu = np.rint((uu - uu.min()) / step).astype(np.int64)
    iv = np.rint((vv - vv.min()) / step).astype(np.int64)
    ga = np.full((iv.max() + 1, iu.max() + 1), np.nan)
    gb = ga.copy()
    ga[iv, iu], gb[iv, iu] = a, b
    for lag in range(1, ga.shape[1] // 2):
        x = ga[:, lag:] * gb[:, :-lag] + gb[:, lag:] * ga[:, :-lag]
        ok = np.isfinite(x)
        if ok.sum() < 30:
            break
        if 0.5 * float(x[ok].mean()) < c0 / np.e:
            return float(lag * step)
    return float("nan")


def static_fields(real: Samples, sim: Samples, window_px: float = 9.0) -> list[StaticField]:
    """Per standpoint: the variance of the residual's part that repeats in every frame, real and sim."""
    tile = TILE_WINDOWS * window_px
    to_sim = {n: i for i, n in enumerate(sim.names)}
    out = []
    for k, name in enumerate(real.names):
        if name not in to_sim:
            continue
        hr, hs = _half_means(real, k), _half_means(sim, to_sim[name])
        if hr is None or hs is None:
            continue
        cr, ser, g = _cross_cov(*hr, tile)
        cs, ses, _ = _cross_cov(*hs, tile)
        out.append(
            StaticField(
                name,
                cr,
                cs,
                cr - cs,
                float(np.hypot(ser, ses)),
                g,
                _correlation_length(*hr) if cr - cs > 2 * np.hypot(ser, ses) else float("nan"),
            )
        )
    return out


def frame_slopes(s: Samples) -> dict[int, tuple[FloatArray, FloatArray]]:
    """Per standpoint the plane slopes of delta along u and along v of each of its frames (px per
    px; frames with 50 samples or more spanning 10 px both ways), from per-frame normal equations."""
    d = disparity_residual(s)
    ok = np.isfinite(d)
    fi, fsp = s.frame_index()
    fi, u, v, d = fi[ok], s.u[ok], s.v[ok], d[ok]
    nf = fsp.size

    def tot(w: FloatArray) -> FloatArray:
        return np.asarray(np.bincount(fi, weights=w, minlength=nf), dtype=np.float64)

    n = tot(np.ones_like(u))
    with np.errstate(invalid="ignore", divide="ignore"):
        mu, mv, md = tot(u) / n, tot(v) / n, tot(d) / n
        uu, vv = u - mu[fi], v - mv[fi]
        dd = d - md[fi]
        suu, svv, suv = tot(uu * uu), tot(vv * vv), tot(uu * vv)
        sud, svd = tot(uu * dd), tot(vv * dd)
        det = suu * svv - suv**2
        su = (svv * sud - suv * svd) / det
        sv = (suu * svd - suv * sud) / det
    span_u = np.zeros(nf)
    span_v = np.zeros(nf)
    np.maximum.at(span_u, fi, np.abs(uu))
    np.maximum.at(span_v, fi, np.abs(vv))
    good = (n >= 50) & (span_u >= 5) & (span_v >= 5) & np.isfinite(su) & np.isfinite(sv)
    return {int(k): (su[good & (fsp == k)], sv[good & (fsp == k)]) for k in np.unique(fsp)}


def _slope_mean(slopes: FloatArray) -> tuple[float, float] | None:
    """Mean of a standpoint's frame slopes and its SE from their scatter (window noise, pose jitter)."""
    if slopes.size < 2:
        return None
    return float(slopes.mean()), float(slopes.std(ddof=1) / np.sqrt(slopes.size))


@dataclass
class Gradient:
    slope_px_per_px: float
    se_px_per_px: float
    tau_px_per_px: float  # scatter of the standpoints' slopes beyond their frames' (pose tilt)
    standpoints: int
    p: float


def gradients(
    real: Samples, sim: Samples, axis: str, slopes: tuple[Any, Any] | None = None
) -> Gradient | None:
    """The slope of delta along `axis` (px per px) common to the standpoints, real minus sim.

    Per standpoint a slope with the SE of its frames' scatter; standpoints combined with
    random-effects weights 1 / (se^2 + tau^2) (DerSimonian-Laird tau: the reference pose's static
    tilt differs per standpoint), the SE from the weighted scatter (Knapp-Hartung, t with n - 1 dof),
    so neither a small far board nor a bad pose carries the test."""
    to_sim = {n: i for i, n in enumerate(sim.names)}
    fr, fs = slopes if slopes is not None else (frame_slopes(real), frame_slopes(sim))
    ys, vs = [], []
    for k, name in enumerate(real.names):
        if name not in to_sim:
            continue
        j = 0 if axis == "u" else 1
        r = _slope_mean(fr[k][j]) if k in fr else None
        s = _slope_mean(fs[to_sim[name]][j]) if to_sim[name] in fs else None
        if r is None or s is None:
            continue
        ys.append(r[0] - s[0])
        vs.append(r[1] ** 2 + s[1] ** 2)
    n = len(ys)
    if n < MIN_STANDPOINTS:
        return None
    y, v = np.array(ys), np.maximum(np.array(vs), 1e-30)
    w = 1 / v
    mean_f = float((w * y).sum() / w.sum())
    q = float((w * (y - mean_f) ** 2).sum())
    c = float(w.sum() - (w**2).sum() / w.sum())
    tau2 = max(0.0, (q - (n - 1)) / c) if c > 0 else 0.0
    w = 1 / (v + tau2)
    mean = float((w * y).sum() / w.sum())
    se = float(np.sqrt(max((w * (y - mean) ** 2).sum() / ((n - 1) * w.sum()), 1.0 / w.sum() / n)))
    t = mean / se if se > 0 else 0.0
    return Gradient(mean, se, float(np.sqrt(tau2)), n, float(2 * stdtr(n - 1, -abs(t))))


def _k_median(s: Samples) -> float:
    return float(np.median(s.k_m_per_px)) if len(s) else float("nan")


def fine_tests(real: Samples, sim: Samples, window_px: float = 9.0) -> list[dict[str, Any]]:
    """The tests of this module, each the fields of a locate GroupTest (diff in m at the session's
    median K, or m^2 for the static field's variance); `locate` Holm-corrects them with the rest."""
    k = _k_median(real)
    tests: list[dict[str, Any]] = []
    slopes = (frame_slopes(real), frame_slopes(sim))
    for axis in ("u", "v"):
        r = ripple(real, sim, axis)
        if r is not None:
            t = r.amplitude_px / r.amplitude_se_px if r.amplitude_se_px > 0 else float("nan")
            tests.append(
                _test(
                    f"periodic_{axis}",
                    "bias",
                    f"period {r.period_px:.3g} px along {axis}",
                    {
                        "period_px": r.period_px,
                        "amplitude_px": r.amplitude_px,
                        "amplitude_se_px": r.amplitude_se_px,
                        "phase_rad": r.phase_rad,
                        "periods_tried": r.periods_tried,
                        "p_unadjusted": r.p,
                        "heldout_rmse_before_px": r.heldout_rmse_before_px,
                        "heldout_rmse_after_px": r.heldout_rmse_after_px,
                    },
                    float("nan"),
                    float("nan"),
                    r.amplitude_px * k,
                    r.amplitude_se_px * k,
                    t,
                    float(r.standpoints - 2),
                    r.p_family,
                    r.standpoints,
                    r.standpoints,
                    axes=[axis],
                )
            )
        g = gradients(real, sim, axis, slopes)
        if g is not None:
            n = g.standpoints
            tests.append(
                _test(
                    f"gradient_{axis}",
                    "bias",
                    f"slope along {axis}",
                    {
                        "slope_px_per_px": g.slope_px_per_px,
                        "slope_se_px_per_px": g.se_px_per_px,
                        "detectable_px_per_px": DETECT * g.se_px_per_px,
                        "tau_px_per_px": g.tau_px_per_px,
                        "standpoints": n,
                    },
                    float("nan"),
                    float("nan"),
                    g.slope_px_per_px * k,
                    g.se_px_per_px * k,
                    g.slope_px_per_px / g.se_px_per_px if g.se_px_per_px > 0 else 0.0,
                    float(n - 1),
                    g.p,
                    n,
                    n,
                    axes=[axis],
                )
            )
    fields = static_fields(real, sim, window_px)
    for f in fields:
        t = f.diff_px2 / f.se_px2 if f.se_px2 > 0 else 0.0
        tests.append(
            _test(
                "static",
                "noise",
                f.standpoint,
                {
                    "real_px2": f.real_px2,
                    "sim_px2": f.sim_px2,
                    "correlation_px": f.correlation_px,
                    "tiles": f.tiles,
                },
                f.real_px2 * k**2,
                f.sim_px2 * k**2,
                f.diff_px2 * k**2,
                f.se_px2 * k**2,
                t,
                float(max(f.tiles - 1, 1)),
                float(2 * stdtr(max(f.tiles - 1, 1), -abs(t))),
                f.tiles,
                f.tiles,
                axes=["tile"],
            )
        )
    if len(fields) >= MIN_STANDPOINTS:
        d = np.array([f.diff_px2 for f in fields])
        n = d.size
        mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(n))
        t = mean / se if se > 0 else 0.0
        lengths = [f.correlation_px for f in fields if np.isfinite(f.correlation_px)]
        tests.append(
            _test(
                "static",
                "noise",
                "pooled",
                {
                    "diff_px2": mean,
                    "se_px2": se,
                    "standpoints": n,
                    "correlation_px": float(np.median(lengths)) if lengths else float("nan"),
                },
                float("nan"),
                float("nan"),
                mean * k**2,
                se * k**2,
                t,
                float(n - 1),
                float(2 * stdtr(n - 1, -abs(t))),
                n,
                n,
                axes=["tile"],
            )
        )
    return tests


FIELDS = (
    "family",
    "kind",
    "label",
    "coords",
    "real",
    "sim",
    "diff",
    "se",
    "t",
    "dof",
    "p",
    "n_real",
    "n_sim",
)


def _test(*values: Any, axes: list[str]) -> dict[str, Any]:
    return {**dict(zip(FIELDS, values, strict=True)), "axes": axes}


def fine_terms(tests: list[Any], present: dict[str, dict[str, float]], fx: float,
               kinds: tuple[str, ...] = ("periodic", "static")) -> list[dict[str, Any]]:
    """The model terms the significant fine tests call for (effect name and parameters), each
    validated on held-out standpoints where it can be: a ripple (`periodic_bias`, the stronger axis
    when both differ; kept only if it lowers the held-out RMS of the profiles) and the static
    pattern (`static_pattern` calibrated: sigma^2 + the pooled real-minus-sim variance of the part
    repeating over frames, in px of the 1280-wide mode as the effect states it, its correlation
    length in normalised units). `kinds`: which of the two to look for. The static pattern is
    calibrated on the tests after the catalogue's refit: before it, the static excess also holds
    what a selected bias renders the same in every frame (black squares read farther), which the
    pattern would then render twice."""
    out: list[dict[str, Any]] = []
    ripples = sorted(
        (t for t in tests if t.significant and t.family.startswith("periodic") and "periodic" in kinds),
        key=lambda t: t.p,
    )
    for t in ripples[:1]:
        c = t.coords
        if not c["heldout_rmse_after_px"] < c["heldout_rmse_before_px"]:
            continue
        out.append(
            {
                "effect": "periodic_bias",
                "family": t.family,
                "params": {
                    "amplitude_px": c["amplitude_px"],
                    "period_px": c["period_px"],
                    "phase_rad": c["phase_rad"],
                    "axis": 0.0 if t.family.endswith("u") else 1.0,
                },
                "heldout_rmse_before_px": c["heldout_rmse_before_px"],
                "heldout_rmse_after_px": c["heldout_rmse_after_px"],
            }
        )
    pooled = [t for t in tests if t.significant and t.family == "static" and t.label == "pooled"
              and "static" in kinds]
    if pooled and pooled[0].coords["diff_px2"] > 0:
        c = pooled[0].coords
        old = present.get("static_pattern", {})
        # the pattern is an angle, stated in px of the camera's 1280-wide mode (the samples' fx_ref,
        # the D455's); the excess is measured in px of these images: / (fx / fx_ref)^2
        scale = PixelContext(z_m=0.0, fx=fx).reference_scale
        sigma2 = old.get("sigma_px", 0.0) ** 2 + c["diff_px2"] / scale**2
        length = c["correlation_px"] / fx if np.isfinite(c["correlation_px"]) else old.get("length", 0.05)
        out.append(
            {
                "effect": "static_pattern",
                "family": "static",
                "params": {
                    "sigma_px": float(np.sqrt(sigma2)),
                    "length": float(np.clip(length, 0.002, 1.0)),
                    "pattern_seed": float(old.get("pattern_seed", 0.0)),
                },
                "heldout_rmse_before_px": float("nan"),
                "heldout_rmse_after_px": float("nan"),
            }
        )
    return out
