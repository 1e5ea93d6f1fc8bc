"""The `evaluate scan` workflow: prepare (open, mesh, register), run the chunks, write the folder.

One path for everyone: the command, `evaluate batch`, `explain --scan` and the demo call
`prepare_scan` (inputs opened once), run its chunks on a ChunkRunner (`run_prepared`, or the batch's
own runner), and `write_scan` writes the result folder, so a batch item and the command write the
same files.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import check_lenses, open_recording
from depthstation.core.capture.topics import TopicChoice, topic_choice
from depthstation.core.errors import EvaluationError, InputError
from depthstation.core.frames import FrameSource
from depthstation.core.parallel import ChunkRunner, ProgressFn
from depthstation.core.progress import progress
from depthstation.core.rerun_bridge import RerunTarget, recording
from depthstation.core.results import result_folder
from depthstation.core.run_warnings import warn
from depthstation.evaluate.scan import rerun_log
from depthstation.evaluate.scan.budget import run_budget
from depthstation.evaluate.scan.chunks import (
    ScanChunk,
    frames_to_read,
    renderer_for,
    run_scan_chunks,
    scan_chunks,
    split_last,
)
from depthstation.evaluate.scan.point_reference import REFERENCE_MODES, PointParams
from depthstation.evaluate.scan.rasterise import DEFAULT_RENDERER, check_renderer
from depthstation.evaluate.scan.reference import (
    SURFACE_GAP_M,
    PoissonParams,
    measured_part,
    reference_mesh,
    sample_reference_points,
    unmeasured_file,
)
from depthstation.evaluate.scan.registration import (
    REGISTER_MODES,
    NoPosedFrame,
    NoStart,
    Registration,
    initial_similarity,
    read_pass_points,
    read_similarity,
    register,
)
from depthstation.evaluate.scan.report import write_scan
from depthstation.evaluate.scan.study import (
    FIT_MISS_SHARE,
    PER_FRAME_DIR,
    ChunkResult,
    FitCheck,
    FitSample,
    StudyConfig,
    fit_check,
    fit_sample,
)
from depthstation.evaluate.scan.trajectory import (
    POSE_CONVENTIONS,
    LocalFrames,
    Trajectory,
    local_shift,
    read_tum,
)


@dataclass
class ScanOptions:
    """Everything the command line (and a batch item's `options`) can set besides the four paths."""

    similarity: Path | None = None
    pass_points: Path | None = None
    register: str = "none"
    icp: bool | None = None  # deprecated: --icp was --register similarity, --no-icp --register none
    icp_band_m: tuple[float, float] = (0.5, 2.0)
    icp_every: int = 10
    frames: int | None = None
    every: int = 1
    per_frame_grids: bool = False
    workers: int = 1
    cluster: str | None = None
    chunk_frames: int = 64
    tolerance_s: float = 0.01
    pose_offset_s: float = 0.0  # added to the trajectory's time stamps (its clock onto the frames')
    distance_bin_m: float = 0.005
    inclination_bin_deg: float = 0.1
    distance_max_m: float = 6.0
    min_count_frame: int = 10
    min_count_sequence: int = 2000
    figure_frame: int | None = None
    intrinsics: Path | None = None
    force: bool = False
    poisson_depth: int = 9
    density_quantile: float = 0.05
    poisson_threads: int = 1
    surface_gap_m: float = SURFACE_GAP_M
    reference_mode: str = "points"  # a cloud: 'points' (planes fitted to them) or 'mesh' (its Poisson mesh)
    poses_of: str = "depth"  # the camera the trajectory describes: 'depth' or 'color' (RGB-D SLAM)
    pose_convention: str = "tum"  # how the pose file's lines are meant (trajectory.POSE_CONVENTIONS)
    depth_topic: str | None = None      # ROS recordings: topics (None: the realsense-ros layout)
    color_topic: str | None = None
    infrared_topic: str | None = None
    renderer: str = DEFAULT_RENDERER
    budget: bool = False  # --budget: the error's parts (budget.py): sensor_grid.npz, budget.json
    target: RerunTarget = field(default_factory=RerunTarget)

    @property
    def topics(self) -> TopicChoice | None:
        return topic_choice(self.depth_topic, self.color_topic, self.infrared_topic)

    def to_dict(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k not in ("target", "force")}
        d["rrd"] = self.target.rrd
        return d

    def check(self) -> None:
        if self.similarity is not None and self.pass_points is not None:
            raise InputError(None, "give either --similarity or --pass-points, not both")
        if self.register not in REGISTER_MODES:
            raise InputError(None, f"--register must be one of {', '.join(REGISTER_MODES)}, "
                                   f"not '{self.register}'")
        if self.every < 1 or self.workers < 1 or self.chunk_frames < 1:
            raise InputError(None, "--every, --workers and --chunk-frames must be at least 1")
        for name, value in (("--distance-bin-m", self.distance_bin_m),
                            ("--inclination-bin-deg", self.inclination_bin_deg),
                            ("--distance-max-m", self.distance_max_m)):
            if not (math.isfinite(value) and value > 0):
                raise InputError(None, f"{name} must be a positive number, not {value}")
        if not (math.isfinite(self.tolerance_s) and self.tolerance_s >= 0):
            raise InputError(None, f"--pose-tolerance-s must be 0 or more seconds, not {self.tolerance_s}")
        if self.figure_frame is not None and self.figure_frame < 0:
            raise InputError(None, f"--figure-frame counts from 0, not {self.figure_frame}")
        if not (math.isfinite(self.surface_gap_m) and self.surface_gap_m >= 0):
            raise InputError(None, f"--surface-gap-m must be 0 (keep all the meshed surface) or more metres, "
                                   f"not {self.surface_gap_m}")
        if not math.isfinite(self.pose_offset_s):
            raise InputError(None, f"--pose-offset-s must be a number of seconds, not {self.pose_offset_s}")
        if self.pose_convention not in POSE_CONVENTIONS:
            raise InputError(None, f"--pose-convention must be one of {', '.join(POSE_CONVENTIONS)}, "
                                   f"not '{self.pose_convention}'")
        if self.poses_of not in POSES_OF:
            raise InputError(None, f"--poses-of must be one of {', '.join(sorted(set(POSES_OF)))}, "
                                   f"not '{self.poses_of}'")
        if self.poisson_threads < 0:
            raise InputError(None, "--poisson-threads must be 0 (all cores) or more, "
                                   f"not {self.poisson_threads}")
        check_renderer(self.renderer)
        if self.reference_mode not in REFERENCE_MODES:
            raise InputError(None, f"--reference-mode must be one of {', '.join(REFERENCE_MODES)}, "
                                   f"not '{self.reference_mode}'")

    @property
    def register_mode(self) -> str:
        """--register, or what the deprecated --icp / --no-icp meant."""
        if self.icp is None:
            return self.register
        mode = "similarity" if self.icp else "none"
        warn(f"--{'' if self.icp else 'no-'}icp is deprecated: it means --register {mode} "
             "(a fitted scale hides the depth-scale error the study measures; see docs/scan-study.md)",
             code="deprecated")
        return mode

    @classmethod
    def from_mapping(cls, options: dict[str, Any], paths: dict[str, Path], source: Path | None,
                     where: str) -> ScanOptions:
        """Options of a batch item (the command's option names, snake_case) and its optional paths
        (similarity, pass_points, intrinsics); an unknown name is an error naming it."""
        names = {f.name for f in dataclasses.fields(cls)} - {"target", "workers", "cluster", "force"}
        unknown = sorted(set(options) - names)
        if unknown:
            raise InputError(source, f"{where}: unknown scan options {', '.join(unknown)} "
                                     f"(known: {', '.join(sorted(names))})")
        values: dict[str, Any] = dict(options)
        if "icp_band_m" in values:
            values["icp_band_m"] = tuple(values["icp_band_m"])
        for key in ("similarity", "pass_points", "intrinsics"):
            if key in paths:
                values[key] = paths[key]
        try:
            return cls(**values)
        except TypeError as exc:
            raise InputError(source, f"{where}: {exc}") from exc


@dataclass
class ScanJob:
    """A prepared scan study: inputs opened once, the mesh built, the trajectory registered."""

    sequence: Path
    poses: Path
    reference: Path
    out: Path
    options: ScanOptions
    source: Recording
    trajectory: Trajectory          # as read (trajectory frame)
    posed: Trajectory               # camera-to-reference (registration applied), local frame
    registration: Registration
    mesh_path: Path
    mesh_info: dict[str, Any]
    fit: FitCheck | None
    config: StudyConfig
    chunks: list[ScanChunk]
    seconds: dict[str, float] = field(default_factory=dict)
    camera: dict[str, Any] = field(default_factory=dict)  # which camera the poses are of, and the check

    @property
    def frames_to_read(self) -> int | None:
        return frames_to_read(self.source, self.config)


def prepare_scan(sequence: Path, poses: Path, reference: Path, out: Path,
                 options: ScanOptions | None = None, *, in_process: bool = True) -> ScanJob:
    """Open the sequence, read the trajectory, mesh the reference, register, cut the chunks.

    `in_process`: the chunks will run in this process (one ray-casting thread per process
    otherwise, since processes, not threads, add speed: PERF-NOTES).
    """
    opt = options or ScanOptions()
    opt.check()
    t0 = time.perf_counter()
    out = Path(out)
    for role, path in (("sequence", sequence), ("poses", poses), ("reference", reference)):
        if not Path(path).exists():
            raise InputError(path, f"{role} not found")
    out.mkdir(parents=True, exist_ok=True)
    source = open_recording(Path(sequence), intrinsics=opt.intrinsics, topics=opt.topics)
    check_lenses(source, ("depth",))
    n_frames = source.frame_count
    if opt.figure_frame is not None and n_frames and opt.figure_frame >= n_frames:
        raise InputError(Path(sequence), f"--figure-frame {opt.figure_frame}: the sequence has {n_frames} "
                                         f"frames (0 to {n_frames - 1})")
    given = read_tum(Path(poses), opt.pose_convention)
    check_clocks(source, given.shifted(opt.pose_offset_s), Path(poses), opt.tolerance_s)
    rig = depth_to_colour(source)
    depth_poses = depth_camera_poses(given, opt, rig)
    if POSES_OF[opt.poses_of] == "color" and rig is None and not source.info.depth_aligned_to_color:
        warn("--poses-of color: the recording carries no depth-to-colour extrinsics (or the identity): the "
             "poses are used as the depth camera's, off by the rig's lever arm if they are the colour "
             "camera's", str(sequence), "poses-camera")
    similarity = read_similarity(opt.similarity) if opt.similarity is not None else None
    pass_points = read_pass_points(opt.pass_points) if opt.pass_points is not None else None
    mesh, mesh_path, mesh_info = reference_mesh(
        Path(reference), out, PoissonParams(depth=opt.poisson_depth, density_quantile=opt.density_quantile,
                                         threads=opt.poisson_threads, surface_gap_m=opt.surface_gap_m),
        viewpoints=camera_centres(depth_poses, similarity, pass_points),
        points=PointParams(gap_m=opt.surface_gap_m) if opt.reference_mode == "points" else None)
    say_meshing(mesh_info, Path(reference))
    # far-away coordinates (survey frames) are shifted before anything is registered or cast
    centres = depth_poses.poses[:, :3, 3]
    local = LocalFrames(np.asarray(mesh_info.get("local_shift_m", [0.0, 0.0, 0.0]), dtype=np.float64),
                        local_shift(centres.min(axis=0), centres.max(axis=0)))
    traj = depth_poses.translated(-local.trajectory_m)
    t_mesh = time.perf_counter()
    unmeasured = unmeasured_file(mesh_path, mesh_info)
    scanned = measured_part(mesh, unmeasured, Path(reference))  # fitted to, and checked on, what was scanned
    point_fits = mesh_path.parent / mesh_info["point_fits"]["file"] if "point_fits" in mesh_info else None
    try:
        reg = register(source, traj, scanned, sample_reference_points(scanned), mode=opt.register_mode,
                       similarity=similarity, pass_points=pass_points, band_m=opt.icp_band_m,
                       tolerance_s=opt.tolerance_s, every=opt.icp_every, local=local if local.any else None)
    except NoPosedFrame as exc:  # the trajectory's stamps sit between the frames' (another rate, an offset)
        raise InputError(Path(poses), str(exc)) from exc
    except NoStart as exc:   # a frame far from the reference's: exit 1 before, as if the station failed
        raise InputError(Path(poses), f"--register {opt.register_mode}: {exc}; give a start with "
                                      "--similarity FILE or --pass-points FILE, or check the pose file's "
                                      "frame and units") from exc
    posed = traj.transformed(reg.matrix)
    config = StudyConfig(opt.distance_bin_m, opt.inclination_bin_deg, opt.distance_max_m, 90.0,
                         every=opt.every, max_frames=opt.frames, tolerance_s=opt.tolerance_s,
                         nthreads=0 if in_process else 1,
                         per_frame_dir=out / PER_FRAME_DIR if opt.per_frame_grids else None,
                         renderer=opt.renderer, unmeasured=None if point_fits else unmeasured,
                         point_fits=point_fits)
    renderer = renderer_for(mesh_path, source.info.depth_intrinsics, config)
    sample = fit_sample(source)  # read once: every reading of the poses below is checked on it
    fit = fit_check(renderer, source, posed, tolerance_s=opt.tolerance_s, sample=sample)
    say_registration(reg, fit, Path(sequence))
    fixed = reg.mode not in ("rigid", "similarity")  # poses used as read, then moved by a fixed transform
    camera = check_pose_camera(renderer, source, posed, fit, rig, POSES_OF[opt.poses_of], opt.tolerance_s,
                               Path(sequence), sample, fixed)
    camera["offset_s"] = opt.pose_offset_s
    if fixed and not local.any:
        camera["convention"] = check_pose_convention(renderer, source, fit, Path(poses), opt, rig,
                                                     reg.matrix, Path(sequence), sample)
    t_reg = time.perf_counter()
    chunks = split_last(scan_chunks(Path(sequence), mesh_path, posed, config, chunk_frames=opt.chunk_frames,
                                    intrinsics=opt.intrinsics, source=source, topics=opt.topics))
    return ScanJob(Path(sequence), Path(poses), Path(reference), out, opt, source, given, posed, reg,
                   mesh_path, mesh_info, fit, config, chunks,
                   {"reference": t_mesh - t0, "registration": t_reg - t_mesh}, camera)


def _frame_time_s(source: FrameSource, index: int) -> float | None:
    for fs in source.frames(limit=1, start=index):
        return fs.timestamp_ns * 1e-9
    return None


def check_clocks(source: FrameSource, trajectory: Trajectory, poses: Path, tolerance_s: float) -> None:
    """Frames and poses on one clock: their time spans must overlap. Poses in milliseconds or
    nanoseconds, relative to the first frame, or from another clock match no frame; said here, in
    the units of both files, instead of a registration that finds nothing."""
    n = source.frame_count
    first = _frame_time_s(source, 0)
    if first is None or len(trajectory) == 0:
        return
    p0, p1 = float(trajectory.timestamps_s[0]), float(trajectory.timestamps_s[-1])

    def apart(last: float) -> bool:
        return p1 + tolerance_s < first or p0 - tolerance_s > last

    fps = source.info.fps
    # the span from the frame rate first: reading the last frame reads the whole file through
    if n and fps and not apart(first + (n - 1) / fps):
        return
    last = _frame_time_s(source, n - 1) if n else first
    if last is not None and apart(last):
        raise InputError(poses, f"no pose time lies within the frames' times: poses span {p0:.6f} to "
                                f"{p1:.6f} s, the frames {first:.6f} to {last:.6f} s (poses in "
                                "milliseconds or nanoseconds, relative to the first frame, or from "
                                "another clock? TUM time stamps are seconds on the frames' clock)")


UNMEASURED_SHARE = 0.01  # of the meshed reference's vertices beyond the cloud's gap
POSES_OF = {"depth": "depth", "color": "color", "colour": "color"}
RIG_MIN_M = 0.005  # a depth-to-colour lever arm shorter than this is not worth a second fit check
OTHER_CAMERA_GAIN = 0.75  # the other camera's median |error| at most this share of the given one's


def depth_to_colour(source: Recording) -> NDArray[np.float64] | None:
    """T_colour_depth (4x4: depth-camera points into the colour camera's frame) of the recording,
    None where it is the identity (aligned depth, or no extrinsics recorded)."""
    if source.info.depth_aligned_to_color:  # one camera: the depth is the colour's
        return None
    m = np.asarray(source.info.depth_to_color.matrix, dtype=np.float64)
    return None if np.allclose(m, np.eye(4), atol=1e-9) else m


def depth_camera_poses(given: Trajectory, opt: ScanOptions, rig: NDArray[np.float64] | None) -> Trajectory:
    """The trajectory as read, on the frames' clock (`--pose-offset-s`) and of the depth camera
    (`--poses-of`)."""
    out = given.shifted(opt.pose_offset_s)
    return out.camera_moved(rig) if POSES_OF[opt.poses_of] == "color" and rig is not None else out


CONVENTION_GAIN = 0.5  # another reading's median |error| at most this share of the given one's


def check_pose_convention(renderer: Any, source: Recording, fit: FitCheck | None, poses: Path,
                          opt: ScanOptions, rig: NDArray[np.float64] | None, matrix: NDArray[np.float64],
                          sequence: Path, sample: FitSample | None = None) -> dict[str, Any]:
    """Where the trajectory does not fit the reference: would it, read another way? A file of
    world-to-camera poses (COLMAP's images.txt order) or with the quaternion's w first fits nowhere
    as TUM; the fit check says only that it does not fit. Each other reading is fit-checked (with
    the same fixed transform to the reference); one that fits is a warning naming it."""
    out: dict[str, Any] = {"given": opt.pose_convention}
    if fit is None or fit.fits:
        return {**out, "checked": False, "reason": "the trajectory fits as given"}
    tried: dict[str, dict[str, Any]] = {}
    best: tuple[str, FitCheck] | None = None
    for name in POSE_CONVENTIONS:
        if name == opt.pose_convention:
            continue
        alt_poses = depth_camera_poses(read_tum(poses, name), opt, rig).transformed(matrix)
        alt = fit_check(renderer, source, alt_poses, tolerance_s=opt.tolerance_s, sample=sample)
        if alt is None:
            continue
        tried[name] = alt.to_dict()
        if alt.fits and (best is None or alt.median_abs_error_m < best[1].median_abs_error_m):
            best = (name, alt)
    out.update({"checked": True, "tried": tried})
    clear = best is not None and (not np.isfinite(fit.median_abs_error_m)
                                  or best[1].median_abs_error_m < CONVENTION_GAIN * fit.median_abs_error_m)
    if best is None or not clear:
        out["fits_as"] = None
        return out
    name, alt = best
    out["fits_as"] = name
    warn(f"the trajectory fits the reference when its lines are read as {POSE_CONVENTIONS[name]}: "
         f"median |error| {1000 * alt.median_abs_error_m:.1f} mm, {100 * alt.off_share:.0f} % of the pixels "
         f"off, against {100 * fit.off_share:.0f} % as {POSE_CONVENTIONS[opt.pose_convention]}: give "
         f"--pose-convention {name}", str(poses), "pose-convention")
    return out


def check_pose_camera(renderer: Any, source: Recording, posed: Trajectory, fit: FitCheck | None,
                      rig: NDArray[np.float64] | None, poses_of: str, tolerance_s: float,
                      sequence: Path, sample: FitSample | None = None, fixed: bool = True) -> dict[str, Any]:
    """Which camera of the rig the poses describe, checked on the data: RGB-D SLAM on depth aligned
    to colour (ORB-SLAM3 on a RealSense, as in the paper) tracks the colour camera, and its poses
    put on the depth camera's rays are off by the lever arm between the two (59 mm on a D455):
    an error that grows with the inclination, the very thing the grid measures. The other
    camera's poses are fit-checked too; clearly better is a warning (`--poses-of`). Not after a
    registration fitted to the poses as read (`fixed` False): ICP has then taken part of the lever
    arm into its transform, and the other camera's poses would need a registration of their own."""
    out: dict[str, Any] = {"poses_of": poses_of, "other_fits_better": None}
    if rig is None:
        aligned = source.info.depth_aligned_to_color
        return {**out, "checked": False, "reason": "depth aligned to colour: one camera" if aligned
                else "no depth-to-colour extrinsics in the recording"}
    lever = float(np.linalg.norm(rig[:3, 3]))
    out["lever_arm_m"] = lever
    if fit is None:
        return {**out, "checked": False, "reason": "no fit check (no frame with a pose)"}
    if lever < RIG_MIN_M:
        return {**out, "checked": False, "reason": f"lever arm under {1000 * RIG_MIN_M:g} mm"}
    if not fixed:
        return {**out, "checked": False, "reason": "registered by ICP on the poses as read: the other "
                                                   "camera's would need their own registration"}
    other = "color" if poses_of == "depth" else "depth"
    move = rig if poses_of == "depth" else np.asarray(np.linalg.inv(rig), dtype=np.float64)
    alt = fit_check(renderer, source, posed.camera_moved(move), tolerance_s=tolerance_s, sample=sample)
    out.update({"checked": alt is not None, "other": other,
                "fit_other": None if alt is None else alt.to_dict()})
    if alt is None or not np.isfinite(alt.median_abs_error_m) or not np.isfinite(fit.median_abs_error_m):
        return out
    better = (alt.median_abs_error_m < OTHER_CAMERA_GAIN * fit.median_abs_error_m
              and alt.off_share <= fit.off_share)
    out["other_fits_better"] = bool(better)
    if better:
        why = ("RGB-D SLAM on depth aligned to colour tracks the colour camera" if other == "color" else
               "a trajectory of the depth stream itself (depth-only SLAM, or poses already moved) is the "
               "depth camera's")
        warn(f"the trajectory fits the reference better as the {other} camera's poses than as the "
             f"{poses_of} camera's (median |error| {1000 * alt.median_abs_error_m:.1f} mm against "
             f"{1000 * fit.median_abs_error_m:.1f} mm, {100 * alt.off_share:.0f} % of the pixels off "
             f"against {100 * fit.off_share:.0f} %; the rig's lever arm is {1000 * lever:.0f} mm, and its "
             f"error grows with the inclination): {why}. Give --poses-of {other} if the trajectory is that "
             "camera's", str(sequence), "poses-camera")
    return out


def say_meshing(mesh_info: dict[str, Any], reference: Path) -> None:
    """A reference meshed from a cloud holds surface nobody measured (Poisson's rounded edges and
    closed holes): pixels that see it compare with it, and u95 does not include that error."""
    gap = mesh_info.get("surface_to_points")
    if not isinstance(gap, dict) or gap.get("share_beyond_gap", 0.0) <= UNMEASURED_SHARE:
        return
    um = mesh_info.get("unmeasured")
    triangles = int(um.get("triangles", 0)) if isinstance(um, dict) else 0
    effect = ("the study measures against planes fitted to the points, and the pixels whose triangle the "
              "points do not support are left out (summary: pixels.reference_*)" if "point_fits" in mesh_info
              else f"its {triangles} triangles are kept as occluders, and the pixels that see them are left "
              "out of the grid (summary: pixels.unmeasured_surface; --surface-gap-m 0 keeps them)"
              if triangles else
              "pixels that see it compare with a surface nobody measured, and their cells' u95 does not "
              "include that (--surface-gap-m leaves them out)")
    warn(f"{100 * gap['share_beyond_gap']:.1f} % of the reference mesh made from the cloud lies more than "
         f"{1000 * gap['gap_m']:.0f} mm off the scanned surface (up to {1000 * gap['max_m']:.0f} mm: "
         f"Poisson's rounded edges and closed holes): {effect}; raise --density-quantile, or give a mesh",
         str(reference), "reference-meshing")


def say_registration(reg: Registration, fit: FitCheck | None, sequence: Path) -> None:
    """The two things a registration can hide, said where the user looks: a trajectory that does
    not fit the reference, and a scale that absorbs the depth-scale error."""
    advice = ("register it: --register rigid (another frame), similarity (another frame and scale), "
              "pass-points, or give --similarity; or check the depth units, the pose file's axes and "
              "quaternion order, and the reference's units")
    if fit is not None and fit.miss_share > FIT_MISS_SHARE:
        warn(f"the trajectory does not fit the reference after registration '{reg.mode}': "
             f"{100 * fit.miss_share:.0f}% of the depth pixels of {fit.frames} frames see no reference "
             f"surface at all (the reference in other axes or units, or covering little of the walk); "
             f"{advice}", str(sequence), "registration-fit")
    elif fit is not None and not fit.fits:
        warn(f"the trajectory does not fit the reference after registration '{reg.mode}': "
             f"{100 * fit.off_share:.0f}% of the depth pixels of {fit.frames} frames miss the mesh by more "
             f"than the depth noise explains (median |error| {1000 * fit.median_abs_error_m:.0f} mm); "
             f"{advice}",
             str(sequence), "registration-fit")
    if reg.absorbed() is not None:
        warn(f"{reg.caption()}: that is the depth-scale error of the depth the trajectory was built on "
             "(RGB-D SLAM); if the poses are exact instead, the scale has moved the cameras to fit that "
             "depth error, and the grid measures against the moved cameras: its errors are then not the "
             "camera's, too small near the registration band and wrong beyond it (--register none keeps "
             "them, with poses in the reference frame)", str(sequence), "absorbed-scale")
    if reg.mode in ("rigid", "similarity"):
        band = reg.icp.get("band_m") if isinstance(reg.icp, dict) else None
        within = f" ({band[0]:g}-{band[1]:g} m)" if isinstance(band, list | tuple) and len(band) == 2 else ""
        warn(f"--register {reg.mode} fitted the trajectory to the reference on this camera's own depth"
             f"{within}: a depth error there (an offset, a scale) is partly taken into the pose, so the "
             "grid reads it near zero in that band and misplaced beyond it. For the camera's absolute "
             "error give poses in the reference frame (--register none) or register on independent "
             "targets (--register pass-points)", str(sequence), "registration-absorbs")


def camera_centres(trajectory: Trajectory, similarity: NDArray[np.float64] | None,
                   pass_points: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
                   ) -> NDArray[np.float64]:
    """The walk's camera centres in the reference frame by the initial registration (to orient a
    cloud's normals towards where its surfaces were seen from)."""
    m = initial_similarity(similarity, pass_points)[0]
    c = trajectory.poses[:, :3, 3]
    return np.asarray(c @ m[:3, :3].T + m[:3, 3], dtype=np.float64)


def run_prepared(job: ScanJob, runner: ChunkRunner, *, rec: Any = None,
                 on_progress: ProgressFn | None = None) -> ChunkResult:
    """Run the job's chunks on `runner`; in one process every frame reaches the rerun stream."""
    opt = job.options
    total = job.frames_to_read

    with progress() as bar:
        task = bar.add_task("scan", total=total, status="")

        def on_frame(index: int, stats: NDArray[np.int64]) -> None:
            bar.update(task, completed=index + 1, status=f"{int(stats[3])} px")
            rerun_log.log_frame(rec, index, stats)

        def on_chunk(k: int, n: int, merged: ChunkResult) -> None:
            last = max(merged.used) if merged.used else 0
            if not runner.in_process:
                bar.update(task, completed=last + 1, status=f"chunk {k + 1}/{n}")
            final = k + 1 == n
            rerun_log.log_grid(rec, merged.grid, last,
                               opt.min_count_sequence if final else opt.min_count_frame)

        def on_task(done: int, n: int) -> None:
            if on_progress is not None:
                on_progress(done, n)

        t0 = time.perf_counter()
        result = run_scan_chunks(job.sequence, job.mesh_path, job.posed, job.config, runner,
                                 chunk_frames=opt.chunk_frames, intrinsics=opt.intrinsics,
                                 topics=opt.topics, source=job.source,
                                 on_frame=on_frame if runner.in_process else None,
                                 on_chunk=on_chunk, progress=on_task)
        job.seconds["study"] = time.perf_counter() - t0
    if not result.used:
        raise EvaluationError(f"no frame could be evaluated ({len(result.no_pose)} frames had no pose "
                              f"within {opt.tolerance_s} s)")
    if result.no_pose:  # the grid holds only the posed frames: a tracker that lost half the walk says so
        n = len(result.used) + len(result.no_pose) + len(result.no_depth)
        warn(f"{len(result.no_pose)} of {n} frames have no pose within {opt.tolerance_s:g} s in the "
             "trajectory: left out of the grid (the tracker lost them, or --pose-tolerance-s is too tight)",
             str(job.poses), "frames-without-pose")
    return result


def run_scan(sequence: Path, poses: Path, reference: Path, out: Path,
             options: ScanOptions | None = None) -> dict[str, Any]:
    """The reference-scan study (paper Section 3.2) into the result folder `out`; returns the summary."""
    opt = options or ScanOptions()
    opt.check()
    inputs = [p for p in (sequence, poses, reference, opt.similarity, opt.pass_points, opt.intrinsics)
              if p is not None]
    with result_folder(out, force=opt.force, inputs=inputs, kind="scan") as tmp, \
            ChunkRunner(opt.workers, opt.cluster) as runner:
        job = prepare_scan(sequence, poses, reference, tmp, opt, in_process=runner.in_process)
        with recording("depthstation-scan", opt.target.within(out, tmp),
                       description=rerun_log.DESCRIPTION) as rec:
            result = run_prepared(job, runner, rec=rec)
            rerun_log.log_grid_tensors(rec, result.grid, opt.min_count_sequence)
        summary = write_scan(job, result)
        if opt.budget:  # after the plain study's files, which it leaves as they are
            summary["budget"] = run_budget(job, result, runner)
        return summary
