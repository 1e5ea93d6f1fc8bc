"""A guided session with the simulated D455 and the simulated operator, evaluated by the
checkerboard study against the simulator's truth; the end of the range ends a trajectory; a seed
repeats a session exactly."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.protocol import Plan, Protocol, Streams, Tolerances


def run_session(out: Path, proto: Protocol, seed: int, model: Any = "d455-ideal") -> tuple[list[Any], Any]:
    """In-process: the CLI's wiring (operator steps on frame time) without the subprocess."""
    from depthstation.acquire.guided_capture import GuidedCapture
    from depthstation.core.capture.session import Session
    from depthstation.simulate.operator import SimulatedOperator, Stance
    from depthstation.simulate.simulated_camera import SimulatedCamera

    cam = SimulatedCamera(model, board=proto.board, seed=seed)
    op = SimulatedOperator(proto.board, Stance(range_m=proto.plan.start_distance_m + 0.3, azimuth_deg=-4.0,
                                               yaw_deg=3.0), seed=seed)
    fps = float(proto.streams.fps)
    cam.set_pose(op.pose(0.0))
    trail: list[tuple[float, float]] = []

    def on_guidance(g: Any, fs: Any, t_s: float) -> None:
        op.step(g, t_s)
        cam.set_pose(op.pose(t_s + 1.0 / fps))
        trail.append((t_s, op.stance.azimuth_deg))

    session = Session.create(out, protocol=proto)
    outcomes = GuidedCapture(cam, proto, session, on_guidance=on_guidance, max_guidance_s=60.0).run()
    return outcomes, trail


def two_by_two(frames: int = 10) -> Protocol:
    return Protocol("truth", streams=Streams(width=424, height=240, fps=30),
                    plan=Plan(frames_per_standpoint=frames, start_distance_m=1.0, step_m=0.6,
                              max_distance_m=1.6, inclinations_deg=(0.0, 30.0)),
                    tolerances=Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3))


@pytest.fixture(scope="module")
def guided(tmp_path_factory: pytest.TempPathFactory) -> tuple[Protocol, Path, list[Any]]:
    proto = two_by_two()
    out = tmp_path_factory.mktemp("guided") / "s"
    outcomes, _ = run_session(out, proto, seed=5)
    return proto, out, outcomes


def test_guided_session_evaluates_to_the_simulators_truth(guided: tuple[Protocol, Path, list[Any]]) -> None:
    """Judged: the evaluation of the guided session agrees with the simulator's truth (the
    checkerboard study's own tolerances: distance 0.5 %, pose inclination 0.5 degrees)."""
    from depthstation.core.capture.session import Session
    from depthstation.evaluate.checkerboard.study import evaluate_recording

    proto, out, outcomes = guided
    plan = proto.plan.standpoints()
    assert [o.status for o in outcomes] == ["complete"] * len(plan)
    recs = Session.open(out).recordings()
    assert [r.name for r in recs] == [sp.name for sp in plan]
    for rec, sp in zip(recs, plan, strict=True):
        truth = rec.metadata["truth"]
        # the operator put the camera inside the protocol's tolerances (truth, not the station's view)
        assert abs(truth["distance_m"] - sp.distance_m) <= proto.tolerances.distance_m, rec.name
        assert abs(truth["inclination_deg"] - sp.inclination_deg) <= proto.tolerances.inclination_deg
        r = evaluate_recording(rec, proto.board, frames=proto.plan.frames_per_standpoint)
        assert r.truth == truth
        assert r.frames_used == proto.plan.frames_per_standpoint, r.rejected
        f = r.figures
        assert abs(f["distance_m"] - truth["distance_m"]) < 0.005 * truth["distance_m"], rec.name
        assert abs(f["inclination_deg"] - truth["inclination_deg"]) < 0.5, rec.name
        # noise: RMS of ~10 frames x thousands of board pixels; the sampling error of an RMS over N
        # values is 1/sqrt(2N) (< 1 %), the rest of the 10 % is the plane fit and flying pixels
        n = f["pixels_per_frame"] * r.frames_used
        assert f["noise_m"] == pytest.approx(truth["noise_m"], rel=0.10 + 3 / np.sqrt(2 * n)), rec.name


def test_end_of_range_moves_to_the_next_trajectory(tmp_path: Path) -> None:
    """A protocol reaching past the camera's range: the fill rate on the board collapses at 2.2 m
    (a unit whose range ends at ~1.7 m), the station skips the rest of that trajectory, starts
    the next inclination at the first distance again, and says so in session.json."""
    from depthstation.core.capture.session import Session
    from depthstation.simulate.model import load_model

    proto = Protocol("range", streams=Streams(width=424, height=240, fps=30),
                     plan=Plan(frames_per_standpoint=4, start_distance_m=1.0, step_m=1.2, max_distance_m=2.2,
                               inclinations_deg=(0.0, 30.0)),
                     tolerances=Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3,
                                           end_fill_rate=0.5))
    short = load_model("d455-ideal").with_effect("dropout", range_z50_m=1.7, range_width_m=0.05)
    outcomes, _ = run_session(tmp_path / "s", proto, seed=1, model=short)
    plan = proto.plan.standpoints()
    names = [sp.name for sp in plan]
    assert [(o.name, o.status) for o in outcomes] == [(names[0], "complete"), (names[1], "end_of_range"),
                                                      (names[2], "complete"), (names[3], "end_of_range")]
    s = Session.open(tmp_path / "s")
    cap = s.data["capture"]
    assert sorted(cap["skipped"]) == [names[1], names[3]]
    ev = [e for e in cap["events"] if e["event"] == "end_of_range"]
    assert [(e["standpoint"], e["trajectory"]) for e in ev] == [(names[1], plan[1].trajectory),
                                                               (names[3], plan[3].trajectory)]
    assert plan[1].trajectory != plan[3].trajectory
    assert [e["name"] for e in s.standpoints if e["status"] == "complete"] == [names[0], names[2]]


def test_a_seed_repeats_the_session(tmp_path: Path) -> None:
    """The operator steps on frame time and the camera's noise is drawn from (seed, frame): two runs
    with one seed give the same walk and the same measured standpoints; another seed does not."""
    proto = Protocol("seed", streams=Streams(width=424, height=240, fps=30),
                     plan=Plan(frames_per_standpoint=4, start_distance_m=1.2, max_distance_m=1.2,
                               inclinations_deg=(20.0,)),
                     tolerances=Tolerances(distance_m=0.05, inclination_deg=3.0, still_seconds=0.3))
    a, trail_a = run_session(tmp_path / "a", proto, seed=7)
    b, trail_b = run_session(tmp_path / "b", proto, seed=7)
    _, trail_c = run_session(tmp_path / "c", proto, seed=8)
    assert trail_a == trail_b and len(trail_a) > 10
    assert [o.measured for o in a] == [o.measured for o in b]
    assert trail_c != trail_a
