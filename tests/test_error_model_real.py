"""The error model on the real D435 ChArUco set: fitted on five standpoints, applied to the four
between them, and the checkerboard study run again on the corrected recordings."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.app.cli import run_cli
from depthstation.evaluate.errormodel.schema import load_model

FIT = ["pose04", "pose05", "pose06", "pose07", "pose10"]      # the nearest, the farthest, the flattest
HELD_OUT = ["pose03", "pose08", "pose09", "pose11"]          # between them in distance and inclination


NUMBERS = ("frames", "distance_m", "inclination_deg", "accuracy_m", "accuracy_m_u95", "noise_m")


def _table(path: Path) -> dict[str, dict[str, float]]:
    with (path / "standpoints.csv").open(newline="") as fh:
        return {r["standpoint"]: {k: float(r[k]) for k in NUMBERS} for r in csv.DictReader(fh)}


@pytest.fixture(scope="module")
def real(charuco_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("d435model")
    board = ["--board", str(charuco_dir / "board.json"), "--no-figures"]
    assert run_cli(["evaluate", "checkerboard", *[str(charuco_dir / p) for p in FIT], *board,
                    "--out", str(root / "fit")]) == 0
    assert run_cli(["model", "fit", str(root / "fit"), "--out", str(root / "model.json")]) == 0
    assert run_cli(["evaluate", "checkerboard", *[str(charuco_dir / p) for p in HELD_OUT], *board,
                    "--out", str(root / "raw")]) == 0
    for p in HELD_OUT:
        assert run_cli(["correct", str(charuco_dir / p), "--model", str(root / "model.json"),
                        "--out", str(root / f"corrected_{p}")]) == 0
    fixed = [str(root / f"corrected_{p}" / f"{p}.mcap") for p in HELD_OUT]
    assert run_cli(["evaluate", "checkerboard", *fixed, *board, "--out", str(root / "corrected")]) == 0
    return {"model": load_model(root / "model.json"), "raw": _table(root / "raw"),
            "corrected": _table(root / "corrected")}


def test_correction_moves_each_held_out_board_by_the_models_bias(real: dict[str, Any]) -> None:
    """The study's accuracy (orthogonal to the board) moves by -b(z, theta) cos(theta): `correct`
    does on real 1920x1080 depth what the model says, and adds no noise of its own."""
    m = real["model"]
    for p in HELD_OUT:
        raw, fixed = real["raw"][p], real["corrected"][p]
        b, _, inside = m.evaluate(raw["distance_m"], raw["inclination_deg"])
        assert inside, p
        want = -float(b) * np.cos(np.radians(raw["inclination_deg"]))
        moved = fixed["accuracy_m"] - raw["accuracy_m"]
        assert abs(moved - want) < 0.15 * abs(want) + 1e-3, (p, moved, want)
        assert fixed["noise_m"] < 1.1 * raw["noise_m"], p
        assert fixed["frames"] == raw["frames"] == 3


def test_held_out_accuracy_gains_less_than_its_u95_and_the_model_says_why(real: dict[str, Any]) -> None:
    """Five hand-held standpoints of three frames each scatter by about their own U95 (6-9 mm) around
    any smooth field: BIC keeps an offset alone, and the model's own leave-one-standpoint-out check
    finds it barely better than no correction. The held-out boards then improve by less than their
    U95 on average: this set cannot show a gain beyond it (a scan study, or many more standpoints,
    can; tests/test_error_model.py shows it on the tests' room)."""
    m = real["model"]
    assert m.bias.terms == ("offset",)
    v = m.bias.info["validation"]
    assert v["done"] and v["rms_residual_m"] > 0.8 * v["rms_raw_m"]
    before = np.mean([abs(real["raw"][p]["accuracy_m"]) for p in HELD_OUT])
    after = np.mean([abs(real["corrected"][p]["accuracy_m"]) for p in HELD_OUT])
    u95 = np.median([real["raw"][p]["accuracy_m_u95"] for p in HELD_OUT])
    assert before - after < u95, (before, after, u95)
    # nor is it made worse beyond it
    assert after - before < u95
