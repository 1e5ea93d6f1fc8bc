"""Generic terms and window noise in the simulator, and explain's noise statistics on correlated
noise, checked against forms written here (a running-sum box filter, per-frame draws), not against
the modules under test.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.errors import InputError
from depthstation.evaluate.explain.library import INTERPRETATION
from depthstation.evaluate.explain.locate import locate
from depthstation.evaluate.explain.samples import Samples, concat
from depthstation.evaluate.explain.structure import decompose, frame_common
from depthstation.simulate.effects import PixelContext
from depthstation.simulate.model import load_model, model_from_toml

ROOT = Path(__file__).resolve().parents[1]
H, W, FX, B = 60, 80, 70.0, 0.095
PPX, PPY = (W - 1) / 2, (H - 1) / 2


def _plain(model: Any) -> Any:
    """The model without the effects that are not disparity noise (quantisation, dropout, edges)."""
    for name in ("quantization", "dropout", "flying_pixels", "disparity_noise", "window_noise"):
        model = model.without_effect(name)
    return model


@pytest.mark.parametrize("fused", [True, False])
def test_generic_terms_render_their_expressions(fused: bool) -> None:
    """A bias along v, a noise growing like z^2 (in disparity variance), a frame-common noise and a
    window-shared noise on dark pixels, drawn frame by frame: each statistic is the expression's."""
    toml = """
[camera]
preset = "d455"
[effects.term_bias_v_poly2]
c1 = 0.3
c2 = -0.5
[effects.term_noise_distance_poly1]
c1 = 0.0016
[effects.term_noise_frame_common]
c = 0.0009
[effects.term_noise_albedo_poly1_window]
c1 = 0.004
window_px = 5
"""
    model = _plain(model_from_toml(toml))
    assert model.to_toml().count("[effects.term_") == 4
    assert [e.name for e in model_from_toml(model.to_toml()).effects] == [e.name for e in model.effects]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = np.where(u < W / 2, 1.5, 3.0).astype(np.float32)              # two depths
    albedo = np.where(v < H / 2, 0.05, 0.85)                           # dark top, bright bottom
    ctx = PixelContext(z_m=z, u=u, v=v, albedo=albedo, fx=FX, ppx=PPX, ppy=PPY, baseline_m=B)
    rng = np.random.default_rng(4)
    fb = FX * B
    d = np.stack([fb / model.sample(ctx, z, rng, fused=fused) for _ in range(400)]).astype(np.float64)
    d -= fb / z
    y = (v - PPY) / FX
    np.testing.assert_allclose(d.mean(axis=0).mean(axis=1), (0.3 * y - 0.5 * y * y).mean(axis=1), atol=0.01)
    frame_mean = d.mean(axis=(1, 2))
    within = d - frame_mean[:, None, None]
    var = within.var(axis=0)
    dark = 0.004 * (1 - 0.05)
    bright = 0.004 * (1 - 0.85)
    for rows, extra in ((v < H / 2, dark), (v >= H / 2, bright)):
        for cols, zz in ((u < W / 2, 1.5), (u >= W / 2, 3.0)):
            m = rows & cols
            assert var[m].mean() == pytest.approx(0.0016 * zz ** 2 + extra, rel=0.1)
    assert frame_mean.var() == pytest.approx(0.0009, rel=0.2)   # 400 frames: +-7 % (2 SE 14 %)
    # the dark rows' noise is shared by neighbours 5 px wide: lag 2 correlates by (1 - 2/5) of its share
    noise = within - within.mean(axis=0)           # the static bias pattern out
    top = noise[:, : H // 2 - 2, W // 2 + 2:]
    r2 = (top[:, :, :-2] * top[:, :, 2:]).mean() / top.var()
    assert r2 == pytest.approx(0.6 * dark / (0.0016 * 9 + dark), abs=0.05)


def test_bad_generic_term_is_refused() -> None:
    with pytest.raises(InputError, match="term_bias_frame_common"):
        model_from_toml('[camera]\npreset = "d455"\n[effects.term_bias_frame_common]\nc = 1.0\n')
    with pytest.raises(InputError, match="unknown parameter"):
        model_from_toml('[camera]\npreset = "d455"\n[effects.term_bias_v_poly1]\nc7 = 1.0\n')


def test_window_noise_shares_the_error_of_a_box() -> None:
    """window_noise against a running-sum box filter's statistics: variance sigma^2, correlation
    (1 - k/w) along u and v, and the mean of an n x n patch varying like w^2 / n^2 independent pixels."""
    model = _plain(load_model("d455-ideal")).with_effect("window_noise", sigma_px=0.1, window_px=9)
    z = np.full((90, 120), 2.0, dtype=np.float32)
    v, u = np.mgrid[0:90, 0:120].astype(np.float64)
    ctx = PixelContext(z_m=z, u=u, v=v, fx=FX, ppx=60.0, ppy=45.0, baseline_m=B)
    rng = np.random.default_rng(2)
    d = np.stack([FX * B / model.sample(ctx, z, rng) - FX * B / 2.0 for _ in range(300)]).astype(np.float64)
    assert d.var() == pytest.approx(0.01, rel=0.05)
    for k in (3, 6):
        assert (d[:, :, :-k] * d[:, :, k:]).mean() / d.var() == pytest.approx(1 - k / 9, abs=0.04)
        assert (d[:, :-k, :] * d[:, k:, :]).mean() / d.var() == pytest.approx(1 - k / 9, abs=0.04)
    patch = d[:, 20:56, 30:66].mean(axis=(1, 2))     # 36 x 36 = 16 windows
    assert patch.var() == pytest.approx(0.01 * 81 / 36 ** 2, rel=0.25)


def _session(seed: int, window: int, sigma: float, frames: int = 6) -> Samples:
    """Planes at 1-3 m seen at 160x90, disparity noise sigma (px) shared over a window x window box
    (a running sum over a white field, written here) or white (window 1), all pixels of each frame."""
    rng = np.random.default_rng(seed)
    w_, h_, fx = 160, 90, 124.8
    ppx, ppy, fb = (w_ - 1) / 2, (h_ - 1) / 2, 124.8 * B
    names = [f"standpoint_{i + 1:02d}" for i in range(6)]
    v, u = np.mgrid[10:h_ - 10, 20:w_ - 20].astype(np.float64)
    parts = []
    for i in range(6):
        z = np.full(u.shape, 1.0 + 0.4 * i)
        for f in range(frames):
            white = rng.standard_normal((u.shape[0] + window - 1, u.shape[1] + window - 1))
            c = np.cumsum(np.cumsum(np.pad(white, ((1, 0), (1, 0))), axis=0), axis=1)
            w = window
            box = (c[w:, w:] - c[:-w, w:] - c[w:, :-w] + c[:-w, :-w]) / w
            d = fb / z + sigma * box
            parts.append(Samples.build(
                names=names, fx=fx, ppx=ppx, ppy=ppy, baseline_m=B, standpoint=i, frame=f, u=u.ravel(),
                v=v.ravel(), z_ref_m=z.ravel(), err_m=(fb / d - z).ravel(), inclination_deg=0.0,
                albedo=np.where((u // 10 + v // 10) % 2, 0.85, 0.05).ravel(), time_s=(i * frames + f) * 1.0))
    return concat(parts)


def test_correlated_real_noise_is_not_a_bias() -> None:
    """Real noise shared over 15 px windows, simulated white of the same size: no bias test and no
    frame-common test may flag it (frame means carry the correlated noise; the split-half covariance
    is not fooled by it), while the neighbour correlation is located."""
    real, sim = _session(1, 15, 0.1), _session(2, 1, 0.1)
    st = decompose(real)
    assert st.corr.fraction > 0.8 and 10 <= st.corr.window_px <= 20
    assert abs(float(np.mean(frame_common(real, st).excess_px2))) < 3e-4
    loc = locate(real, sim)
    flagged = {(t.family, t.kind) for t in loc.significant}
    assert not {f for f, k in flagged if k == "bias"}, flagged
    assert "frame_common" not in {f for f, _ in flagged}
    assert {"correlation_u", "correlation_v"} & {f for f, _ in flagged}


def test_interpretation_table_is_in_the_docs() -> None:
    """Every signature explain can name has its row in docs/explain.md (the table it is taken from)."""
    doc = (ROOT / "docs" / "explain.md").read_text()
    rows = {tuple(m) for m in re.findall(r"^\| (bias|noise) \| ([a-z, ]+) \|", doc, flags=re.M)}
    for quantity, axes in INTERPRETATION:
        assert (quantity, ", ".join(axes)) in rows, (quantity, axes)
