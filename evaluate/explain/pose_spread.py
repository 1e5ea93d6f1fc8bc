"""The board pose's spread: what the colour camera does to the checkerboard study's reference.

Every frame's reference plane is the board pose found in that frame's colour image, so a colour
camera that blurs, vignettes and adds shot and read noise moves the detected corners by a fraction
of a pixel per frame, and the reference distance (the board centre's z) scatters over the frames of
a standpoint: more far away (the board spans fewer pixels, sigma_z ~ z^2 / (f L)) and at steep
inclinations (stretched along the ray by 1 / cos). The depth does not show it apart from a noise
common to a frame, which a disparity jitter of the stereo head gives as well (docs/explain.md): the
evidence is the colour image's own, the per-frame reference distance (`reference_distance_std_m`,
the paper's Fig. 4), real against simulated.

Per standpoint an F test of the two spreads (n - 1 degrees of freedom each), Holm over the
standpoints. The excess variance real - sim is fitted with the signature of `reference_pose_noise`
(sigma_z = corner_sigma_px z^2 / (f L cos theta); weighted least squares, the weights from the
fitted model itself, iterated). The fitted term is written into model.toml: the re-simulated depth
then carries the frame-common error the real reference has, and the check after compares the real
spread with the re-simulated one plus the term's variance (the term stands for the reference's
error; the re-simulated colour image is still the model's).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.special import fdtr, fdtrc

ALPHA = 0.05
WALD_Z = 3.29      # |fitted / SE| for p < 1e-3 (two-sided), the catalogue's Wald threshold
MIN_STANDPOINTS = 3
NAME = "color_camera"
TERM = "reference_pose_noise"


@dataclass
class SpreadTest:
    """One standpoint: the reference distance's spread over its frames, real against simulated."""

    standpoint: str
    distance_m: float
    inclination_deg: float
    real_m: float
    sim_m: float          # the simulation's spread, with the model's pose-noise term added (after)
    frames_real: int
    frames_sim: int
    ratio: float          # real / sim spread
    p: float
    p_holm: float = float("nan")
    significant: bool = False


def _f_test(real: float, sim: float, nr: int, ns: int) -> float:
    """Two-sided p of the variance ratio real^2 / sim^2 with (nr - 1, ns - 1) dof."""
    if nr < 3 or ns < 3 or not (np.isfinite(real) and np.isfinite(sim)) or sim <= 0:
        return float("nan")
    f = real**2 / sim**2
    lo, hi = float(fdtr(nr - 1, ns - 1, f)), float(fdtrc(nr - 1, ns - 1, f))
    return min(1.0, 2.0 * min(lo, hi))


def holm(tests: list[SpreadTest], alpha: float = ALPHA) -> None:
    """Holm's step-down adjusted p over the tests with a p (in place)."""
    ok = sorted((t for t in tests if np.isfinite(t.p)), key=lambda t: t.p)
    m, running = len(ok), 0.0
    for i, t in enumerate(ok):
        running = max(running, min(1.0, (m - i) * t.p))
        t.p_holm = running
        t.significant = running < alpha


def signature_m2(distance_m: float, inclination_deg: float, fx: float, board_size_m: float) -> float:
    """Reference z variance per px^2 of corner noise: (z^2 / (f L cos theta))^2 (`reference_pose_noise`)."""
    cos = float(np.cos(np.radians(np.clip(inclination_deg, 0.0, 85.0))))
    return float((distance_m**2 / (fx * board_size_m * cos)) ** 2)


def spread_tests(real: dict[str, dict[str, float]], sim: dict[str, dict[str, float]],
                 frames_real: dict[str, int], frames_sim: dict[str, int],
                 added_m2: dict[str, float] | None = None) -> list[SpreadTest]:
    """Per standpoint both sides have: the F test of the reference spreads (Holm over them).
    `added_m2`: a pose-noise variance the simulated side carries besides its colour image's."""
    out = []
    for name, fr in real.items():
        fs = sim.get(name)
        if fs is None:
            continue
        sr = float(fr.get("reference_distance_std_m", np.nan))
        ss = float(np.sqrt(float(fs.get("reference_distance_std_m", np.nan)) ** 2
                           + (added_m2 or {}).get(name, 0.0)))
        nr, ns = frames_real.get(name, 0), frames_sim.get(name, 0)
        p = _f_test(sr, ss, nr, ns)
        out.append(SpreadTest(name, float(fr.get("distance_m", np.nan)),
                              float(fr.get("inclination_deg", np.nan)), sr, ss, nr, ns,
                              sr / ss if ss > 0 else float("inf"), p))
    holm(out)
    return out


@dataclass
class SpreadFit:
    """The excess reference variance fitted with reference_pose_noise's signature."""

    corner_sigma_px: float
    corner_sigma_se_px: float
    variance_px2: float         # fitted corner_sigma^2 (may be negative: the real spread is smaller)
    variance_se_px2: float
    standpoints: int
    board_size_m: float


def fit_excess(tests: list[SpreadTest], fx: float, board_size_m: float) -> SpreadFit | None:
    """corner_sigma^2 from s_real^2 - s_sim^2 = c^2 g(z, theta), weights 1 / Var(excess) under the fit
    (Var of a variance estimate: 2 sigma^4 / (n - 1)), iterated from equal weights."""
    ok = [t for t in tests if np.isfinite(t.real_m) and np.isfinite(t.sim_m) and t.frames_real >= 3
          and t.frames_sim >= 3 and np.isfinite(t.distance_m)]
    if len(ok) < MIN_STANDPOINTS:
        return None
    g = np.array([signature_m2(t.distance_m, t.inclination_deg, fx, board_size_m) for t in ok])
    e = np.array([t.real_m**2 - t.sim_m**2 for t in ok])
    s2 = np.array([t.sim_m**2 for t in ok])
    nr = np.array([t.frames_real - 1 for t in ok], dtype=float)
    ns = np.array([t.frames_sim - 1 for t in ok], dtype=float)
    c2 = 0.0
    w = 1.0 / np.maximum(g * g, 1e-300)
    for _ in range(6):
        c2 = float((w * g * e).sum() / (w * g * g).sum())
        var = 2 * (max(c2, 0.0) * g + s2) ** 2 / nr + 2 * s2**2 / ns
        w = 1.0 / np.maximum(var, 1e-300)
    se = float(1.0 / np.sqrt((w * g * g).sum()))
    c = float(np.sqrt(max(c2, 0.0)))
    return SpreadFit(c, se / (2 * c) if c > 0 else float("inf"), c2, se, len(ok), board_size_m)


def pose_term(fit: SpreadFit | None, tests: list[SpreadTest], present: dict[str, dict[str, float]]
              ) -> dict[str, Any] | None:
    """The model term a significant spread calls for (the fine-terms shape run.improved_model takes):
    reference_pose_noise with corner_sigma_px^2 = the model's own + the fitted excess, when some
    standpoint differs (Holm) and the fit is strong (Wald, as the catalogue's)."""
    if fit is None or not any(t.significant and t.ratio > 1 for t in tests):
        return None
    if not fit.variance_px2 > WALD_Z * fit.variance_se_px2:
        return None
    old = float(present.get(TERM, {}).get("corner_sigma_px", 0.0))
    return {"effect": TERM, "family": "pose_spread", "named": NAME,
            "params": {"corner_sigma_px": float(np.sqrt(old**2 + fit.variance_px2)),
                       "board_size_m": fit.board_size_m},
            "heldout_rmse_before_px": float("nan"), "heldout_rmse_after_px": float("nan")}


def added_variance(model_params: dict[str, float] | None, figures: dict[str, dict[str, float]], fx: float
                   ) -> dict[str, float]:
    """Per standpoint the z variance a model's reference_pose_noise adds to the reference (m^2)."""
    if not model_params:
        return {}
    c = float(model_params.get("corner_sigma_px", 0.0))
    size = float(model_params.get("board_size_m", 0.57))
    return {n: c * c * signature_m2(float(f["distance_m"]), float(f["inclination_deg"]), fx, size)
            for n, f in figures.items() if np.isfinite(f.get("distance_m", np.nan))}


def summary(tests: list[SpreadTest], fit: SpreadFit | None, term: dict[str, Any] | None) -> dict[str, Any]:
    """explain.json's pose_spread (before) or pose_spread_after."""
    return {"evidence": "the reference distance of each frame (board pose from the colour image)",
            "significant": [t.standpoint for t in tests if t.significant],
            "tests": [asdict(t) for t in tests],
            "fit": asdict(fit) if fit is not None else None,
            "named": NAME if term is not None else None,
            "term": term}


def board_size(board: Any) -> float:
    """reference_pose_noise's L: inner corners times the square along the longer side (m; 6 x 0.095 m
    for the default 7 x 5 board, the effect's own default)."""
    cx, cy = board.inner_corners
    return float(max(cx, cy, 1) * board.square_length_m)
