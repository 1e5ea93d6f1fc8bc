"""Every effect of the catalogue: its sampler against its analytic signature (contract 5)."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.simulate.effects import EFFECTS, PixelContext
from depthstation.simulate.effects.base import Effect

# A non-trivial parameter set per effect (defaults of calibration-type effects are zero).
TEST_PARAMS: dict[str, dict[str, float]] = {
    "disparity_noise": {"sigma_px": 0.08},
    "quantization": {},
    "dropout": {"dark_probability": 0.2, "base_probability": 0.05},
    "disparity_offset": {"offset_px": 0.15},
    "depth_scale": {"scale_error": 0.004},
    "lr_focal_mismatch": {"ratio": 3e-4},
    "distortion_residual": {"coeff_px": 0.3},
    "pixel_locking": {"amplitude_px": 0.05},
    "thermal_drift": {"coeff_px_per_c": 0.01, "reference_c": 35.0},
    "slant_noise": {"window_px": 7.0},
    "slant_bias": {"offset_px_at_45": 0.05},
    "albedo_bias": {"offset_px_black": 0.1},
    "albedo_noise": {"sigma_px_black": 0.12},
    "flying_pixels": {"edge_probability": 0.4, "width_px": 1.5, "spread_ratio": 0.05},
    "reference_pose_noise": {"corner_sigma_px": 0.2},
    "window_noise": {"sigma_px": 0.1, "window_px": 5.0},
    "incidence_noise": {"sigma_px": 0.08, "exponent": 1.0, "max_deg": 80.0},
    "static_pattern": {"sigma_px": 0.2, "length": 0.05, "pattern_seed": 3.0},
    "slant_scale": {"k": 0.02, "max_deg": 75.0},
    "periodic_bias": {"amplitude_px": 0.05, "period_px": 24.0, "phase_rad": 0.3, "axis": 0.0},
    "spline_bias": {"axis": 2.0, "lo": 1.0, "hi": 5.0, "knots": 4.0,
                    "c0": 0.05, "c1": -0.03, "c2": 0.02, "c3": 0.06},
    "color_camera": {"psf_sigma_px": 0.8, "full_well_e": 250.0, "read_noise_e": 4.0},  # leaves depth alone
}
FX, PPX, PPY, B = 674.42, 641.8, 358.1, 0.095
N = 1500  # samples per cell


def _cells(rng: np.random.Generator) -> PixelContext:
    """N x cells context over distance x inclination x pixel x albedo x edge distance x temperature.

    z is jittered by +-1 % per sample so that quantisation sees a uniform fractional position.
    """
    d, inc, u, alb, edge, temp = np.meshgrid([0.6, 1.0, 2.0, 4.0, 6.0], [0.0, 30.0, 60.0, 78.0],
                                             [60.0, 640.0, 1220.0], [0.05, 0.85], [0.5, 2.5, np.inf],
                                             [30.0, 45.0], indexing="ij")
    flat = [a.ravel() for a in (d, inc, u, alb, edge, temp)]
    z = flat[0][None, :] * (1 + rng.uniform(-0.01, 0.01, (N, flat[0].size)))
    return PixelContext(z_m=z, inclination_deg=flat[1], u=flat[2], v=flat[2] * 0.5, albedo=flat[3],
                        time_s=0.0, temperature_c=flat[5], edge_distance_px=flat[4],
                        fx=FX, ppx=PPX, ppy=PPY, baseline_m=B)


def _sample(effect: Effect, ctx: PixelContext, rng: np.random.Generator) -> np.ndarray:
    z = np.asarray(ctx.z_m, dtype=np.float32)
    if effect.name in ("reference_pose_noise", "window_noise"):  # correlated within a frame: rows are frames
        rows = [effect.apply(PixelContext(**{**ctx.__dict__, "z_m": ctx.z_m[i]}), z[i].copy(), rng)
                for i in range(N)]
        return np.asarray(rows, dtype=np.float64)
    return effect.apply(ctx, z.copy(), rng).astype(np.float64)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_effect_sampler_matches_signature(name: str) -> None:
    rng = np.random.default_rng(7)
    effect = EFFECTS[name](TEST_PARAMS[name])
    assert effect.name == name and effect.meaning and set(effect.units) == set(effect.params)
    ctx = _cells(rng)
    zt = np.asarray(ctx.z_m, dtype=np.float64)
    zs = _sample(effect, ctx, rng)
    bias = np.broadcast_to(effect.bias_m(ctx), zt.shape)
    var = np.broadcast_to(effect.variance_m2(ctx), zt.shape)
    keep = np.broadcast_to(effect.valid_probability(ctx), zt.shape)
    # float32 storage of z adds a rounding error of ~6e-8 z
    eps = 4e-7 * zt.max()

    valid = np.isfinite(zs)
    frac = valid.mean(axis=0)
    p = keep.mean(axis=0)
    assert np.all(np.abs(frac - p) <= 5 * np.sqrt(p * (1 - p) / N) + 1e-9), "keep probability"
    if not valid.all():
        assert name == "dropout"
        np.testing.assert_array_equal(zs[valid], zt.astype(np.float32)[valid])
        return

    resid = zs - zt - bias
    mean = resid.mean(axis=0)
    pred_var = var.mean(axis=0)
    samp_var = resid.var(axis=0, ddof=1)
    se_mean = np.sqrt(pred_var / N)
    assert np.all(np.abs(mean) <= 5 * se_mean + eps), f"mean residual {np.abs(mean).max():.3g}"
    m4 = ((resid - mean) ** 4).mean(axis=0)
    se_var = np.sqrt(np.maximum(m4 - samp_var**2, 0) / N)
    assert np.all(np.abs(samp_var - pred_var) <= 5 * se_var + eps**2 + 1e-3 * pred_var), "variance"
    if np.any(pred_var > 0):
        assert np.any(samp_var > 0) and np.any(np.abs(mean) < 1)  # the noise is really there


def test_signatures_have_their_physical_shape() -> None:
    z = np.array([1.0, 2.0, 4.0])
    ctx = PixelContext(z_m=z, fx=FX, ppx=PPX, ppy=PPY, baseline_m=B, fx_ref=FX)  # the 1280-wide mode
    fb = FX * B
    off = EFFECTS["disparity_offset"]({"offset_px": 0.1}).bias_m(ctx)
    np.testing.assert_allclose(off, -z**2 * 0.1 / (fb + z * 0.1), rtol=1e-9)  # ~ z^2, + offset = nearer
    assert np.all(off < 0)
    np.testing.assert_allclose(EFFECTS["depth_scale"]({"scale_error": 0.01}).bias_m(ctx), 0.01 * z)
    rms = np.sqrt(EFFECTS["disparity_noise"]().variance_m2(ctx))
    np.testing.assert_allclose(rms, z**2 * 0.08 / fb, rtol=1e-3)  # Intel's formula
    us = np.array([PPX - 300, PPX, PPX + 300])
    wedge = PixelContext(z_m=2.0, u=us, fx=FX, ppx=PPX, ppy=PPY, baseline_m=B)
    b = EFFECTS["lr_focal_mismatch"]({"ratio": 1e-3}).bias_m(wedge)
    assert b[0] > 0 and abs(b[1]) < 1e-12 and b[2] < 0  # a wedge that changes sign at cx
    drop = EFFECTS["dropout"]()
    near = PixelContext(z_m=np.array([0.45, 0.55, 3.0, 7.5]), fx=FX, baseline_m=B)
    keep = drop.valid_probability(near)
    assert keep[0] == 0 and keep[1] > 0.95 and keep[2] > 0.95 and keep[3] < 0.1  # min-z 0.51 m, range
    steep = PixelContext(z_m=2.0, inclination_deg=np.array([30.0, 85.0]), albedo=np.array([1.0, 1.0]))
    assert drop.valid_probability(steep)[1] < 0.2 < drop.valid_probability(steep)[0]


def test_unknown_parameter_is_refused() -> None:
    from depthstation.core.errors import SimulationError

    with pytest.raises(SimulationError, match="unknown parameter"):
        EFFECTS["disparity_noise"]({"sigma": 0.1})


@pytest.mark.parametrize("fused", [True, False])
def test_model_sample_matches_model_signature(fused: bool) -> None:
    """The whole default model plus calibration effects, fused pass and effect-by-effect alike."""
    from depthstation.simulate.model import load_model

    model = (load_model("d455-ideal").with_effect("disparity_offset", offset_px=0.1)
             .with_effect("albedo_noise", sigma_px_black=0.1).with_effect("depth_scale", scale_error=0.002)
             .with_effect("lr_focal_mismatch", ratio=2e-4))
    rng = np.random.default_rng(11)
    z = np.repeat(np.array([0.8, 1.5, 3.0, 5.0]), 6)[None, :] * (1 + rng.uniform(-0.01, 0.01, (4000, 24)))
    alb = np.tile([0.05, 0.85], 12)
    u = np.tile([100.0, 100.0, 640.0, 640.0, 1180.0, 1180.0], 4)
    ctx = PixelContext(z_m=z, u=u, albedo=alb, fx=FX, ppx=PPX, ppy=PPY, baseline_m=B)
    zs = model.sample(ctx, z.astype(np.float32), rng, fused=fused).astype(np.float64)
    keep = model.valid_probability(ctx).mean(axis=0)
    frac = np.isfinite(zs).mean(axis=0)
    assert np.all(np.abs(frac - keep) <= 5 * np.sqrt(keep * (1 - keep) / 4000) + 1e-9)
    resid = np.where(np.isfinite(zs), zs - z - model.bias_m(ctx), np.nan)
    var = model.variance_m2(ctx).mean(axis=0)
    n = np.isfinite(resid).sum(axis=0)
    # the window noise is shared by w rows of a column: its share of the column mean's variance is
    # w times that of independent draws (the triangular correlation sums to w)
    win = model.effect("window_noise")
    assert win is not None
    var_win = win.variance_m2(ctx).mean(axis=0)
    var_mean = (var - var_win + var_win * win.params["window_px"]) / n
    assert np.all(np.abs(np.nanmean(resid, axis=0)) <= 5 * np.sqrt(var_mean) + 2e-5)
    # first-order sum of variances; the effects' interaction (1/d nonlinearity) stays within 5 %
    np.testing.assert_allclose(np.nanvar(resid, axis=0), var, rtol=0.05 + 5 * np.sqrt(2 / n.min()))


def test_spline_bias_passes_through_its_knots_and_holds_its_ends() -> None:
    """The spline's value at each knot is that knot's coefficient (a natural interpolating spline),
    constant beyond the ends: what explain fitted is what the simulator renders."""
    c = [0.05, -0.03, 0.02, 0.06]
    eff = EFFECTS["spline_bias"]({"axis": 0.0, "lo": 100.0, "hi": 400.0, "knots": 4.0,
                                  **{f"c{k}": v for k, v in enumerate(c)}})
    u = np.array([100.0, 200.0, 300.0, 400.0, 20.0, 600.0])
    shift = eff.shift_px(PixelContext(z_m=np.full(6, 2.0), u=u))
    np.testing.assert_allclose(shift, [*c, c[0], c[-1]], atol=1e-12)
