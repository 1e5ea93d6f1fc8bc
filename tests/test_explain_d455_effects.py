"""explain, started from the clean camera (d455-ideal), on data with the effects the d455 preset adds,
each written by this test's own code (tests/d455_effects.py: own forms, own random field, own colour
camera), never by the simulator's effect modules: it names the effect, refits it, and the
re-simulation is clean; the null stays clean.

The session: 12 standpoints (1-4 m x 0/30/60 deg, 640x360) of 6 frames, simulated with
d455-ideal; the effects are written onto its frames. The paper's unit (all effects together) is
checked at 18 standpoints x 15 frames (marked session_size, deselected by default: run with
`-m session_size`).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.protocol import load_protocol
from depthstation.evaluate.explain.run import run_explain
from depthstation.simulate.checkerboard_session import simulate_checkerboard
from depthstation.simulate.model import load_model

sys.path.insert(0, str(Path(__file__).parent))
from d455_effects import PAPER_UNIT, Unit, write_unit

ROOT = Path(__file__).resolve().parents[1]
BOARD = ROOT / "protocols" / "demo-d455.toml"


def _protocol(step: float = 1.0, max_m: float = 4.0) -> Any:
    p = load_protocol("demo-d455")
    plan = replace(p.plan, start_distance_m=1.0, step_m=step, max_distance_m=max_m,
                   inclinations_deg=(0.0, 30.0, 60.0))
    return replace(p, plan=plan)


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 standpoints x 6 frames of the clean camera."""
    return simulate_checkerboard(_protocol(), "d455-ideal", tmp_path_factory.mktemp("clean") / "sim",
                                 frames=6, seed=11)


def _explain(clean: Path, tmp: Path, unit: Unit, frames: int = 6) -> dict[str, Any]:
    real = write_unit(clean, tmp / "real", unit, seed=5)
    return run_explain([real], BOARD, load_model("d455-ideal"), tmp / "out", frames=frames, seed=3)


def _clean_after(data: dict[str, Any]) -> None:
    """No region differs after the refit (Holm), and the board pose's spread matches too."""
    assert not data["mismatch_after"]["significant"], data["mismatch_after"]["regions"]
    assert not data["pose_spread_after"]["significant"], data["pose_spread_after"]["tests"]


def _param(data: dict[str, Any], effect: str, name: str) -> float:
    c = next(x for x in data["candidates"] if x["effect"] == effect)
    return float(c["params"][name]["value"])


def test_the_null_stays_clean(clean: Path, tmp_path: Path) -> None:
    """The clean camera against itself: nothing selected, discovered or written, nothing after."""
    data = _explain(clean, tmp_path, Unit())
    assert data["selected"] == [] and data["discovered"] == [] and data["fine_terms"] == []
    assert data["pose_spread"]["named"] is None and not data["pose_spread"]["significant"]
    assert not data["mismatch"]["significant"]
    _clean_after(data)


def test_slant_scale_is_named_and_refitted(clean: Path, tmp_path: Path) -> None:
    """z read long by 2 % x (1/cos(theta) - 1): slant_scale alone, k within 10 %."""
    data = _explain(clean, tmp_path, Unit(slant_k=0.02))
    assert data["selected"] == ["slant_scale"] and data["discovered"] == []
    assert _param(data, "slant_scale", "k") == pytest.approx(0.02, rel=0.1)
    _clean_after(data)


def test_the_colour_camera_is_named_from_the_board_pose_spread(clean: Path, tmp_path: Path) -> None:
    """A colour image blurred, vignetted and noisy (this test's camera): the depth is untouched, the
    reference distance scatters more, most far away and steep; named color_camera from that
    evidence, its excess fitted as reference_pose_noise, and the spread matches after."""
    data = _explain(clean, tmp_path, Unit(color_psf_px=0.8))
    ps = data["pose_spread"]
    assert ps["named"] == "color_camera" and len(ps["significant"]) >= 6
    tests = {t["standpoint"]: t for t in ps["tests"]}
    far = [t["real_m"] for t in tests.values() if t["distance_m"] > 2.5]
    near = [t["real_m"] for t in tests.values() if t["distance_m"] < 1.2]
    assert np.median(far) > 3 * np.median(near)          # it grows with distance
    assert all(t["ratio"] > 1 for t in tests.values() if t["significant"])
    term = next(f for f in data["fine_terms"] if f["effect"] == "reference_pose_noise")
    assert term["named"] == "color_camera" and 0.005 < term["params"]["corner_sigma_px"] < 0.1
    assert data["selected"] == [] and data["discovered"] == []   # no depth effect invented for it
    _clean_after(data)


def test_catalogue_shapes_are_the_d455_presets() -> None:
    """The shape parameters explain's catalogue fixes (not fitted) are the d455 preset's own."""
    from depthstation.evaluate.explain.basis import SHAPE

    d455 = load_model("d455")
    for name, params in SHAPE.items():
        effect = d455.effect(name)
        assert effect is not None
        for key, value in params.items():
            assert effect.params[key] == value, (name, key)


@pytest.mark.slow
@pytest.mark.session_size
def test_the_paper_unit_has_each_effect_named(tmp_path_factory: pytest.TempPathFactory) -> None:
    """All the d455 preset's effects at once (this module's PAPER_UNIT), at the session size a user
    captures: 18 standpoints (1-3.5 m x 0/30/60 deg) x 15 frames. Each effect is named with its
    value; what the re-simulation still leaves is in docs/explain.md (the depth side is not yet
    clean: the colour pose's tilt jitter reaches the within-frame variance, which incidence_noise
    absorbs, 8 % high)."""
    tmp = tmp_path_factory.mktemp("paper")
    sim = simulate_checkerboard(_protocol(step=0.5, max_m=3.5), "d455-ideal", tmp / "sim", frames=15, seed=11)
    data = _explain(sim, tmp, PAPER_UNIT, frames=15)
    assert {"depth_scale", "slant_scale", "disparity_offset", "incidence_noise"} <= set(data["selected"])
    assert _param(data, "depth_scale", "scale_error") == pytest.approx(0.006, abs=0.001)
    assert _param(data, "slant_scale", "k") == pytest.approx(0.02, rel=0.1)
    # written -0.10 px at 640x360 (fx 337.2): explain states it in px of the 1280-wide mode (fx 674.4)
    assert _param(data, "disparity_offset", "offset_px") == pytest.approx(-0.20, rel=0.2)
    assert "slant_bias" in data["selected"]
    assert _param(data, "slant_bias", "offset_px_at_45") == pytest.approx(-0.05, rel=0.2)
    assert _param(data, "incidence_noise", "sigma_px") == pytest.approx(0.08, rel=0.15)
    # the static pattern: a bias fixed in pixel coordinates, read as the unit's static pattern
    tile = [d for d in data["discovered"] if d["quantity"] == "bias" and d["axes"] == ["tile"]]
    assert tile and "static_pattern" in tile[0]["interpretation"][0]
    assert data["pose_spread"]["named"] == "color_camera" and len(data["pose_spread"]["significant"]) >= 12
    assert not data["pose_spread_after"]["significant"]
