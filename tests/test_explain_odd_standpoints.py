"""Standpoint heterogeneity (evaluate/explain/locate.heterogeneity_tests), on sessions written here
sample by sample, not by the simulator: hand-held standpoints whose real-minus-simulated disparity
planes scatter (0.1 px offset, 0.2 slopes: colour poses of a held board), one of them with its depth
off its board pose by 0.8 px (the board moved between the colour and the depth frame). That one is
flagged, no other; without it none is."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.evaluate.explain.locate import heterogeneity_tests, locate
from depthstation.evaluate.explain.samples import Samples, concat

FX, B, W, H = 400.0, 0.095, 320, 240
N_SP, N_FR = 12, 5
HOLM_FLOOR = 0.05 / 200


def _session(seed: int, odd: int | None = None, scatter: float = 1.0) -> Samples:
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[40:200:3, 40:280:3].astype(np.float64)
    x, y = (u - W / 2) / FX, (v - H / 2) / FX
    names = [f"sp{k:02d}" for k in range(N_SP)]
    parts = []
    for k in range(N_SP):
        z = 1.0 + 0.25 * k
        plane = scatter * rng.normal(0.0, [0.1, 0.2, 0.2])
        if k == odd:
            plane[0] += 0.8
        for i in range(N_FR):
            delta = 0.08 * rng.standard_normal(u.shape) + plane[0] + plane[1] * x + plane[2] * y \
                + 0.01 * rng.standard_normal()
            kk = z * z / (FX * B)
            parts.append(Samples.build(names=names, fx=FX, ppx=W / 2, ppy=H / 2, baseline_m=B, standpoint=k,
                                       frame=i, u=u.ravel(), v=v.ravel(), z_ref_m=z,
                                       err_m=-kk * delta.ravel(), inclination_deg=20.0, albedo=0.85,
                                       time_s=k * 30.0 + i / 30.0))
    return concat(parts)


@pytest.fixture(scope="module")
def sim() -> Samples:
    return _session(1, scatter=0.0)


def test_a_standpoint_whose_depth_is_off_its_board_pose_is_flagged_alone(sim: Samples) -> None:
    tests = heterogeneity_tests(_session(2, odd=5), sim)
    assert len(tests) == N_SP
    flagged = [t.label for t in tests if t.p < HOLM_FLOOR]
    assert flagged == ["sp05"], [(t.label, t.p) for t in tests]
    odd = next(t for t in tests if t.label == "sp05")
    assert odd.coords["component"] == "offset" and abs(odd.diff) == pytest.approx(0.8, abs=0.3)
    summary = locate(_session(2, odd=5), sim).summary()
    assert summary["heterogeneous_standpoints"] == ["sp05"]
    assert "sp05" in summary["standpoints"]


def test_hand_held_scatter_alone_flags_no_standpoint(sim: Samples) -> None:
    tests = heterogeneity_tests(_session(3), sim)
    assert tests and min(t.p for t in tests) > HOLM_FLOOR, [(t.label, t.p) for t in tests]
