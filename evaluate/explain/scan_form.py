"""Explain for the reference-scan study: a real sequence against a simulation of the same trajectory.

Both sides go through the scan study (`evaluate.scan.study.evaluate_chunk`: every depth pixel ray
cast against the reference mesh, errors binned over distance x inclination). The simulation renders
the reference mesh with the current model at the registered pose of every real frame, with the real
frame's intrinsics, time stamp and temperature. Frames of one sequence are not independent (one
pose error, one registration, the same surfaces seen again), so the unit of independence is a frame
block: each side gives one Grid per block, and standard errors come from the scatter of the
block-wise real-minus-sim differences. Attribution fits the catalogue's bias signatures (the
derivative of each `simulate.effects` module's `bias_m`, evaluated at the cell centres: the grid only
knows distance and inclination) by weighted least squares with forward selection by BIC, validated
leaving one frame block out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import stdtr

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.frames import FrameSet, FrameSource
from depthstation.core.grid import Grid
from depthstation.core.results import write_json, write_result_info
from depthstation.core.run_warnings import warn
from depthstation.evaluate.explain.attribute import CandidateFit
from depthstation.evaluate.explain.basis import Candidate, module_candidates
from depthstation.evaluate.explain.discover import Discovery, select_table
from depthstation.evaluate.explain.figures import residual_grid_figure
from depthstation.evaluate.explain.library import library
from depthstation.evaluate.explain.mixed_model import gls
from depthstation.evaluate.explain.run import check_model_camera, known_baseline, present_effects
from depthstation.evaluate.explain.samples import FloatArray, Samples
from depthstation.evaluate.explain.tables import Table
from depthstation.evaluate.scan.chunks import chunk_ranges, new_renderer
from depthstation.evaluate.scan.rasterise import DEFAULT_RENDERER
from depthstation.evaluate.scan.run import ScanOptions, prepare_scan
from depthstation.evaluate.scan.study import StudyConfig, evaluate_chunk
from depthstation.evaluate.scan.trajectory import Trajectory
from depthstation.simulate.model import SensorModel
from depthstation.simulate.scene import mesh_scene
from depthstation.simulate.scene_render import SceneRaster
from depthstation.simulate.view_renderer import ViewRenderer

DISTANCE_BIN_M = 0.1
INCLINATION_BIN_DEG = 10.0
MIN_CELL_COUNT = 30          # pixels of one block in one cell before its mean is used
MIN_BLOCKS = 3               # blocks a cell needs for a standard error
BLOCK_FRAMES = 8             # frames per block unless --block-frames says otherwise
ALPHA = 0.05
BIC_THRESHOLD = -10.0
WALD_P = 1e-3
MAX_SELECTED = 3
# effects whose signature the distance x inclination grid can carry; the others depend on pixel
# position, albedo, time or edges, which the grid averages away (said in the report)
GRID_EFFECTS = ("disparity_offset", "depth_scale", "slant_bias", "pixel_locking")
Progress = Callable[[str], None]


@dataclass
class Clock:
    """The real frames the simulation copies: index, time stamp, temperature (degC)."""

    index: list[int] = field(default_factory=list)
    timestamp_ns: list[int] = field(default_factory=list)
    temperature_c: list[float] = field(default_factory=list)


class SimulatedSequence:
    """A frame source rendering the reference mesh with a model at the real frames' poses and times.

    Frames whose time stamp has no pose are left out (the study would skip them on the real side too).
    """

    def __init__(self, mesh_path: Path, model: SensorModel, info: StreamInfo, trajectory: Trajectory,
                 clock: Clock, *,
                 seed: int = 0, tolerance_s: float = 0.01) -> None:

        self.name = "simulated"
        self.info = info
        self.clock = clock
        self.trajectory = trajectory
        self.tolerance_s = tolerance_s
        self.seed = seed
        scene = mesh_scene(Path(mesh_path))
        self.renderer = ViewRenderer(scene, model, info, seed=seed, color=False, rc=SceneRaster(scene))

    @property
    def frame_count(self) -> int | None:
        return len(self.clock.index)

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        stop = len(self.clock.index) if limit is None else min(len(self.clock.index), start + limit)
        t0 = self.clock.timestamp_ns[0] if self.clock.timestamp_ns else 0
        for i in range(start, stop):
            idx, ts, temp = self.clock.index[i], self.clock.timestamp_ns[i], self.clock.temperature_c[i]
            pose = self.trajectory.match(ts * 1e-9, self.tolerance_s)
            if pose is None:
                continue
            self.renderer.set_pose(pose)
            t = temp if np.isfinite(temp) else 40.0
            rng = np.random.default_rng([self.seed, idx])
            yield self.renderer.frame(idx, ts, (ts - t0) / 1e9, t, rng=rng)


def read_clock(source: FrameSource) -> Clock:
    """Index, time stamp and temperature of every frame of a sequence (one pass over it)."""
    c = Clock()
    for fs in source.frames():
        c.index.append(int(fs.index))
        c.timestamp_ns.append(int(fs.timestamp_ns))
        c.temperature_c.append(float(fs.metadata.get("temperature_c", np.nan)))
    return c


def block_grids(source: FrameSource, mesh_path: Path, trajectory: Trajectory, block_frames: int,
                tolerance_s: float = 0.01, unmeasured: Path | None = None) -> list[Grid]:
    """One coarse distance x inclination Grid per block of `block_frames` consecutive frames;
    `unmeasured`: the mesh's mask of surface nobody scanned (its pixels leave both sides' grids)."""

    config = StudyConfig(DISTANCE_BIN_M, INCLINATION_BIN_DEG, 6.0, 90.0, tolerance_s=tolerance_s,
                         renderer=DEFAULT_RENDERER, unmeasured=unmeasured)
    caster = new_renderer(mesh_path, source.info.depth_intrinsics, config)
    n = source.frame_count
    if n is None:
        raise EvaluationError("the sequence does not say how many frames it has")
    return [evaluate_chunk(caster, source, trajectory, config, s, lim).grid
            for s, lim in chunk_ranges(n, block_frames)]


@dataclass
class BlockCells:
    """Real-minus-sim differences per (frame block, grid cell) where both sides have enough pixels."""

    block: np.ndarray[Any, Any]
    cell: np.ndarray[Any, Any]           # flat index into the grid
    z_m: FloatArray                      # cell centre distance (z-depth)
    inclination_deg: FloatArray
    bias_m: FloatArray                   # real mean - sim mean
    std_m: FloatArray                    # real std - sim std (noise difference)
    count: FloatArray                    # min of the two pixel counts
    var_m2: FloatArray | None = None     # real variance - sim variance (noise discovery)
    sim_var_m2: FloatArray | None = None
    time_s: FloatArray | None = None     # the block's mean time since the first frame


def block_cells(real: list[Grid], sim: list[Grid], min_count: int = MIN_CELL_COUNT,
                block_time_s: FloatArray | None = None) -> BlockCells:
    """Pair the block grids of both sides cell by cell."""
    if len(real) != len(sim):
        raise EvaluationError("real and simulated sides have different numbers of frame blocks")
    rows: list[tuple[Any, ...]] = []
    for b, (r, s) in enumerate(zip(real, sim, strict=True)):
        ok = (r.count >= min_count) & (s.count >= min_count)
        i, j = np.nonzero(ok)
        rs, ss = np.sqrt(r.var), np.sqrt(s.var)
        for a, c in zip(i, j, strict=True):
            rows.append((b, a * r.shape[1] + c, r.distance_centers_m[a], r.inclination_centers_deg[c],
                         r.mean[a, c] - s.mean[a, c], rs[a, c] - ss[a, c], min(r.count[a, c], s.count[a, c]),
                         r.var[a, c] - s.var[a, c], s.var[a, c]))
    if not rows:
        raise EvaluationError("no grid cell has enough pixels on both sides to compare")
    cols = list(zip(*rows, strict=True))
    block = np.asarray(cols[0], np.int64)
    times = (np.asarray(block_time_s, dtype=float)[block] if block_time_s is not None
             else block.astype(float))
    return BlockCells(block, np.asarray(cols[1], np.int64),
                      np.asarray(cols[2], float), np.asarray(cols[3], float), np.asarray(cols[4], float),
                      np.asarray(cols[5], float), np.asarray(cols[6], float), np.asarray(cols[7], float),
                      np.asarray(cols[8], float), times)


def _holm(p: FloatArray) -> FloatArray:
    """Holm-adjusted p-values (family-wise error over all tests together)."""
    order = np.argsort(p)
    m = len(p)
    adj = np.empty(m)
    run = 0.0
    for k, i in enumerate(order):
        run = max(run, min(1.0, (m - k) * p[i]))
        adj[i] = run
    return adj


def locate_cells(bc: BlockCells, shape: tuple[int, int]) -> dict[str, Any]:
    """Cell-wise and block-wise tests of the bias and noise differences (SE from the block scatter)."""
    tests: list[dict[str, Any]] = []
    for kind, y in (("bias", bc.bias_m), ("noise", bc.std_m)):
        for cell in np.unique(bc.cell):
            m = bc.cell == cell
            if m.sum() < MIN_BLOCKS:
                continue
            vals = y[m]
            sd = float(np.std(vals, ddof=1))
            se = sd / np.sqrt(m.sum())
            t = float(np.mean(vals) / se) if se > 0 else 0.0
            p = float(2 * stdtr(m.sum() - 1, -abs(t)))
            a, c = divmod(int(cell), shape[1])
            tests.append({"family": "grid", "kind": kind, "distance_m": round(float(bc.z_m[m][0]), 3),
                          "inclination_deg": round(float(bc.inclination_deg[m][0]), 1),
                          "difference_m": float(np.mean(vals)), "stderr_m": float(se), "blocks": int(m.sum()),
                          "p": p, "cell": [a, c]})
    # frame blocks: a block's mean difference over the compared cells (cells weighted by pixels)
    # against the scatter of the OTHER blocks' means (t with B - 2 dof: exact for independent blocks;
    # the cells of one block share frames, so they are not independent of each other)
    ub = np.unique(bc.block)
    d_b = np.array([np.average(bc.bias_m[bc.block == b], weights=bc.count[bc.block == b]) for b in ub])
    if len(ub) >= 4:
        for i, b in enumerate(ub):
            others = np.delete(d_b, i)
            sd = float(np.std(others, ddof=1))
            t = float(d_b[i] / sd) if sd > 0 else 0.0
            tests.append({"family": "block", "kind": "bias", "block": int(b), "t": t,
                          "difference_m": float(d_b[i]), "stderr_m": sd,
                          "p": float(2 * stdtr(len(ub) - 2, -abs(t)))})
    if tests:
        adj = _holm(np.array([t["p"] for t in tests]))
        for test, pa in zip(tests, adj, strict=True):
            test["p_adj"] = float(pa)
    regions = [t for t in tests if t["p_adj"] < ALPHA and t["family"] == "grid"]
    blocks = [t["block"] for t in tests if t["p_adj"] < ALPHA and t["family"] == "block"]
    return {"significant": bool(regions or blocks), "standpoints": [f"block_{b:02d}" for b in blocks],
            "regions": sorted(regions, key=lambda t: t["p_adj"]), "tests": len(tests)}


# -- attribution -------------------------------------------------------------------------------------

def _pseudo_samples(bc: BlockCells, info: StreamInfo, albedo: float) -> Samples:
    """Block-cells as samples at the cell centres (principal point: the grid has no pixel position)."""
    intr = info.stereo
    baseline = np.nan if info.baseline_m is None else float(info.baseline_m)   # known_baseline set it
    return Samples.build(names=["sequence"], fx=intr.fx, ppx=intr.ppx, ppy=intr.ppy,
                         baseline_m=baseline, standpoint=0, frame=bc.block,
                         u=intr.ppx, v=intr.ppy, z_ref_m=bc.z_m, err_m=bc.bias_m,
                         inclination_deg=bc.inclination_deg, albedo=albedo, temperature_c=40.0,
                         time_s=bc.time_s)


def _cell_weights(bc: BlockCells, values: FloatArray | None = None, tiny: float = 1e-12) -> FloatArray:
    """1/variance of a block-cell difference (the bias, or `values`: the variance differences): each
    cell's block scatter, floored at a quarter of the median (a cell seen in few blocks would
    otherwise get an arbitrarily small variance)."""
    y = bc.bias_m if values is None else values
    var = np.full(len(y), np.nan)
    for cell in np.unique(bc.cell):
        m = bc.cell == cell
        if m.sum() >= 2:
            var[m] = np.var(y[m], ddof=1)
    med = float(np.nanmedian(var)) if np.isfinite(var).any() else float(np.var(y))
    var = np.where(np.isfinite(var), np.maximum(var, 0.25 * med), med)
    return 1.0 / np.maximum(var, tiny)


def _wls(X: FloatArray, y: FloatArray, w: FloatArray) -> tuple[FloatArray, float]:
    sw = np.sqrt(w)
    b, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    r = y - X @ b
    return np.asarray(b, dtype=np.float64), float(np.sum(w * r * r))


def _heldout_rmse(X: FloatArray, y: FloatArray, w: FloatArray, block: np.ndarray[Any, Any]) -> float:
    """RMSE of the residual on each frame block when fitted on the others (X empty: no fit)."""
    err = np.empty_like(y)
    for b in np.unique(block):
        test = block == b
        if X.shape[1] == 0 or (~test).sum() <= X.shape[1]:
            err[test] = y[test]
            continue
        coef, _ = _wls(X[~test], y[~test], w[~test])
        err[test] = y[test] - X[test] @ coef
    return float(np.sqrt(np.mean(err ** 2)))


def _cluster_p(X: FloatArray, y: FloatArray, w: FloatArray, block: np.ndarray[Any, Any],
               j: int) -> tuple[float, float]:
    """Block-cluster-robust standard error and Wald p of coefficient j."""
    sw = np.sqrt(w)
    Xw = X * sw[:, None]
    b, _ = _wls(X, y, w)
    r = (y - X @ b) * sw
    bread = np.linalg.pinv(Xw.T @ Xw)
    meat = np.zeros_like(bread)
    for g in np.unique(block):
        m = block == g
        s = Xw[m].T @ r[m]
        meat += np.outer(s, s)
    G = len(np.unique(block))
    cov = bread @ meat @ bread * G / max(G - 1, 1)
    se = float(np.sqrt(max(cov[j, j], 0.0)))
    p = float(2 * stdtr(max(G - 1, 1), -abs(b[j]) / se)) if se > 0 else 1.0
    return se, p


def attribute_cells(bc: BlockCells, info: StreamInfo, present: dict[str, dict[str, float]],
                    albedo: float = 0.6) -> tuple[list[dict[str, Any]], list[str]]:
    """Rank the grid-visible bias candidates; forward selection by BIC, held-out blocks, Wald test."""

    s = _pseudo_samples(bc, info, albedo)
    cands = {c.name: c for c in module_candidates(present) if c.kind == "bias" and c.name in GRID_EFFECTS}
    cols = {n: c.columns(s) for n, c in cands.items()}
    cols = {n: x for n, x in cols.items() if np.ptp(x, axis=0).max() > 0 or np.abs(x).max() > 0}
    y, w, block = bc.bias_m, _cell_weights(bc), bc.block
    n = len(y)
    selected: list[str] = []
    records: dict[str, dict[str, Any]] = {}

    def design(names: list[str]) -> FloatArray:
        return np.concatenate([cols[k] for k in names], axis=1) if names else np.zeros((n, 0))

    for step in range(MAX_SELECTED):
        X0 = design(selected)
        chi0 = _wls(X0, y, w)[1] if selected else float(np.sum(w * y * y))
        rmse0 = _heldout_rmse(X0, y, w, block)
        best: tuple[str, dict[str, Any]] | None = None
        for name in cols:
            if name in selected:
                continue
            X = np.concatenate([X0, cols[name]], axis=1)
            b, chi = _wls(X, y, w)
            k = cols[name].shape[1]
            dbic = chi - chi0 + k * np.log(n)
            rmse = _heldout_rmse(X, y, w, block)
            ses, ps = zip(*[_cluster_p(X, y, w, block, X0.shape[1] + i) for i in range(k)], strict=True)
            c = cands[name]
            coef = b[X0.shape[1]:]
            old = present.get(name, {})
            role = "calibration" if name in present else "missing_physics"
            rec: dict[str, Any] = {"effect": name, "kind": "bias", "role": role,
                   "meaning": c.meaning,
                   "params": {p: {"value": float(old.get(p, 0.0)) + float(v), "unit": u, "stderr": float(e)}
                              for p, u, v, e in zip(c.params, c.units, coef, ses, strict=True)},
                   "delta_bic": float(dbic), "heldout_rmse_before_m": rmse0, "heldout_rmse_after_m": rmse,
                   "wald_p": float(min(ps)), "selected": False, "step": None}
            if step == 0 or name not in records:
                records[name] = rec
            if best is None or dbic < best[1]["delta_bic"]:
                best = (name, rec)
        if best is None:
            break
        name, rec = best
        if not (rec["delta_bic"] < BIC_THRESHOLD and rec["wald_p"] < WALD_P
                and rec["heldout_rmse_after_m"] < rec["heldout_rmse_before_m"]):
            break
        rec.update(selected=True, step=step)
        records[name] = rec
        selected.append(name)
    ranked = sorted(records.values(), key=lambda r: (not r["selected"], r["step"] if r["selected"] else 0,
                                                     r["delta_bic"]))
    return ranked, selected


# -- discovery on the axes the grid keeps -------------------------------------------------------------

# what a block-cell still knows: its distance (and disparity), its inclination and its block's time
GRID_AXES = {"distance", "disparity", "inclination", "time"}
GRID_NOISE_EFFECTS = ("disparity_noise", "slant_noise")


def _fit_of(rec: dict[str, Any]) -> CandidateFit:
    """A scan candidate record as the fit record discovery works on."""
    return CandidateFit(rec["effect"], rec["kind"], rec["role"],
                        {k: v["value"] for k, v in rec["params"].items()},
                        {k: v["unit"] for k, v in rec["params"].items()}, rec["meaning"], rec["delta_bic"],
                        rec["heldout_rmse_before_m"], rec["heldout_rmse_after_m"], rec["wald_p"],
                        {k: v["stderr"] for k, v in rec["params"].items()}, rec["selected"], rec["step"])


def discover_cells(bc: BlockCells, info: StreamInfo, present: dict[str, dict[str, float]],
                   records: list[dict[str, Any]], albedo: float = 0.6) -> tuple[Discovery, list[str]]:
    """Discovery on the block-cells: generic bias terms along distance, disparity, inclination and
    time (with their products) after the catalogue's choice, and noise terms along the same axes
    on the cells' variance differences; the guards of the checkerboard form (catalogue priority,
    simplest first, extended BIC, leave-one-block-out RMSE, block-cluster-robust Wald).
    Returns the discovery and the catalogue effects it took out again."""
    s = _pseudo_samples(bc, info, albedo)
    lib = [c for c in library(s)
           if c.spec is not None and set(c.spec.axes) <= GRID_AXES and c.table == "tiles"]
    cands = {c.name: c for c in module_candidates(present)}
    out = Discovery(library_size=len(lib))
    dropped: list[str] = []
    tables: list[tuple[Table, list[Candidate], list[Candidate], dict[str, CandidateFit]]] = []
    cat_b = [cands[n] for n in GRID_EFFECTS if n in cands]
    lib_b = [c for c in lib if c.kind == "bias"]
    xb = {c.name: c.columns(s) for c in [*cat_b, *lib_b]}
    tb = Table("bias", bc.bias_m, _cell_weights(bc), xb, bc.block, bc.block, bc.block, name="bias")
    fits = {r["effect"]: _fit_of(r) for r in records}
    tables.append((tb, cat_b, lib_b, fits))
    cat_v = [cands[n] for n in GRID_NOISE_EFFECTS if n in cands]
    lib_v = [c for c in lib if c.kind == "variance"]
    for t, cat, gen, f in tables:
        if len(np.unique(bc.block)) < MIN_BLOCKS:
            continue
        before = {k: v.selected for k, v in f.items()}
        terms, drop, rejected, kept = select_table(t, cat, gen, f, present, s)
        out.terms += terms
        out.dropped += drop
        out.kept += kept
        out.rejected += rejected
        dropped += [k for k, v in f.items() if before.get(k) and not v.selected]
        for k, v in f.items():       # a catalogue effect discovery added on this table
            if v.selected and not before.get(k):
                records.append({"effect": k, "kind": v.kind, "role": v.role, "meaning": v.meaning,
                                "params": {p: {"value": val, "unit": v.units.get(p, ""),
                                               "stderr": v.stderr.get(p)} for p, val in v.params.items()},
                                "delta_bic": v.delta_bic, "heldout_rmse_before_m": v.heldout_rmse_before_m,
                                "heldout_rmse_after_m": v.heldout_rmse_after_m, "wald_p": v.wald_p,
                                "selected": True, "step": v.step})
        if t.name == "bias" and bc.var_m2 is not None and bc.sim_var_m2 is not None:
            # the noise table, once the bias is known: a bias b at depth z scales the depth noise by
            # ((z + b) / z)^2 (sigma_z = z^2 sigma_d / fB), so the simulation's variance is compared
            # at the depth the real camera reports (else a disparity offset reads as more noise)
            chosen = [k for k, v in f.items() if v.selected] + [x.candidate.name for x in terms]
            bias = (np.concatenate([t.X[n] for n in chosen], axis=1) @ gls(t, chosen).beta
                    if chosen else np.zeros(len(t)))
            scale = ((bc.z_m + bias) / bc.z_m) ** 4
            yv = bc.var_m2 + bc.sim_var_m2 * (1.0 - scale)
            xv = {c.name: c.columns(s) for c in [*cat_v, *lib_v]}
            tables.append((Table("variance", yv, _cell_weights(bc, bc.var_m2, 1e-30), xv, bc.block, bc.block,
                                 bc.block, name="variance"), cat_v, lib_v, {}))
    for r in records:
        if r["effect"] in dropped:
            r["selected"] = False
    return out, dropped


# -- the whole thing ---------------------------------------------------------------------------------

@dataclass
class ScanExplanation:
    data: dict[str, Any]
    new_model: SensorModel
    before: BlockCells
    after: BlockCells | None
    shape: tuple[int, int]
    device: dict[str, Any] = field(default_factory=dict)   # the recording's, for result.json


def explain_scan(sequence: Path, poses: Path, reference: Path, model: SensorModel, out: Path, *,
                 frames: int | None = None, block_frames: int | None = None, seed: int = 0,
                 register: str = "none",
                 similarity: Path | None = None, resimulate: bool = True, tolerance_s: float = 0.01,
                 discovery: bool = True, tick: Progress | None = None,
                 topics: TopicChoice | None = None,
                 pose_opt: ScanOptions | None = None) -> ScanExplanation:
    """Evaluate the real sequence and its simulation in frame blocks, locate, attribute, re-simulate.
    `pose_opt`: how the trajectory is read (its poses_of, pose_convention, pose_offset_s)."""
    read = pose_opt or ScanOptions()

    if tick:
        tick("prepare: reference mesh and registration")
    job = prepare_scan(sequence, poses, reference, out,
                       ScanOptions(similarity=similarity, register=register, tolerance_s=tolerance_s,
                                   poses_of=read.poses_of, pose_convention=read.pose_convention,
                                   pose_offset_s=read.pose_offset_s,
                                   depth_topic=topics.depth if topics else None,
                                   color_topic=topics.color if topics else None,
                                   infrared_topic=topics.infrared if topics else None))
    source, mesh_path, posed = job.source, job.mesh_path, job.posed
    reg_info: dict[str, Any] = job.registration.to_dict()
    clock = read_clock(source)
    if frames is not None:
        clock = Clock(clock.index[:frames], clock.timestamp_ns[:frames], clock.temperature_c[:frames])
    if len(clock.index) < MIN_BLOCKS * 2:
        raise EvaluationError(f"{len(clock.index)} frames: too few for frame blocks (need {MIN_BLOCKS * 2})")
    asked = BLOCK_FRAMES if block_frames is None else block_frames
    block = max(1, min(asked, len(clock.index) // MIN_BLOCKS))
    n_frames = len(clock.index)
    if block_frames is not None and block != block_frames:  # a figure asked for is not changed unsaid
        warn(f"--block-frames {block_frames} leaves fewer than {MIN_BLOCKS} blocks of {n_frames} frames: "
             f"blocks of {block} frames are compared", str(source.path), "block-frames")
    # frames without a pose are skipped by both sides' study: say so, and count what is used
    posed_at = [posed.match(ts * 1e-9, tolerance_s) is not None for ts in clock.timestamp_ns]
    n_posed = int(sum(posed_at))
    blocks_used = sum(any(posed_at[a:a + n]) for a, n in chunk_ranges(n_frames, block))
    if n_posed == 0:
        raise InputError(poses, f"no pose within {tolerance_s:g} s of any of the {n_frames} frames' time "
                                "stamps (another sequence's trajectory, or another clock?)")
    if n_posed < n_frames:
        warn(f"{n_frames - n_posed} of {n_frames} frames have no pose within {tolerance_s:g} s in the "
             f"trajectory and are left out: {n_posed} frames in {blocks_used} blocks are compared",
             str(poses), "frames-without-pose")

    class _Limited:
        """The real source cut to the frames used."""

        name = source.name
        info = source.info
        frame_count = n_frames

        def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
            lim = n_frames - start if limit is None else min(limit, n_frames - start)
            return source.frames(limit=lim, start=start)

    if tick:
        tick(f"evaluate real ({n_posed} frames with a pose, blocks of {block})")
    real = block_grids(_Limited(), mesh_path, posed, block, tolerance_s, job.config.unmeasured)
    info = known_baseline(source.info, model.camera.baseline_m, f"model '{model.name}' ([camera] baseline_m)",
                          str(sequence))
    check_model_camera(model, info, dict(source.info.device or {}), str(sequence))

    def side(mdl: SensorModel, s: int) -> list[Grid]:
        seq = SimulatedSequence(mesh_path, mdl, info, posed, clock, seed=s, tolerance_s=tolerance_s)
        return block_grids(seq, mesh_path, posed, block, tolerance_s, job.config.unmeasured)

    if tick:
        tick("simulate and evaluate")
    sim = side(model, seed)
    shape = real[0].shape
    t0 = clock.timestamp_ns[0] if clock.timestamp_ns else 0
    block_time = np.array([np.mean([(ts - t0) / 1e9 for ts in clock.timestamp_ns[a:a + n]])
                           for a, n in chunk_ranges(n_frames, block)])
    bc = block_cells(real, sim, block_time_s=block_time)
    before = locate_cells(bc, shape)
    present = present_effects(model)
    if tick:
        tick("attribute and discover")
    candidates, selected = attribute_cells(bc, info, present)
    disc: Discovery | None = None
    if discovery:
        disc, _ = discover_cells(bc, info, present, candidates)
        selected = [r["effect"] for r in candidates if r["selected"]]
    new_model = model
    for rec in candidates:
        if rec["selected"]:
            params = {k: v["value"] for k, v in rec["params"].items()}
            if rec["kind"] == "variance":
                params = {k: max(v, 0.0) for k, v in params.items()}
            new_model = new_model.with_effect(rec["effect"], **params)
    for term in (disc.terms if disc is not None else []):
        new_model = new_model.with_effect(term.effect, **term.params())
    after = None
    after_bc = None
    if resimulate:
        if tick:
            tick("simulate again with the new model")
        after_bc = block_cells(real, side(new_model, seed + 1), block_time_s=block_time)
        after = locate_cells(after_bc, shape)
    calibrated = [{"effect": r["effect"],
                   "params": {k: {"old": present[r["effect"]].get(k), "new": v["value"]}
                              for k, v in r["params"].items()}}
                  for r in candidates if r["selected"] and r["role"] == "calibration"]
    data = {
        "kind": "scan",
        "inputs": {"sequence": str(sequence), "poses": str(poses), "reference": str(reference)},
        "registration": reg_info, "frames": n_posed, "frames_read": n_frames,
        "skipped_no_pose": n_frames - n_posed, "block_frames": block, "blocks": blocks_used,
        "grid": {"distance_bin_m": DISTANCE_BIN_M, "inclination_bin_deg": INCLINATION_BIN_DEG,
                 "min_cell_count": MIN_CELL_COUNT},
        "mismatch": before, "mismatch_after": after, "candidates": candidates, "selected": selected,
        "missing_physics": [r["effect"] for r in candidates
                            if r["selected"] and r["role"] == "missing_physics"],
        "calibrated": calibrated,
        "discovered": [t.to_dict() for t in disc.terms] if disc is not None else [],
        "discovery": ({**disc.summary(), "axes": sorted(GRID_AXES)} if disc is not None else None),
        "not_testable": "effects that depend on pixel position, albedo, time or depth edges are averaged "
                        "away by the distance x inclination grid: " + ", ".join(
                            sorted({"lr_focal_mismatch", "distortion_residual", "albedo_bias",
                                    "thermal_drift", "flying_pixels"}))
                        + "; discovery looks along distance, disparity, inclination and the blocks' time "
                          "(the scan study keeps no pixel positions: u, v, radius, tile need per-pixel data)",
    }
    return ScanExplanation(data, new_model, bc, after_bc, shape, dict(source.info.device or {}))


def residual_map(bc: BlockCells, shape: tuple[int, int]) -> FloatArray:
    """Mean real-minus-sim bias per grid cell over blocks (NaN where not compared)."""
    out = np.full(shape[0] * shape[1], np.nan)
    for cell in np.unique(bc.cell):
        out[cell] = float(np.mean(bc.bias_m[bc.cell == cell]))
    return out.reshape(shape)


def write_scan_outputs(ex: ScanExplanation, out: Path, inputs: list[str],
                       options: dict[str, Any]) -> dict[str, Any]:
    """explain.json, model.toml, residual_grid.png, report.md, result.json."""
    out.mkdir(parents=True, exist_ok=True)
    data = ex.data
    write_json(out / "explain.json", data)
    (out / "model.toml").write_text(ex.new_model.to_toml())
    maps = [("before", ex.before)] + ([("after", ex.after)] if ex.after is not None else [])
    de = np.arange(ex.shape[0] + 1, dtype=np.float64) * DISTANCE_BIN_M
    ie = np.arange(ex.shape[1] + 1, dtype=np.float64) * INCLINATION_BIN_DEG
    residual_grid_figure(out / "residual_grid.png", [(label, de, ie, residual_map(b, ex.shape))
                                                     for label, b in maps])
    lines = ["# Explain (reference scan)", "",
             f"{data['frames']} frames in {data['blocks']} blocks of {data['block_frames']}; registration: "
             f"{data['registration'].get('method')}.", "",
             f"Mismatch before: {'significant' if data['mismatch']['significant'] else 'none'} "
             f"({len(data['mismatch']['regions'])} cells, blocks: "
             f"{', '.join(data['mismatch']['standpoints']) or 'none'}).",
             "", "| effect | role | delta BIC | held-out RMSE before (mm) | after (mm) | selected |",
             "|---|---|---|---|---|---|"]
    for r in data["candidates"]:
        lines.append(f"| {r['effect']} | {r['role']} | {r['delta_bic']:.1f} | "
                     f"{r['heldout_rmse_before_m'] * 1e3:.3f}"
                     f" | {r['heldout_rmse_after_m'] * 1e3:.3f} | {'yes' if r['selected'] else ''} |")
    lines += ["", "## Missing physics outside the catalogue", ""]
    if not data.get("discovered"):
        lines.append("Nothing found along " + ", ".join(sorted(GRID_AXES)) + ".")
    for d in data.get("discovered", []):
        coefs = ", ".join(f"{n} = {c['value']:.4g} +- {c['stderr']:.2g} {c['unit']}"
                          for n, c in d["coefficients"].items())
        lines += [f"- {d['quantity']} along {', '.join(d['axes'])}: `{d['expression']}`; {coefs}; held-out "
                  f"RMSE {d['heldout_rmse_before_m'] * 1e3:.3g} -> {d['heldout_rmse_after_m'] * 1e3:.3g} mm. "
                  "What makes it: " + " / ".join(d["interpretation"]) + "."]
    if data["mismatch_after"] is not None:
        lines += ["", f"Mismatch after re-simulating with model.toml: "
                  f"{'significant' if data['mismatch_after']['significant'] else 'none'}."]
    lines += ["", f"Not testable on this grid: {data['not_testable']}.", "",
              "![residual grid](residual_grid.png)", ""]
    (out / "report.md").write_text("\n".join(lines))
    write_result_info(out, "explain-scan", inputs, options, ex.device, extra={"explain": "explain.json"})
    return data
