"""Discovery beyond the catalogue, end to end: effects the simulator's catalogue does not have,
written into simulated captures by this test in its own forms (tests/explain_cases.conceal), never
through `simulate.effects` or the library's bases. Each is below the per-pixel noise (0.08 px) or
zero-mean over the board; explain must locate it, name its quantity and axes in `discovered`,
recover its coefficient within 3 standard errors, lower the held-out RMSE and, re-simulated with the
written model.toml, leave no significant mismatch. Small frames (320x180, 6 frames, 1-3 m).
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from explain_cases import conceal, wide_protocol

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """9-10 standpoints at 1-3 m, 0 and 30 deg, 320x180, 6 frames (the plain D455 model)."""
    from depthstation.simulate.checkerboard_session import simulate_checkerboard

    p = wide_protocol(320, 180)
    p = replace(p, plan=replace(p.plan, start_distance_m=1.0, step_m=0.5, max_distance_m=3.0))
    return simulate_checkerboard(p, "d455-ideal", tmp_path_factory.mktemp("small") / "sim", frames=6, seed=11)


def _run(real: Path, out: Path) -> dict[str, Any]:
    """explain in-process (the CLI's own path), with re-simulation."""
    from depthstation.evaluate.explain.run import run_explain
    from depthstation.simulate.model import load_model

    return run_explain([real], ROOT / "protocols" / "demo-d455.toml", load_model("d455-ideal"), out, frames=6,
                       seed=3)


def _shift(z: Any, delta: Any, cam: dict[str, float]) -> Any:
    """Depth of a disparity error delta (px; + = disparity too large = too near), exactly."""
    fb = cam["fx"] * cam["baseline_m"]
    return fb / (fb / z + delta) - z


def _xy(u: Any, v: Any, cam: dict[str, float]) -> tuple[Any, Any]:
    return (u - cam["ppx"]) / cam["fx"], (v - cam["ppy"]) / cam["fx"]


# name: (hidden effect in its own form, random?, expected quantity, axes, coefficients (truth))
ROLL = 2e-3   # rad: right imager rolled about the optical axis
CASES: dict[str, tuple[Any, bool, str, list[str], dict[str, float]]] = {
    # relative roll: delta = -f roll y, zero-mean over the board (the catalogue alone: "no mismatch reported")
    "roll_bias_along_v": (lambda z, u, v, b, t, temp, cam: _shift(z, -cam["fx"] * ROLL * _xy(u, v, cam)[1],
                                                                  cam),
                          False, "bias", ["v"], {"c1": -ROLL}),
    # pattern SNR falling like 1/z^2: disparity noise 0.025 px * z/m on top (depth noise ~ z^3)
    "noise_faster_than_z2": (lambda z, u, v, b, t, temp, cam, rng: _shift(
        z, 0.025 * z * rng.standard_normal(z.shape), cam),
                             True, "noise", ["distance"], {"c1": 0.025 ** 2}),
    # one disparity jump per frame, shared by all pixels (micro-thermal yaw jitter), 0.05 px RMS
    "frame_common_noise": (lambda z, u, v, b, t, temp, cam, rng: _shift(z, 0.05 * rng.standard_normal(), cam),
                           True, "noise", ["frame"], {"c": 0.05 ** 2}),
    # a fixed-pattern rectification residual: a saddle over the image, zero-mean
    "saddle_field": (lambda z, u, v, b, t, temp, cam: _shift(
        z, 0.6 * (_xy(u, v, cam)[0] ** 2 - _xy(u, v, cam)[1] ** 2)
        + 0.8 * _xy(u, v, cam)[0] * _xy(u, v, cam)[1], cam),
        False, "bias", ["tile"], {"c_x": 0.0, "c_y": 0.0, "c_xx": 0.6, "c_xy": 0.8, "c_yy": -0.6}),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_concealed_effect_outside_the_catalogue_is_discovered(case: str, small_session: Path,
                                                               tmp_path: Path) -> None:
    hidden, random, quantity, axes, truth = CASES[case]
    info = json.loads((small_session / "truth.json").read_text())["stream_info"]
    fx = info["depth_intrinsics"]["fx"]
    if case == "roll_bias_along_v":   # in the term's units: px per unit of y = (v - ppy) / fx
        truth = {"c1": -fx * ROLL}
    real = conceal(small_session, tmp_path / "real", hidden, noise_seed=5 if random else None)
    data = _run(real, tmp_path / "out")
    assert data["mismatch"]["significant"], "the concealed effect is located"
    assert len(data["discovered"]) == 1, data["discovered"]
    d = data["discovered"][0]
    assert d["quantity"] == quantity and d["axes"] == axes
    assert set(d) == {"quantity", "axes", "expression", "coefficients", "heldout_rmse_before_m",
                      "heldout_rmse_after_m", "interpretation"}
    for name, value in truth.items():
        c = d["coefficients"][name]
        assert abs(c["value"] - value) <= 3 * c["stderr"], (name, c, value)
    assert d["heldout_rmse_after_m"] < d["heldout_rmse_before_m"]
    assert d["interpretation"] and "[" in d["expression"]
    assert not data["missing_physics"], "no catalogue effect takes the place of the discovered term"
    # the term is written into model.toml and the re-simulation renders it: no mismatch remains
    term = data["discovery"]["terms"][0]["term"]
    assert f"[effects.{term}]" in (tmp_path / "out" / "model.toml").read_text()
    assert not data["mismatch_after"]["significant"], data["mismatch_after"]["regions"]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Missing physics outside the catalogue" in report
    fig = next((tmp_path / "out").glob("discovered_1_*.png"))
    assert fig.stat().st_size > 10_000


def test_null_discovers_nothing(small_session: Path, tmp_path: Path) -> None:
    data = _run(conceal(small_session, tmp_path / "real", None), tmp_path / "out")
    assert data["selected"] == [] and data["discovered"] == []
    assert not data["mismatch"]["significant"] and not data["mismatch_after"]["significant"]
    assert "Nothing found" in (tmp_path / "out" / "report.md").read_text()


def test_window_correlated_noise_is_the_catalogue_effect(small_session: Path, tmp_path: Path) -> None:
    """Extra disparity noise shared over 9 x 9 pixels (a census window), written here by a running
    sum: the catalogue's window_noise takes it (its width measured from the neighbours) as a
    calibration, not a generic term, and not the white disparity_noise."""
    def boxed(z, u, v, b, t, temp, cam, rng):  # type: ignore[no-untyped-def]
        w = 9
        white = rng.standard_normal((z.shape[0] + w - 1, z.shape[1] + w - 1))
        c = np.cumsum(np.cumsum(np.pad(white, ((1, 0), (1, 0))), axis=0), axis=1)
        box = (c[w:, w:] - c[:-w, w:] - c[w:, :-w] + c[:-w, :-w]) / w   # mean of w^2, times w
        return _shift(z, 0.07 * box, cam)

    data = _run(conceal(small_session, tmp_path / "real", boxed, noise_seed=8), tmp_path / "out")
    assert data["discovered"] == []
    assert data["selected"] == ["window_noise"]
    cal = data["calibrated"][0]["params"]["sigma_px"]
    assert cal["new"] == pytest.approx(np.hypot(0.07, 0.07), rel=0.2)
    nc = data["mismatch"]["noise_correlation"]
    assert nc["real"]["correlated_fraction"] > nc["sim"]["correlated_fraction"]
    assert not data["mismatch_after"]["significant"], data["mismatch_after"]["regions"]
