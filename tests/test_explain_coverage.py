"""What explain's data covered: valid depth real against simulated, and the span of fitted axes."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from depthstation.evaluate.explain.coverage import (
    MIN_GAP,
    extrapolation_messages,
    fill_tests,
    fit_domain,
    image_share,
)
from depthstation.evaluate.explain.samples import Samples


def _samples(u: Any, v: Any) -> Samples:
    n = np.asarray(u).size
    return Samples.build(names=["a"], fx=320.0, ppx=319.5, ppy=179.5, baseline_m=0.095, standpoint=0,
                         frame=np.arange(n) % 4, u=u, v=v, z_ref_m=np.linspace(1.0, 3.0, n),
                         err_m=np.zeros(n), inclination_deg=np.linspace(0.0, 30.0, n), albedo=1.0)


def test_a_gap_in_valid_depth_must_be_significant_and_material() -> None:
    real = {"near": {"fill_rate": 0.85, "fill_rate_std": 0.01, "distance_m": 1.0, "inclination_deg": 30.0},
            "edge": {"fill_rate": 0.995, "fill_rate_std": 0.001, "distance_m": 1.0, "inclination_deg": 0.0},
            "noisy": {"fill_rate": 0.90, "fill_rate_std": 0.2, "distance_m": 4.0, "inclination_deg": 0.0}}
    sim = {"near": {"fill_rate": 0.99, "fill_rate_std": 0.01},
           "edge": {"fill_rate": 0.985, "fill_rate_std": 0.001},   # 10 SE apart, but 1 point: edge handling
           "noisy": {"fill_rate": 0.99, "fill_rate_std": 0.2}}     # 9 points, within its frames' spread
    tests = {t.standpoint: t for t in fill_tests(real, sim, {k: 6 for k in real}, {k: 6 for k in sim})}
    one = fill_tests(real, sim, {**{k: 6 for k in real}, "near": 1}, {k: 6 for k in sim})
    assert "near" not in {t.standpoint for t in one}   # one frame: no spread, no test
    assert tests["near"].significant and tests["near"].diff == pytest.approx(-0.14)
    assert tests["near"].se == pytest.approx(np.hypot(0.01, 0.01) / np.sqrt(6))
    assert not tests["edge"].significant and abs(tests["edge"].diff) < MIN_GAP
    assert not tests["noisy"].significant


def test_a_field_fitted_on_a_band_of_rows_is_said_to_extrapolate() -> None:
    rng = np.random.default_rng(1)
    band = _samples(rng.uniform(100, 540, 4000), rng.uniform(120, 240, 4000))   # rows 120-240 of 360
    dom = fit_domain(band)
    lo, hi, share = image_share(dom, band, "v")  # type: ignore[misc]
    assert 119 < lo < 122 and 238 < hi < 241 and share == pytest.approx(120 / 360, abs=0.01)
    assert dom["distance_m"][0] == pytest.approx(1.0, abs=0.02) and dom["inclination_deg"][1] < 30.0
    term = SimpleNamespace(axes=["v"], effect="term_bias_v_poly2")
    said = extrapolation_messages([term], band)  # type: ignore[list-item]
    assert len(said) == 1 and "imager rows 1" in said[0] and "33 %" in said[0]
    field = SimpleNamespace(axes=["tile"], effect="term_bias_tile_field2")   # a 2-D field: rows narrow
    assert len(extrapolation_messages([field], band)) == 1  # type: ignore[list-item]
    across = _samples(rng.uniform(5, 635, 4000), rng.uniform(5, 355, 4000))
    assert extrapolation_messages([term], across) == []  # type: ignore[list-item]
    assert extrapolation_messages([SimpleNamespace(axes=["distance"], effect="t")], band) == []  # type: ignore[list-item]


def test_regions_the_refit_leaves_are_a_warning() -> None:
    from depthstation.core.run_warnings import collecting
    from depthstation.evaluate.explain.locate import GroupTest, LocateResult
    from depthstation.evaluate.explain.run import warn_remaining

    def test(significant: bool, family: str) -> GroupTest:
        return GroupTest(family, "bias", "x", {}, 0.0, 0.0, 1e-3, 1e-4, 10.0, 20.0, 1e-6, 100, 100,
                         significant=significant)

    chosen = SimpleNamespace(selected=[SimpleNamespace(effect="disparity_offset")])
    with collecting() as said:
        warn_remaining(LocateResult([test(False, "grid")]), chosen)  # type: ignore[arg-type]
        assert said == []
        warn_remaining(LocateResult([test(True, "albedo"), test(True, "grid"), test(False, "u")]),
                       chosen)  # type: ignore[arg-type]
    assert [w.code for w in said] == ["explain-remains"]
    assert "2 test(s)" in said[0].message and "albedo, grid" in said[0].message
    assert "disparity_offset" in said[0].message
