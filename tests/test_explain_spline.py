"""The spline term (evaluate/explain/spline.py) on sessions written pixel by pixel here, not by the
simulator: a bias bump over a band of columns (no polynomial of the library holds it) is fitted as
a spline along u, predicts held-out standpoints better, and is rendered by `spline_bias` as fitted;
a bias that bends at one distance is fitted along distance; a null gives no spline."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from depthstation.evaluate.explain.samples import Samples, concat
from depthstation.evaluate.explain.spline import fit_spline
from depthstation.simulate.effects import EFFECTS, PixelContext

W, H, FX, B = 320, 240, 200.0, 0.095
N_SP, N_FR = 12, 6
PER_PIXEL, SHARED, WIN = 0.081, 0.07, 9


def bump(u: np.ndarray) -> np.ndarray:
    return 0.03 * np.exp(-(((u - 200.0) / 25.0) ** 2))


def bend(z: np.ndarray) -> np.ndarray:
    return 0.04 * np.clip(z - 2.5, 0.0, None)


def _session(seed: int, effect: str = "none") -> Samples:
    rng = np.random.default_rng(seed)
    white = np.sqrt(PER_PIXEL ** 2 - SHARED ** 2)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    names = [f"sp{k:02d}" for k in range(N_SP)]
    parts = []
    for k in range(N_SP):
        z = 1.0 + 3.0 * (k // 2) / 5.0
        incl = (0.0, 30.0)[k % 2]
        board = (np.abs(u - W / 2) < 130) & (np.abs(v - H / 2) < 90)
        for i in range(N_FR):
            delta = cv2.blur(rng.standard_normal((H, W)), (WIN, WIN)) * WIN * SHARED \
                + white * rng.standard_normal((H, W))
            delta += 0.01 * rng.standard_normal() + 1e-4 * rng.standard_normal() * (u - W / 2)
            if effect == "bump":
                delta += bump(u)
            if effect == "bend":
                delta += bend(np.full_like(u, z))
            kk = z * z / (FX * B)
            parts.append(Samples.build(
                names=names, fx=FX, ppx=W / 2, ppy=H / 2, baseline_m=B, standpoint=k, frame=i,
                u=u[board][::3], v=v[board][::3], z_ref_m=z, err_m=-kk * delta[board][::3],
                inclination_deg=incl, albedo=0.85, time_s=k * 30.0 + i / 30.0))
    return concat(parts)


@pytest.fixture(scope="module")
def sim() -> Samples:
    return _session(1)


def _rendered(params: dict[str, float], **ctx: np.ndarray) -> np.ndarray:
    eff = EFFECTS["spline_bias"](params)
    return np.asarray(eff.shift_px(PixelContext(z_m=ctx.pop("z_m", np.full(1, 2.0)), **ctx)))


def test_a_bump_over_a_band_of_columns_is_fitted_as_a_spline_along_u(sim: Samples) -> None:
    fit = fit_spline(_session(2, "bump"), sim, "u")
    assert fit is not None and fit.axis == "u"
    assert fit.heldout_rmse_after_px < 0.8 * fit.heldout_rmse_before_px
    u = np.arange(60.0, 280.0)
    got = _rendered(fit.params(), u=u)
    want = bump(u)
    # the spline carries the shape, not a plane (the standpoints' reference planes hold those)
    want = want - np.polyval(np.polyfit(u, want, 1), u)
    got = got - np.polyval(np.polyfit(u, got, 1), u)
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.25 * np.sqrt(np.mean(want ** 2))


def test_a_bias_bending_at_one_distance_is_fitted_along_distance(sim: Samples) -> None:
    fit = fit_spline(_session(3, "bend"), sim, "distance")
    assert fit is not None and fit.heldout_rmse_after_px < 0.6 * fit.heldout_rmse_before_px
    z = np.array([1.0, 1.6, 2.2, 2.8, 3.4, 4.0])
    got = _rendered(fit.params(), z_m=z)
    assert np.abs(got - bend(z)).max() < 0.01       # px, against a bend of 0.06 px at 4 m


def test_a_null_session_gives_no_spline(sim: Samples) -> None:
    real = _session(4)
    for axis in ("u", "distance"):
        fit = fit_spline(real, sim, axis)
        assert fit is None or fit.heldout_rmse_after_px > 0.95 * fit.heldout_rmse_before_px
