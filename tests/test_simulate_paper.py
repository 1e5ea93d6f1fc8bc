"""The default simulated D455 measures like the paper's unit (Section 5.1), through the station's own
checkerboard study: deviations from the reference plane several times the noise (R3), noise growing
with distance but not with inclination (R5), accuracy worse with distance and inclination (R6).
`benchmarks/bench_paper.py` reproduces the whole table at the paper's size; this is its small form."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

DISTANCES = (1.0, 2.2, 3.4)
INCLINATIONS = (0.0, 60.0)
FRAMES = 4


def _protocol(root: Path) -> Path:
    text = (Path(__file__).parents[1] / "protocols" / "demo-d455.toml").read_text()
    text = (text.replace("frames_per_standpoint = 10", f"frames_per_standpoint = {FRAMES}")
            .replace("step_m = 0.8", "step_m = 1.2").replace("max_distance_m = 2.6", "max_distance_m = 3.4")
            .replace("inclinations_deg = [0.0, 35.0]", "inclinations_deg = [0.0, 60.0]")
            .replace("width = 640", "width = 1280").replace("height = 360", "height = 720"))
    p = root / "p.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def paper_rows(tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    pytest.importorskip("open3d")
    from depthstation.core.capture.registry import open_inputs
    from depthstation.core.protocol import load_protocol
    from depthstation.evaluate.checkerboard.study import evaluate_recording
    from depthstation.simulate.checkerboard_session import simulate_checkerboard, stream_info_for
    from depthstation.simulate.effects.base import PixelContext
    from depthstation.simulate.model import load_model

    root = tmp_path_factory.mktemp("paper")
    proto = load_protocol(_protocol(root))
    model = load_model("d455")
    out = simulate_checkerboard(proto, model, root / "sim", frames=FRAMES, seed=2)
    di = stream_info_for(proto, model).depth_intrinsics
    plan = {s.name: s for s in proto.plan.standpoints()}
    rows = []
    for rec in open_inputs([out]):
        r = evaluate_recording(rec, proto.board, frames=FRAMES)
        assert r.frames_used == FRAMES, (rec.name, r.rejected)
        sp = plan[rec.name]
        # the model's own signature at the board centre: expected z bias and z noise
        ctx = PixelContext(z_m=np.array([sp.distance_m]), inclination_deg=np.array([sp.inclination_deg]),
                           u=di.ppx, v=di.ppy, albedo=0.85, fx=di.fx, ppx=di.ppx, ppy=di.ppy,
                           baseline_m=model.camera.baseline_m)
        expected = abs(float(model.bias_m(ctx)[0])) / float(np.sqrt(model.variance_m2(ctx)[0]))
        rows.append({"d": sp.distance_m, "inc": sp.inclination_deg, "noise": r.figures["noise_m"],
                     "acc": abs(r.figures["accuracy_m"]), "expected_ratio": expected,
                     "frames": r.frames_used})
    assert len(rows) == len(DISTANCES) * len(INCLINATIONS)
    assert all(r["frames"] == FRAMES for r in rows), rows
    return rows


def _at(rows: list[dict[str, Any]], d: float, inc: float) -> dict[str, Any]:
    return next(r for r in rows if r["d"] == d and r["inc"] == inc)


def test_accuracy_is_several_times_the_noise(paper_rows: list[dict[str, Any]]) -> None:
    """R3: |accuracy| / noise 3-4 in the paper; each standpoint within 35 % of what the model's
    bias and noise say at the board centre (the board's pixels spread round it), median 2.5-6."""
    ratios = [r["acc"] / r["noise"] for r in paper_rows]
    for r, q in zip(paper_rows, ratios, strict=True):
        assert abs(q / r["expected_ratio"] - 1) < 0.35, (r, q)
    assert 2.5 <= float(np.median(ratios)) <= 6.0, ratios


def test_noise_grows_with_distance_not_with_inclination(paper_rows: list[dict[str, Any]]) -> None:
    """R5: noise ~ z^2 (Intel's RMS law: 1.2 m -> 2.2 m is 4.8x, 3.4 m 11.6x over 1 m, within 30 %)
    at both inclinations; at 60 deg 0.8-1.5x head-on (a noise that did not grow with the incidence
    would read cos 60 = 0.5x: the plane fit sees it foreshortened)."""
    for inc in INCLINATIONS:
        n = [_at(paper_rows, d, inc)["noise"] for d in DISTANCES]
        for d, x in zip(DISTANCES, n, strict=True):
            assert abs(x / n[0] / (d / DISTANCES[0]) ** 2 - 1) < 0.3, (inc, d, n)
    for d in DISTANCES:
        q = _at(paper_rows, d, 60.0)["noise"] / _at(paper_rows, d, 0.0)["noise"]
        assert 0.8 <= q <= 1.5, (d, q)


def test_accuracy_worsens_with_distance_and_inclination(paper_rows: list[dict[str, Any]]) -> None:
    """R6: |accuracy| grows with distance at each inclination, and at every distance it is larger
    at 60 deg than head-on (the model says 1.6-2.0x; more than 1.2x asked)."""
    for inc in INCLINATIONS:
        a = [_at(paper_rows, d, inc)["acc"] for d in DISTANCES]
        assert a[0] < a[1] < a[2], (inc, a)
    for d in DISTANCES:
        assert _at(paper_rows, d, 60.0)["acc"] > 1.2 * _at(paper_rows, d, 0.0)["acc"], d
