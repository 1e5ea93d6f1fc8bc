"""The steps of `depthstation demo`, each a thin call into a stage's public functions."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.acquire.guided_capture import GuidedCapture, LiveState
from depthstation.acquire.station import Station, do_calibrate, do_warmup
from depthstation.acquire.views import BOARD_HELP, RerunView, blueprint
from depthstation.app.compare_report import run_compare
from depthstation.app.demo import DEMO_MODEL, DEMO_PROTOCOL, DemoContext, Step
from depthstation.core.errors import CaptureError
from depthstation.core.progress import progress, stderr_console
from depthstation.core.protocol import PROTOCOL_DIR, load_protocol
from depthstation.core.rerun_bridge import RerunTarget, recording
from depthstation.core.results import STANDPOINTS_FILE, read_standpoints
from depthstation.evaluate.checkerboard.run import run_checkerboard
from depthstation.evaluate.explain.run import run_explain
from depthstation.evaluate.scan.run import ScanOptions, run_scan
from depthstation.simulate.checkerboard_session import simulate_checkerboard
from depthstation.simulate.model import load_model
from depthstation.simulate.poses import walk_around, write_tum
from depthstation.simulate.scan_sequence import simulate_scan
from depthstation.simulate.scene import load_scene

# ------------------------------------------------------------------------------ checkerboard study


def evaluate_checkerboard_session(inputs: list[Path], out: Path, ctx: DemoContext, name: str,
                                  frames: int | None = None) -> Path:
    """The checkerboard study of a session, as `evaluate checkerboard` runs it (every frame, up to 150)."""
    rows = run_checkerboard(inputs, PROTOCOL_DIR / f"{DEMO_PROTOCOL}.toml", out, frames=frames,
                     target=ctx.target(out, name))
    ctx.facts[f"{name}_standpoints"] = rows
    return out


def _checkerboard_step(ctx: DemoContext) -> tuple[Path, str]:
    session = ctx.results.get("session")
    protocol = load_protocol(DEMO_PROTOCOL)
    inputs: list[Path] = []
    text_input = ""
    if session is None:
        inputs.append(simulate_checkerboard(protocol, load_model(DEMO_MODEL), ctx.out / "session-simulated",
                                            seed=1))
        ctx.facts["checkerboard_input"] = "simulated session (the guided session step did not run)"
        text_input = " of a directly simulated session (the guided session did not finish)"
    else:
        inputs.append(session)
        done = set(ctx.facts.get("session", {}).get("complete", []))
        missing = [sp.name for sp in protocol.plan.standpoints() if sp.name not in done]
        if missing:
            # the capture's wall-clock budget ran out (a loaded machine): the standpoints it did not
            # reach are simulated directly with the same model, so the figures span the whole plan
            inputs.append(simulate_checkerboard(protocol, load_model(DEMO_MODEL),
                                                ctx.out / "session-simulated", seed=1, standpoints=missing))
            ctx.facts["checkerboard_input"] = (f"guided session ({len(done)} standpoints) + {len(missing)} "
                                               f"simulated directly: {', '.join(missing)}")
            text_input = (f" ({len(done)} guided, {len(missing)} simulated directly: the capture's time "
                          "ran out)")
    out = evaluate_checkerboard_session(inputs, ctx.out / "checkerboard", ctx, "checkerboard")

    rows = read_standpoints(out / STANDPOINTS_FILE)
    noise = [float(r["noise_m"]) for r in rows if r.get("noise_m") == r.get("noise_m")]
    text = f"{len(rows)} standpoints{text_input}"
    if noise:
        text += f", noise {1e3 * min(noise):.2f} to {1e3 * max(noise):.2f} mm"
    paper = paper_relations(rows)
    ctx.facts["paper_relations"] = paper
    if paper["accuracy_over_noise_median"] == paper["accuracy_over_noise_median"]:
        # the paper's 3-4x is at 1280x720; the matching noise is in px of the matched image, so in a
        # coarser mode the depth noise grows by fx_1280 / fx while the unit's errors (angles) do not
        w, h = protocol.streams.width, protocol.streams.height
        cam = load_model(DEMO_MODEL).camera
        grow = cam.reference_fx / cam.depth_intrinsics(w, h).fx
        text += (f"; |accuracy| {paper['accuracy_over_noise_median']:.1f}x the noise (paper: 3-4x at "
                 f"1280x720, where the depth noise is {grow:.1f}x smaller than at {w}x{h})")
    if paper["accuracy_steep_over_frontal_median"] == paper["accuracy_steep_over_frontal_median"]:
        text += (f", {paper['accuracy_steep_over_frontal_median']:.2f}x larger at "
                 f"{paper['steep_inclination_deg']:.0f} deg than head-on")
    return out, text


def paper_relations(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The paper's Section 5.1 relations on the demo's standpoints: median |accuracy| / noise (R3),
    and |accuracy| at the steepest inclination over head-on at the same target distance (R6)."""
    def num(r: dict[str, Any], k: str) -> float:
        try:
            return float(r.get(k, "nan"))
        except (TypeError, ValueError):
            return float("nan")

    ok = [r for r in rows if num(r, "noise_m") > 0 and np.isfinite(num(r, "accuracy_m"))]
    ratio = [abs(num(r, "accuracy_m")) / num(r, "noise_m") for r in ok]
    by_target: dict[float, dict[float, float]] = {}
    for r in ok:
        d, inc = round(num(r, "distance_m"), 1), 5.0 * round(num(r, "inclination_deg") / 5.0)
        by_target.setdefault(d, {})[inc] = abs(num(r, "accuracy_m"))
    steep = max((inc for v in by_target.values() for inc in v), default=float("nan"))
    grow = [v[steep] / v[0.0] for v in by_target.values()
            if 0.0 in v and steep in v and v[0.0] > 0 and steep > 0]
    return {"accuracy_over_noise_median": float(np.median(ratio)) if ratio else float("nan"),
            "steep_inclination_deg": float(steep),
            "accuracy_steep_over_frontal_median": float(np.median(grow)) if grow else float("nan")}


CHECKERBOARD = Step("checkerboard", "checkerboard study of the session", (), _checkerboard_step)

# ------------------------------------------------------------------------------ compare D455 / D435


def _compare_step(ctx: DemoContext) -> tuple[Path, str]:

    ref = ctx.results["checkerboard"]
    sess = simulate_checkerboard(load_protocol(DEMO_PROTOCOL), load_model("d435"), ctx.out / "session-d435",
                                 seed=2)
    other = evaluate_checkerboard_session([sess], ctx.out / "checkerboard-d435", ctx, "checkerboard_d435")
    out = ctx.out / "compare-d455-d435"
    summary = run_compare([ref, other], out, target=ctx.target(out, "compare"))
    ratio = summary["standpoints"]["others"][other.name]["noise_m"]["median_ratio"]
    ctx.facts["noise_ratio_d435_over_d455"] = ratio
    return out, (f"noise D435 / D455 (median over standpoints) = {ratio:.2f} "
                 f"(Intel's formula: 95 / 50 mm = 1.9)")


COMPARE = Step("compare", "compare with a simulated D435 (shorter baseline)", ("step:checkerboard",),
               _compare_step)


# ------------------------------------------------------------------------------ guided session

WARMUP_INTERVAL_S = 15.0     # simulated seconds between temperature samples
WARMUP_ACCELERATE = 300.0    # the simulated clock runs this much faster: 10 min of warm-up in 2 s
MAX_GUIDANCE_S = 60.0        # simulated seconds before a standpoint the operator cannot reach is given up
CAPTURE_BUDGET_S = 150.0     # wall-clock seconds the demo gives the guided capture
RERUN_EVERY = 5              # with --rrd, log every 5th frame of the guided capture


class CaptureBudgetSpent(Exception):
    """Raised from the capture's state callback when the demo's time for it is used up."""


def _guided_capture(st: Any, budget_s: float, target: RerunTarget) -> tuple[list[str], str]:
    """The guided loop (acquire's GuidedCapture with its simulated operator) under a wall-clock budget,
    with a progress bar over the standpoints; returns (complete standpoints, why it stopped)."""

    plan = st.protocol.plan.standpoints()
    on_guidance = st.attach_operator()
    t0 = time.perf_counter()
    stop = "all standpoints done"
    views: list[Any] = []
    calls = [0]
    with recording("depthstation-acquire", target, blueprint(), description=BOARD_HELP) as rec, \
            progress() as bar:
        task = bar.add_task("guided capture", total=len(plan), status="")

        def on_state(state: LiveState) -> None:
            g = state.guidance
            where = "" if g is None or g.distance_m is None else \
                f"at {g.distance_m:.2f} m / {g.inclination_deg or 0.0:.1f} deg"
            bar.update(task, completed=len(state.done) + len(state.skipped),
                       status=f"{state.standpoint.name} -> {state.standpoint.distance_m:.1f} m / "
                              f"{state.standpoint.inclination_deg:.0f} deg: {state.phase} {where}")
            calls[0] += 1
            if rec is not None and cap.info is not None and calls[0] % RERUN_EVERY == 0:
                if not views:        # every RERUN_EVERY-th frame: the live view without a 250 MB file
                    views.append(RerunView(rec, cap.info.depth_units_m))
                views[0](state)
            if time.perf_counter() - t0 > budget_s:
                raise CaptureBudgetSpent

        cap = GuidedCapture(st.camera, st.protocol, st.session, on_guidance=on_guidance, on_state=on_state,
                            max_guidance_s=MAX_GUIDANCE_S)
        try:
            cap.run()
        except CaptureBudgetSpent:
            stop = f"the demo's {budget_s:.0f} s for the capture were used up"
        except CaptureError as exc:
            stop = str(exc)
        finally:
            if cap.events or cap.skipped:
                st.session.set("capture", {"skipped": dict(cap.skipped), "events": list(cap.events)})
    done = [e["name"] for e in st.session.standpoints if e.get("status") == "complete"]
    return done, stop


def _session_step(ctx: DemoContext) -> tuple[Path, str]:
    """Warm-up on an accelerated clock, calibration, then the guided capture with a simulated operator
    (the functions `depthstation acquire session --camera sim` runs)."""

    folder = ctx.out / "session"
    st = Station("sim:" + DEMO_MODEL, DEMO_PROTOCOL, folder, False, 1, False)
    warm = do_warmup(st, WARMUP_INTERVAL_S, WARMUP_ACCELERATE, ctx.target(ctx.out, "session-warmup"))
    if hasattr(st.camera, "set_clock"):
        # the warm-up hands the simulated camera its accelerated clock; the capture must run on
        # frame time again, else the operator's seconds fly by 300 times too fast
        st.camera.set_clock(None)
    cal = do_calibrate(st, True, write=False)
    done, stop = _guided_capture(st, CAPTURE_BUDGET_S, ctx.target(ctx.out, "session-capture"))
    total = len(st.protocol.plan.standpoints())
    ctx.facts["session"] = {"warmup": warm, "calibration_skipped": cal.get("skipped", False),
                            "complete": done, "of": total, "stopped": stop}
    if not done:
        msg = f"no standpoint recorded ({stop})"
        raise RuntimeError(msg)
    return folder, (f"{len(done)} of {total} standpoints recorded ({stop}); warm-up: "
                    f"{warm.get('reason', '?')}; calibration: {'skipped' if cal.get('skipped') else 'done'}")


SESSION = Step("session", "guided session with the simulated D455 (warm-up, calibration, capture)", (),
               _session_step)
# ------------------------------------------------------------------------------ reference-scan study

SCAN_SAMPLES_PER_S = 1.5     # one full walk round the table, sampled this often (about 60 frames)


def _scan_step(ctx: DemoContext) -> tuple[Path, str]:
    """Simulate a walk round the room's table with the D455 model (capture, true trajectory in TUM,
    the room mesh as the reference), then the reference-scan study of it with the trajectory as
    given (the study's default: a registration scale would hide a depth-scale error), checked
    against the reference along the rays."""
    scene = load_scene("room")
    table_height = float(scene.meta.get("table_height_m", 0.75))
    poses = walk_around(np.array([0.0, -table_height, 0.0]), fps=SCAN_SAMPLES_PER_S)
    plan = ctx.out / "scan-walk"
    plan.mkdir(parents=True, exist_ok=True)
    write_tum(plan / "walk.txt", np.arange(len(poses)) / SCAN_SAMPLES_PER_S, poses)
    np.savetxt(plan / "similarity.txt", np.eye(4))
    capture = simulate_scan(scene, plan / "walk.txt", DEMO_MODEL, ctx.out / "scan-capture", seed=4,
                            fps=SCAN_SAMPLES_PER_S, progress=True)  # stamped as sampled: no rate warning
    out = ctx.out / "scan"
    summary = run_scan(capture / "sequence.mcap", capture / "trajectory.txt", capture / "scene.ply", out,
                       ScanOptions(similarity=plan / "similarity.txt", min_count_sequence=200,
                                   target=ctx.target(out, "scan")))
    reg = summary.get("registration", {})
    fit = summary.get("fit_check") or {}
    ctx.facts["scan_registration"] = {k: reg.get(k) for k in ("mode", "scale", "mean_c2m_m", "absorbed")}
    ctx.facts["scan_fit_check"] = fit
    text = f"{len(poses)} frames; {summary.get('registration_caption', '')}"
    if fit:
        text += f"; {100 * fit['off_share']:.1f}% of pixels off the reference (fit check)"
    return out, text


SCAN = Step("scan", "reference-scan study of a simulated room walk", (), _scan_step)
# ------------------------------------------------------------------------------ explain

HIDDEN_EFFECT = "disparity_offset"
# px at 1280 wide (offset_px's unit, an angle): 0.06 px in the demo's 640x360 frames, below their 0.08 px
# disparity noise, so the bias hides under the per-frame noise
HIDDEN_OFFSET_PX = 0.12
EXPLAIN_FRAMES = 20


def _explain_step(ctx: DemoContext) -> tuple[Path, str]:
    """A capture made with a D455 model that carries a concealed disparity offset; explain is given
    only the capture and the plain D455 model, and must find, name and fit what is missing."""

    protocol = load_protocol(DEMO_PROTOCOL)
    base = load_model(DEMO_MODEL)
    # concealed on top of the unit's own offset (the default D455 carries one): explain, given the
    # plain model, must find the difference
    own = base.effect(HIDDEN_EFFECT)
    hidden = base.with_effect(HIDDEN_EFFECT, offset_px=(own.params["offset_px"] if own else 0.0)
                              + HIDDEN_OFFSET_PX)
    hidden.name = f"{DEMO_MODEL}-concealed"
    capture = simulate_checkerboard(protocol, hidden, ctx.out / "explain-capture", seed=5,
                                    frames=EXPLAIN_FRAMES, progress=True)
    out = ctx.out / "explain"

    def tick(msg: str) -> None:
        stderr_console.print(f"  explain: {msg}")

    data = run_explain([capture], protocol.board, base, out, frames=EXPLAIN_FRAMES, seed=0, resimulate=True,
                       parameters={"board": DEMO_PROTOCOL, "model": DEMO_MODEL, "frames": EXPLAIN_FRAMES,
                                   "seed": 0},
                       target=ctx.target(out, "explain"), tick=tick)
    top = data["candidates"][0] if data.get("candidates") else None
    ctx.facts["explain"] = {"hidden": {HIDDEN_EFFECT: {"offset_px": HIDDEN_OFFSET_PX}},
                            "significant": data["mismatch"]["significant"], "selected": data["selected"],
                            "top": top}
    total = (own.params["offset_px"] if own else 0.0) + HIDDEN_OFFSET_PX   # what explain refits: all of it
    text = (f"concealed {HIDDEN_EFFECT} {HIDDEN_OFFSET_PX} px at 1280 wide on top of the unit's "
            f"{total - HIDDEN_OFFSET_PX:+.2f} px (true offset_px {total:+.2f}); mismatch "
            f"{'significant' if data['mismatch']['significant'] else 'not significant'}")
    if top is not None:
        params = ", ".join(f"{k} {v['value']:.4g} {v.get('unit', '')}" if isinstance(v, dict) else f"{k} {v}"
                           for k, v in top.get("params", {}).items())
        before, after = top.get("heldout_rmse_before_m"), top.get("heldout_rmse_after_m")
        text += f"; ranked first: {top['effect']} ({params})"
        if before is not None and after is not None:
            text += f", held-out RMSE {1e3 * before:.2f} -> {1e3 * after:.2f} mm"
    text += f"; selected: {', '.join(data['selected']) or 'nothing'}"
    return out, text


EXPLAIN = Step("explain", "explain a capture with a concealed effect", (), _explain_step)

DEMO_STEPS = [SESSION, CHECKERBOARD, SCAN, EXPLAIN, COMPARE]
