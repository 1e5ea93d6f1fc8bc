"""Explain end to end: evaluate real, simulate the same standpoints, locate, attribute, refit, check.

The simulation re-renders every real standpoint at the pose the real evaluation estimated, frame
for frame with the real frames' time stamps and temperatures, and is evaluated by the same
checkerboard study (contract 3), so both sides share every step but the sensor.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.board import Board
from depthstation.core.camera_model import StreamInfo, ray_xy
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.parallel import ChunkRunner
from depthstation.core.protocol import load_board
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import result_folder
from depthstation.core.run_warnings import warn
from depthstation.evaluate.checkerboard.chunks import StandpointOptions, run_standpoints
from depthstation.evaluate.checkerboard.run import check_usable, prepare_checkerboard, say_warnings
from depthstation.evaluate.checkerboard.study import evaluate_frames
from depthstation.evaluate.explain import pose_spread
from depthstation.evaluate.explain.attribute import Attribution, attribute
from depthstation.evaluate.explain.basis import Candidate, module_candidates
from depthstation.evaluate.explain.coverage import FillTest, extrapolation_messages, fill_message, fill_tests
from depthstation.evaluate.explain.discover import Discovery, discover, remaining
from depthstation.evaluate.explain.fine import fine_terms
from depthstation.evaluate.explain.library import library
from depthstation.evaluate.explain.locate import (
    FAMILY_AXES,
    MIN_NOISE_FRAMES,
    LocateResult,
    locate,
    short_standpoints,
)
from depthstation.evaluate.explain.report import reference_lookalikes, write_outputs
from depthstation.evaluate.explain.rerun_log import log_explanation
from depthstation.evaluate.explain.samples import (
    Samples,
    board_edge_px,
    concat,
    session_clock,
    thin,
    unpaired_standpoints,
    without_clock,
)
from depthstation.evaluate.explain.spline import spline_term
from depthstation.evaluate.explain.structure import decompose
from depthstation.simulate.checkerboard_session import DepthTally
from depthstation.simulate.effects import PixelContext
from depthstation.simulate.effects.base import CorrelatedJitter
from depthstation.simulate.model import SensorModel
from depthstation.simulate.scene import BLACK_ALBEDO, WHITE_ALBEDO, board_scene
from depthstation.simulate.view_renderer import ViewRenderer

MAX_SAMPLES_PER_FRAME = 20_000
EXPLAIN_FRAMES = 30  # frames per standpoint read when --frames is not given
# Each frame against its own board pose: the reference-plane error then varies from frame to frame
# and the frame-level standard errors include it (an averaged pose would carry one error per
# standpoint that no frame statistic can see, and real and sim would differ by it).
REFERENCE = "frame"
Progress = Callable[[str], None]


@dataclass
class FrameClock:
    """Per frame of a standpoint: index, timestamp and temperature the simulation copies."""

    index: list[int]
    timestamp_ns: list[int]
    temperature_c: list[float]


@dataclass
class Side:
    """One evaluated session (real or simulated): samples plus what the simulation needs."""

    samples: Samples
    poses: dict[str, Any]               # standpoint -> board-to-depth-camera 4x4 (averaged)
    clocks: dict[str, FrameClock]
    info: StreamInfo
    figures: dict[str, dict[str, float]]
    device: dict[str, Any] = field(default_factory=dict)   # the recording's, for result.json


def samples_from_results(results: Sequence[Any], info: StreamInfo, baseline_m: float,
                         t0_ns: int | None = None, true_poses: dict[str, Any] | None = None) -> Samples:
    """Contract-3 `PixelSamples` of several standpoints into one `Samples` (z-depth errors).

    Pixels that are neither black nor white (square edges, ChArUco markers) are left out, so the
    albedo axis stays two clean classes. Each class carries the reflectance the simulator gives that
    print (`simulate.scene` BLACK_ALBEDO / WHITE_ALBEDO), not 0/1: the effects' signatures must be
    evaluated on the same `PixelContext.albedo` the simulator feeds them, or an albedo effect fitted
    on a 0/1 axis reaches the white squares (albedo 0.85, not 1) when the new model is simulated.
    """

    names = [r.name for r in results if r.samples is not None and len(r.samples)]
    if not names:
        raise EvaluationError("no standpoint gave board pixels to compare")
    if t0_ns is None:
        t0_ns = min(int(r.samples.timestamp_ns.min()) for r in results if r.samples is not None
                    and len(r.samples))
    stereo = info.stereo
    parts = []
    for r in results:
        ps = r.samples
        if ps is None or not len(ps):
            continue
        keep = ps.is_black | ps.is_white
        z_ref = ps.z_ref_m[keep].astype(np.float64)
        ref_err = np.zeros_like(z_ref)
        if true_poses is not None and r.name in true_poses:
            # simulated: both sides are measured against their estimated board pose (so systematic
            # errors of the pose estimate cancel); how far the estimate is from the rendered board
            # is kept as the size of the reference error
            ref_err = z_ref - _plane_z(true_poses[r.name], info, ps.u[keep], ps.v[keep])
        us, vs = info.to_stereo_pixels(ps.u[keep], ps.v[keep])  # disparity lives in the imager's pixels
        scale = stereo.fx / info.depth_intrinsics.fx
        # distance to the board's outline (the depth edge of the plate, in the imager's pixels)
        edge = board_edge_px(ps.u.astype(np.int64), ps.v.astype(np.int64),
                             (info.depth_intrinsics.height, info.depth_intrinsics.width))[keep] * scale
        parts.append(Samples.build(
            names=names, fx=stereo.fx, ppx=stereo.ppx, ppy=stereo.ppy, baseline_m=baseline_m,
            standpoint=names.index(r.name), frame=ps.frame[keep], u=us, v=vs,
            z_ref_m=z_ref, err_m=ps.z_meas_m[keep].astype(np.float64) - z_ref,
            inclination_deg=ps.inclination_deg[keep],
            albedo=np.where(ps.is_white[keep], WHITE_ALBEDO, BLACK_ALBEDO),
            time_s=(ps.timestamp_ns[keep] - t0_ns) / 1e9, temperature_c=ps.temperature_c[keep],
            edge_px=edge, ref_err_m=ref_err, u_px=ps.u[keep], v_px=ps.v[keep], px_scale=scale))
    return thin(concat(parts), MAX_SAMPLES_PER_FRAME)


def _plane_z(board_to_cam: Any, info: StreamInfo, u: Any, v: Any) -> Any:
    """z-depth of the board plane along the rays of pixels (u, v)."""
    p = np.asarray(board_to_cam, dtype=np.float64)
    n, t = p[:3, 2], p[:3, 3]
    rx, ry = ray_xy(info.depth_intrinsics, u, v)
    dot = n[0] * rx + n[1] * ry + n[2]
    return float(n @ t) / dot


def _side(results: Sequence[Any], info: StreamInfo, baseline_m: float, t0_ns: int | None = None,
          true_poses: dict[str, Any] | None = None, time_stamps: bool | None = None) -> Side:
    """One side's samples, poses, clocks and figures. `time_stamps` None: decided from the frames'
    own stamps (`session_clock`); the simulated sides take the real side's verdict. Without a
    session clock the samples carry no time (0), so no locate test and no term runs along it."""
    ok = [r for r in results if r.usable and r.samples is not None]
    poses = {r.name: r.pose_depth for r in ok if r.pose_depth is not None}
    clocks = {r.name: FrameClock([f.index for f in r.frames if f.ok],
                                 [int(f.timestamp_ns) for f in r.frames if f.ok],
                                 [float(f.temperature_c) for f in r.frames if f.ok]) for r in ok}
    figures = {r.name: dict(r.figures) for r in ok}
    if time_stamps is None:
        time_stamps = session_clock([c.timestamp_ns for c in clocks.values()])
    samples = samples_from_results(ok, info, baseline_m, t0_ns, true_poses)
    return Side(samples if time_stamps else without_clock(samples), poses, clocks, info, figures)


def known_baseline(info: StreamInfo, baseline_m: float, source: str, where: str) -> StreamInfo:
    """`info` with a stereo baseline: the recording's, else `baseline_m` (the model's), warned with the
    value and where it came from. Why: disparity-domain effects (lr_focal_mismatch, disparity_offset)
    scale with f B; a wrong B moves them by the same factor without a word."""
    if info.baseline_m:
        return info
    warn(f"the recording gives no stereo baseline: {1e3 * baseline_m:g} mm assumed from {source}; "
         "disparity-domain figures (disparity offset, focal mismatch) scale with it", where,
         "assumed-baseline")
    return replace(info, baseline_m=baseline_m)


def check_model_camera(model: SensorModel, info: StreamInfo, device: dict[str, Any], where: str) -> None:
    """Warn where the model's [camera] differs from the recording's camera. Why: the simulation renders
    the recording's geometry (baseline, depth units, intrinsics), so a model camera that differs is
    never simulated, yet model.toml keeps it, and a D455 model on D435 data compares the wrong noise."""
    cam, src = model.camera, f"model '{model.name}'"
    said = []
    if info.baseline_m and abs(cam.baseline_m - info.baseline_m) > 1e-3 * info.baseline_m:
        said.append(f"baseline {1e3 * cam.baseline_m:g} mm (the recording's {1e3 * info.baseline_m:g} mm)")
    if info.depth_units_m and abs(cam.depth_units_m - info.depth_units_m) > 1e-6 * info.depth_units_m:
        said.append(f"depth units {cam.depth_units_m:g} m (the recording's {info.depth_units_m:g} m)")
    name = str(device.get("name") or device.get("model") or "")
    if name and cam.product.lower() not in name.lower() and cam.name.lower() not in name.lower():
        said.append(f"camera {cam.product} (the recording's '{name}')")
    for key in ("depth_hfov_deg", "color_hfov_deg", "depth_pp_offset_px", "color_pp_offset_px",
                "depth_to_color_translation_m"):  # geometry the model file set: the recording's is rendered
        if key in model.camera_overrides:
            mine = getattr(cam, key)
            said.append(f"{key} {list(mine) if isinstance(mine, tuple) else mine} (the recording's "
                        "intrinsics and extrinsics are rendered)")
    if said:
        warn(f"{src} [camera] differs from the recording: {'; '.join(said)}; the simulation renders the "
             "recording's camera, so the model's values were not simulated (model.toml keeps them): give a "
             "model of this camera", where, "model-camera")


def _stride(info: StreamInfo) -> int:
    return max(1, round(info.depth_intrinsics.width / 320))


def evaluate_real(paths: Sequence[Path], board: Board | Path, *, frames: int | None, baseline_m: float,
                  tick: Progress | None = None, workers: int = 1, cluster: str | None = None,
                  topics: TopicChoice | None = None, baseline_source: str = "the model",
                  model: SensorModel | None = None) -> Side:
    """The checkerboard study of the real inputs (its one prepare/run path), with per-pixel samples.

    Standpoints go out as tasks on a ChunkRunner: each is read and evaluated by the worker that
    gets it, local processes (`workers`) or a Dask scheduler (`cluster`).
    """
    probe = prepare_checkerboard(list(paths), board,
                                 StandpointOptions(frames=frames, up_to=EXPLAIN_FRAMES, topics=topics),
                                 one_camera=True)
    info = known_baseline(probe.recordings[0].info, baseline_m, baseline_source,
                          str(probe.recordings[0].path))
    device = probe.device
    if model is not None:
        check_model_camera(model, info, device, str(probe.recordings[0].path))
    options = StandpointOptions(frames=frames, up_to=EXPLAIN_FRAMES, collect_samples=True,
                                sample_stride=_stride(info),
                                reference=REFERENCE, topics=topics)
    job = replace(probe, options=options)

    def progress(done: int, total: int) -> None:
        if tick:
            tick(f"evaluated {done}/{total} standpoints")

    with ChunkRunner(workers, cluster) as runner:
        results = run_standpoints(job.recordings, job.board, job.options, runner, progress=progress)
    say_warnings(results)   # a standpoint with no usable frame is named here, and absent from the tests
    check_usable(job, results)   # none at all: the board file or the recordings are the cause (exit 2)
    try:
        side = _side(results, info, float(info.baseline_m or baseline_m))
    except EvaluationError as exc:   # usable frames, yet no black or white board pixel with depth
        raise InputError(None, f"{exc} in the recordings ({', '.join(str(p) for p in paths)}): their board "
                               "shows no depth (depth stream empty, or the board out of range?)") from exc
    return replace(side, device=device)


def simulate_like(real: Side, board: Board, model: SensorModel, *, seed: int = 0,
                  tick: Progress | None = None) -> Side:
    """Render and evaluate every real standpoint with `model` at the real pose, time and temperature."""

    info = replace(real.info, baseline_m=real.info.baseline_m or model.camera.baseline_m)
    renderer = ViewRenderer(board_scene(board), model, info, seed=seed, color=True)
    results = []
    # time since the session's first frame, as the samples carry it (a generic time term is fitted
    # and rendered on the same clock)
    t0 = min((c.timestamp_ns[0] for c in real.clocks.values() if c.timestamp_ns), default=0)
    tally = DepthTally()
    for k, (name, pose) in enumerate(real.poses.items()):
        if tick:
            tick(f"simulate {name}")
        renderer.set_pose(np.linalg.inv(pose))
        clock = real.clocks[name]

        def frames(clock: FrameClock = clock, t0: int = t0, k: int = k) -> Any:
            for i, (idx, ts, temp) in enumerate(zip(clock.index, clock.timestamp_ns, clock.temperature_c,
                                                    strict=True)):
                rng = np.random.default_rng([seed, k, i])
                t = temp if np.isfinite(temp) else 40.0
                fs: FrameSet = renderer.frame(idx, ts, (ts - t0) / 1e9, t, rng=rng)
                if not np.isfinite(temp):
                    fs.metadata.pop("temperature_c", None)
                yield fs

        results.append(evaluate_frames(name, tally.watch(frames()), info, board,
                                       frames_requested=len(clock.index), collect_samples=True,
                                       sample_stride=_stride(info), reference=REFERENCE))
        tally.done(name)
    tally.warn_if_empty(f"'{model.name}'")
    return _side(results, info, info.baseline_m or model.camera.baseline_m, t0, true_poses=real.poses,
                 time_stamps=real.samples.time_stamps)


def warn_unpaired(real: Samples, sim: Samples, what: str) -> None:
    """A standpoint one side lacks (no board pixels: the board not found in its frames) is left out of
    every test; the user must know that the verdict does not cover it."""
    only_real, only_sim = unpaired_standpoints(real, sim)
    for name in only_real:
        warn(f"the {what} of this standpoint gave no board pixels (board not found in its rendered "
             "frames); it is left out of every real-vs-simulated test", name, "explain-unpaired-standpoint")
    for name in only_sim:
        warn(f"only the {what} gave board pixels here (none in the real frames); it is left out of every "
             "real-vs-simulated test", name, "explain-unpaired-standpoint")


def warn_remaining(after: LocateResult, attr: Attribution) -> None:
    """Regions that still differ after the refit: the printed verdict names what was selected, and
    nothing said that it did not explain the data (an audit's within-standpoint drift was fitted
    as a noise calibration, a dark-print scale as an offset plus a depth scale; 15 and 2 regions
    remained, visible only in explain.json)."""
    sig = after.significant
    if not sig:
        return
    families = ", ".join(sorted({t.family for t in sig}))
    chosen = ", ".join(c.effect for c in attr.selected) or "nothing"
    warn(f"after the refit {len(sig)} test(s) still differ significantly (Holm; {families}): the refitted "
         f"model does not explain the data there, and the values selected ({chosen}) may absorb physics "
         "of another form; explain.json remaining_after says what each region would need", None,
         "explain-remains")


def warn_short(real: Samples, sim: Samples) -> None:
    """A standpoint with board pixels in fewer than 3 frames has no usable temporal variance: it is
    left out of the noise tests (its bias is still tested), and the user must know."""
    for name in sorted(set(short_standpoints(real)) | set(short_standpoints(sim))):
        warn(f"board pixels in fewer than {MIN_NOISE_FRAMES} frames: left out of the noise tests (a "
             "temporal variance needs 3 frames or more)", name, "explain-short-standpoint")


def present_effects(model: SensorModel) -> dict[str, dict[str, float]]:
    """The model's effects and their parameters: refitting one of these is calibration."""
    return {e.name: dict(e.params) for e in model.effects}


def noise_variance(model: SensorModel) -> Callable[[Samples], Any]:
    """The noise model's per-pixel z variance (weights of the bias fit)."""

    def var(s: Samples) -> Any:
        v = np.asarray(model.variance_m2(PixelContext(**s.context())), dtype=np.float64)
        v = np.broadcast_to(v, (len(s),))
        return np.where(np.isfinite(v) & (v > 0), v, np.nanmedian(v[v > 0]) if (v > 0).any() else 1e-6)
    return var


def correlated_variance(model: SensorModel) -> Callable[[Samples], tuple[Any, float]] | None:
    """The window-correlated part of the model's z variance and its window (None if it has none)."""
    corr = [e for e in model.effects if isinstance(e, CorrelatedJitter)]
    if not corr:
        return None

    def var(s: Samples) -> tuple[Any, float]:
        ctx = PixelContext(**s.context())
        v = sum(np.broadcast_to(np.asarray(e.variance_m2(ctx), dtype=np.float64), (len(s),)) for e in corr)
        return np.where(np.isfinite(v), v, 0.0), max(e.window() for e in corr)
    return var


def improved_model(model: SensorModel, attribution: Attribution, discovery: Discovery | None = None,
                   candidates: Sequence[Candidate] = (), fine: Sequence[dict[str, Any]] = ()) -> SensorModel:
    """The base model with every selected effect added or its parameters replaced by the fit, and
    every discovered term as a generic term the simulator renders."""
    fixed = {c.name: c.fixed for c in candidates}
    new = model
    for c in attribution.selected:
        params = {k: v for k, v in c.params.items() if np.isfinite(v)}
        if c.kind == "variance":   # a fitted total variance below zero: no such noise at all
            params = {k: max(v, 0.0) for k, v in params.items()}
        new = new.with_effect(c.effect, **{**fixed.get(c.effect, {}), **params})
    for t in (discovery.terms if discovery is not None else []):
        new = new.with_effect(t.effect, **t.params())
    for f in fine:
        new = new.with_effect(f["effect"], **f["params"])
    return new


@dataclass
class Explanation:
    real: Side
    sim: Side
    before: LocateResult
    attribution: Attribution
    model: SensorModel
    new_model: SensorModel
    resim: Side | None
    after: LocateResult | None
    candidates: list[Candidate]
    discovery: Discovery | None = None
    library: list[Candidate] | None = None
    remaining: list[dict[str, Any]] | None = None   # regions significant after, and what would explain them
    valid_depth: list[FillTest] = field(default_factory=list)   # fill rates real vs sim per standpoint
    fine_terms: list[dict[str, Any]] = field(default_factory=list)   # ripple / static pattern written
    pose_spread: dict[str, Any] | None = None         # the board pose's spread (colour), before
    pose_spread_after: dict[str, Any] | None = None


def explain_sides(real: Side, sim: Side, model: SensorModel, board: Board, *, seed: int = 0,
                  resimulate: bool = True, discovery: bool = True, tick: Progress | None = None
                  ) -> Explanation:
    """Locate, attribute, discover, build the improved model and (optionally) check it by simulating
    again."""
    present = present_effects(model)
    warn_unpaired(real.samples, sim.samples, "simulation")
    warn_short(real.samples, sim.samples)
    fills = fill_tests(real.figures, sim.figures, _frame_counts(real), _frame_counts(sim))
    for t in fills:
        if t.significant:
            warn(fill_message(t), t.standpoint, "explain-valid-depth")
    if tick:
        tick("locate")
    structures = (decompose(real.samples), decompose(sim.samples))
    before = locate(real.samples, sim.samples, structures=structures)
    corr = structures[0].corr
    # window noise is fitted at the width the real data's neighbour correlation shows
    cands = module_candidates(present, window_px=corr.window_px if corr.fraction > 0.2 else None)
    lib = library(real.samples, corr.window_px if corr.fraction > 0.2 else None) if discovery else []
    if tick:
        tick("attribute" + (f" and discover ({len(lib)} generic terms)" if lib else ""))
    attr = attribute(real.samples, sim.samples, [*cands, *lib], present, noise_var=noise_variance(model),
                     corr_var=correlated_variance(model), structures=structures)
    disc = discover(attr, cands, lib, present, real.samples) if lib else None
    if disc is not None and disc.terms and not before.significant:
        found = "; ".join(f"{t.quantity} along {'/'.join(t.axes)} (Wald p {t.wald_p:.2g})"
                          for t in disc.terms)
        warn(f"discovered {found}, although no region differs significantly (Holm): the term rests on "
             "the pooled fit alone; confirm it on another session before trusting it", None,
             "explain-discovery-unlocated")
    for message in extrapolation_messages(disc.terms if disc is not None else [], real.samples):
        warn(message, None, "explain-extrapolation")
    for look in reference_lookalikes(attr.selected):
        warn(f"{look['effect']} selected (scale_error {look['scale_error']:+.4f}): {look['also']}", None,
             "reference-lookalike")
    fine = fine_terms(before.tests, present, real.samples.fx, kinds=("periodic",))
    fx_depth, size = real.info.depth_intrinsics.fx, pose_spread.board_size(board)
    spread = pose_spread.spread_tests(real.figures, sim.figures, _frame_counts(real), _frame_counts(sim),
                                      pose_spread.added_variance(present.get(pose_spread.TERM), sim.figures,
                                                                 fx_depth))
    spread_fit = pose_spread.fit_excess(spread, fx_depth, size)
    pose_term = pose_spread.pose_term(spread_fit, spread, present)
    fine = [*fine, *([pose_term] if pose_term is not None else [])]
    new_model = improved_model(model, attr, disc, cands, fine)
    resim = after = None
    spread_after: list[pose_spread.SpreadTest] = []
    if resimulate:
        resim = simulate_like(real, board, new_model, seed=seed + 1, tick=tick)
        warn_unpaired(real.samples, resim.samples, "re-simulation")
        if tick:
            tick("locate after")
        after = locate(real.samples, resim.samples)
        # a static excess left after the refit (real repeating more over frames than the re-simulation):
        # the unit's static pattern calibrated on it, rendered and located once more
        static = fine_terms(after.tests, present_effects(new_model), real.samples.fx, kinds=("static",))
        if static:
            new_model, resim, after = _rendered_with(real, board, new_model, static, seed + 3, tick,
                                                     "the static pattern")
            fine = [*fine, *static]
        # a bias still located along u, v, distance or inclination: the spline along that axis (kept
        # only where it predicts held-out standpoints better), rendered and checked once more
        spline = spline_term(after.significant, real.samples, resim.samples)
        if spline is not None:
            new_model, resim, after = _rendered_with(real, board, new_model, [spline], seed + 2, tick,
                                                     "the spline")
            fine = [*fine, spline]
        spread_after = pose_spread.spread_tests(
            real.figures, resim.figures, _frame_counts(real), _frame_counts(resim),
            pose_spread.added_variance(present_effects(new_model).get(pose_spread.TERM), resim.figures,
                                       fx_depth))
        warn_remaining(after, attr)
    summary = after.summary() if after is not None else None
    rest = (remaining(summary["regions"], attr, lib, disc, FAMILY_AXES, cands, present,
                      summary.get("noise_correlation")) if summary is not None and lib else None)
    return Explanation(real, sim, before, attr, model, new_model, resim, after, cands, disc, lib, rest, fills,
                       fine, pose_spread.summary(spread, spread_fit, pose_term),
                       pose_spread.summary(spread_after, None, None) if resimulate else None)


def _rendered_with(real: Side, board: Board, model: SensorModel, terms: list[dict[str, Any]], seed: int,
                   tick: Progress | None, label: str) -> tuple[SensorModel, Side, LocateResult]:
    """The model with `terms` added, the real standpoints re-simulated with it and located again."""
    for term in terms:
        model = model.with_effect(term["effect"], **term["params"])
    resim = simulate_like(real, board, model, seed=seed, tick=tick)
    warn_unpaired(real.samples, resim.samples, "re-simulation")
    if tick:
        tick(f"locate after {label}")
    return model, resim, locate(real.samples, resim.samples)


def _frame_counts(side: Side) -> dict[str, int]:
    return {name: len(clock.index) for name, clock in side.clocks.items()}


def run_explain(real: Sequence[Path], board: Board | Path, model: SensorModel, out: Path, *,
                frames: int | None, seed: int = 0, resimulate: bool = True, workers: int = 1,
                cluster: str | None = None,
                discovery: bool = True, parameters: dict[str, Any] | None = None,
                target: RerunTarget | None = None, tick: Progress | None = None, force: bool = False,
                topics: TopicChoice | None = None, model_file: Path | None = None) -> dict[str, Any]:
    """`depthstation explain` of checkerboard captures: evaluate the real standpoints, simulate them
    with `model`, locate, attribute, refit, check, and write the result folder (whole or not at
    all; a non-empty `out` only with `force`); its explain.json. The board and `model_file` (the model
    TOML it was read from) are inputs: `--force` never deletes them, result.json lists them."""
    inputs = [*real, *([board] if isinstance(board, Path) else []), *([model_file] if model_file else [])]
    with result_folder(out, force=force, inputs=inputs, kind="explain") as tmp:
        return _run_explain(real, board, model, tmp, frames, seed, resimulate, workers, cluster,
                            parameters, None if target is None else target.within(out, tmp), tick, topics,
                            discovery, inputs, model_file)


def _run_explain(real: Sequence[Path], board: Board | Path, model: SensorModel, out: Path, frames: int | None,
                 seed: int, resimulate: bool, workers: int, cluster: str | None,
                 parameters: dict[str, Any] | None, target: RerunTarget | None,
                 tick: Progress | None, topics: TopicChoice | None = None,
                 discovery: bool = True, inputs: Sequence[Path] = (),
                 model_file: Path | None = None) -> dict[str, Any]:
    brd = board if isinstance(board, Board) else load_board(board)
    real_side = evaluate_real(real, board, frames=frames, baseline_m=model.camera.baseline_m, tick=tick,
                              workers=workers, cluster=cluster, topics=topics,
                              baseline_source=f"model '{model.name}' ([camera] baseline_m)", model=model)
    try:
        sim_side = simulate_like(real_side, brd, model, seed=seed, tick=tick)
    except EvaluationError as exc:   # the real side has board pixels: the model is the cause
        raise InputError(model_file, f"model '{model.name}': its simulation of the real standpoints gave no "
                                     "board pixels to compare (frames without depth, or the board not found "
                                     "in them): check the model's [camera] and effects") from exc
    ex = explain_sides(real_side, sim_side, model, brd, seed=seed, resimulate=resimulate, discovery=discovery,
                       tick=tick)
    data = write_outputs(ex, out, [str(p) for p in (inputs or real)], dict(parameters or {}))
    if target is not None and target.enabled:
        log_explanation(ex, target)
    return data
