"""What the bins average away (evaluate/explain/fine.py), on sessions written here pixel by pixel
(not by the simulator): 18 standpoints x 15 frames at 1-4 m, a 320x240 imager, D455-like disparity
noise 0.081 px per pixel of which 0.07 px is shared over the 9x9 matching window, a per-frame pose
jitter of the reference plane; the real and the simulated side are two draws of the same generator,
the real one with a concealed effect below the per-pixel noise:

- a ripple along u, 0.02 px at a 24 px period;
- a static field per standpoint (smooth, 0.03 px RMS over ~6 px), the same in every frame;
- a roll of the right imager, delta = -f roll y (zero mean over the rows).

Each must come out with a p that survives Holm over a run's ~200 tests; the null none.
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from depthstation.evaluate.explain.fine import fine_terms, fine_tests, gradients, ripple
from depthstation.evaluate.explain.samples import Samples, concat
from depthstation.simulate.effects.base import PixelContext

W, H, FX, B = 320, 240, 200.0, 0.095
N_SP, N_FR = 18, 15
PER_PIXEL, SHARED, WIN = 0.081, 0.07, 9
HOLM_FLOOR = 0.05 / 200      # a p below this is significant after Holm over any run's tests


def _session(seed: int, effect: str = "none", amplitude: float = 0.0) -> Samples:
    rng = np.random.default_rng(seed)
    field_rng = np.random.default_rng(777)         # the real camera's static fields: one per standpoint
    white = np.sqrt(PER_PIXEL ** 2 - SHARED ** 2)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    parts = []
    names = [f"standpoint_{k + 1:02d}" for k in range(N_SP)]
    for k in range(N_SP):
        z = 1.0 + 3.0 * (k // 3) / 5.0
        incl = (0.0, 25.0, 45.0)[k % 3]
        half = min(0.45 * FX / z, 110.0)
        cu, cv = W / 2 + 30 * np.sin(k), H / 2 + 20 * np.cos(k)
        board = (np.abs(u - cu) < half * np.cos(np.radians(incl))) & (np.abs(v - cv) < half * 0.8)
        board &= (u > 5) & (u < W - 5) & (v > 5) & (v < H - 5)
        static = np.zeros((H, W))
        if effect == "static":
            f = cv2.GaussianBlur(field_rng.standard_normal((H, W)), (0, 0), 3.0)
            static = amplitude * f / f.std()
        for i in range(N_FR):
            shared = cv2.blur(rng.standard_normal((H, W)), (WIN, WIN)) * WIN * SHARED
            delta = shared + white * rng.standard_normal((H, W)) + static
            # the reference plane of this frame's pose estimate (random offset and tilt)
            delta += 0.01 * rng.standard_normal() + 1e-4 * rng.standard_normal() * (u - W / 2) \
                + 1e-4 * rng.standard_normal() * (v - H / 2)
            if effect == "ripple":
                delta += amplitude * np.sin(2 * np.pi * u / 24.0)
            if effect == "roll":
                delta += -FX * amplitude * (v - H / 2) / FX
            kk = z * z / (FX * B)
            parts.append(Samples.build(
                names=names, fx=FX, ppx=W / 2, ppy=H / 2, baseline_m=B, standpoint=k, frame=i,
                u=u[board], v=v[board], z_ref_m=z, err_m=-kk * delta[board], inclination_deg=incl,
                albedo=0.85, time_s=k * 30.0 + i / 30.0))
    return concat(parts)


@pytest.fixture(scope="module")
def sim() -> Samples:
    return _session(1)


def test_null_session_shows_nothing(sim: Samples) -> None:
    tests = fine_tests(_session(2), sim)
    assert {t["family"] for t in tests} >= {"periodic_u", "periodic_v", "gradient_u", "gradient_v", "static"}
    assert min(t["p"] for t in tests) > HOLM_FLOOR, [(t["family"], t["label"], t["p"]) for t in tests]


def test_a_ripple_along_u_below_the_noise_is_found_with_its_period(sim: Samples) -> None:
    real = _session(3, "ripple", 0.02)
    r = ripple(real, sim, "u")
    assert r is not None and r.p_family < HOLM_FLOOR
    assert r.heldout_rmse_after_px < r.heldout_rmse_before_px
    assert r.period_px == pytest.approx(24.0, rel=0.05)
    assert abs(r.amplitude_px - 0.02) < 3 * r.amplitude_se_px + 0.003
    along_v = ripple(real, sim, "v")
    assert along_v is None or along_v.p_family > HOLM_FLOOR   # not along v


def test_a_static_field_repeating_over_the_frames_is_found(sim: Samples) -> None:
    tests = [t for t in fine_tests(_session(4, "static", 0.03), sim) if t["family"] == "static"]
    pooled = [t for t in tests if t["label"] == "pooled"]
    assert pooled and pooled[0]["p"] < HOLM_FLOOR
    diffs = np.array([t["coords"]["real_px2"] - t["coords"]["sim_px2"] for t in tests
                      if t["label"] != "pooled"])
    assert np.median(diffs) == pytest.approx(0.03 ** 2, rel=0.35)   # minus what the plane takes
    lengths = [t["coords"]["correlation_px"] for t in tests if np.isfinite(t["coords"]["correlation_px"])]
    assert lengths and 2.0 <= np.median(lengths) <= 12.0


def test_a_roll_zero_mean_over_the_rows_is_found_and_the_detectable_size_said(sim: Samples) -> None:
    roll = 2e-4    # rad: delta = -roll (v - c_y), 0.02 px over 100 rows
    real = _session(5, "roll", roll)
    g = gradients(real, sim, "v")
    assert g is not None and g.p < HOLM_FLOOR
    assert abs(g.slope_px_per_px + roll) < 3 * g.se_px_per_px
    assert 2.8 * g.se_px_per_px < roll    # the session's detectable slope, as explain.json says it
    assert gradients(real, sim, "u").p > HOLM_FLOOR   # not along u


def test_the_static_excess_is_written_in_px_of_the_1280_wide_mode() -> None:
    """The static pattern is an angle (the simulator renders sigma_px x fx / fx_ref): an excess
    measured at 640 wide (fx half the reference's) is written as 2x the px, so that re-simulating
    at 640 wide renders the variance that was measured."""
    fx_ref = PixelContext(z_m=0.0).fx_ref
    pooled = SimpleNamespace(significant=True, family="static", label="pooled", p=1e-9,
                             coords={"diff_px2": 0.0009, "correlation_px": 16.0})
    for fx, want in ((fx_ref, 0.03), (fx_ref / 2.0, 0.06)):
        (term,) = fine_terms([pooled], {}, fx)
        assert term["effect"] == "static_pattern"
        assert term["params"]["sigma_px"] == pytest.approx(want, rel=1e-12)
        rendered = term["params"]["sigma_px"] * PixelContext(z_m=0.0, fx=fx).reference_scale
        assert rendered**2 == pytest.approx(0.0009, rel=1e-12)
