"""Explain end to end: simulated sessions with a concealed effect written by the test, and real D435 data."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from explain_cases import conceal

ROOT = Path(__file__).resolve().parents[1]
EXE = ROOT / ".venv" / "bin" / "depthstation"


@pytest.fixture(scope="module")
def plain_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from simulate.checkerboard import simulate_checkerboard

    out = tmp_path_factory.mktemp("plain") / "sim"
    return simulate_checkerboard("demo-d455", "d455", out, frames=6, seed=11)


def _explain(real: Path, out: Path) -> dict:
    r = subprocess.run([str(EXE), "explain", str(real), "--board", str(ROOT / "protocols" / "demo-d455.toml"),
                        "--model", "d455", "--out", str(out), "--frames", "6", "--seed", "3"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads((out / "explain.json").read_text())


def test_concealed_focal_mismatch(plain_session: Path, tmp_path: Path) -> None:
    """Right focal 0.1 % longer, written as a column-dependent disparity term: a zero-mean wedge."""
    k = 0.001

    def wedge(z, u, v, black, t, temp, cam):  # type: ignore[no-untyped-def]
        fb = cam["fx"] * cam["baseline_m"]
        return fb / (fb / z + k * (u - cam["ppx"])) - z

    real = conceal(plain_session, tmp_path / "real", wedge)
    data = _explain(real, tmp_path / "out")
    top = data["candidates"][0]
    assert top["effect"] == "lr_focal_mismatch" and top["selected"]
    assert data["selected"][0] == "lr_focal_mismatch"
    assert top["params"]["ratio"]["value"] == pytest.approx(k, rel=0.25)
    assert top["heldout_rmse_after_m"] < top["heldout_rmse_before_m"]
    for f in ("model.toml", "report.md", "result.json", "residual_grid.png", "residual_columns.png"):
        assert (tmp_path / "out" / f).is_file()
    assert "lr_focal_mismatch" in (tmp_path / "out" / "model.toml").read_text()
    # the re-simulation with the new model leaves no significant column-wise bias
    after = data["mismatch_after"]
    assert not [r for r in after["regions"] if r["family"] == "column" and r["kind"] == "bias"]


def test_concealed_dark_squares(plain_session: Path, tmp_path: Path) -> None:
    """Black squares measured 2 mm/m^2 * z^2 farther: half of it hides in every all-pixel mean."""
    def dark(z, u, v, black, t, temp, cam):  # type: ignore[no-untyped-def]
        return np.where(black, 2e-3 * z * z, 0.0)

    data = _explain(conceal(plain_session, tmp_path / "real", dark), tmp_path / "out")
    top = data["candidates"][0]
    info = json.loads((plain_session / "truth.json").read_text())["stream_info"]
    fb = info["baseline_m"] * info["depth_intrinsics"]["fx"]
    assert top["effect"] == "albedo_bias" and top["selected"] and top["role"] == "missing_physics"
    assert top["params"]["offset_px_black"]["value"] == pytest.approx(-2e-3 * fb, rel=0.25)
    assert top["heldout_rmse_after_m"] < top["heldout_rmse_before_m"]
    after = data["mismatch_after"]
    assert not [r for r in after["regions"] if r["family"] == "albedo" and r["kind"] == "bias"]


def test_null_session_selects_nothing(plain_session: Path, tmp_path: Path) -> None:
    real = conceal(plain_session, tmp_path / "real", None)
    data = _explain(real, tmp_path / "out")
    assert data["missing_physics"] == []
    assert not data["mismatch"]["significant"]


def test_bad_input_exit_code(tmp_path: Path) -> None:
    r = subprocess.run([str(EXE), "explain", str(tmp_path / "nope"), "--board", "x.json", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "not found" in r.stderr


def test_real_d435_runs_end_to_end(charuco_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = subprocess.run([str(EXE), "explain", str(charuco_dir / "pose03"), str(charuco_dir / "pose05"),
                        str(charuco_dir / "pose07"), "--board", str(charuco_dir / "board.json"),
                        "--model", "d435", "--out", str(out), "--frames", "3", "--no-resimulate"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((out / "explain.json").read_text())
    assert isinstance(data["mismatch"]["significant"], bool)
    assert data["candidates"] and np.isfinite(data["candidates"][0]["delta_bic"])
    assert "# Explain" in (out / "report.md").read_text()
