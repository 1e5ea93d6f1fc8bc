"""A simulated D4xx behind the acquire Camera/CalibratableCamera protocols.

It renders the board scene at the pose a simulated operator sets, warms up like a device (an
exponential approach of the temperatures to steady state on an injectable, accelerable clock),
drifts with temperature, carries calibration errors that on-chip and tare calibration reduce
(reporting health values on the device's scales: Intel's on-chip health, tare's relative depth
error as a fraction), and can drop off the bus after N frames. Its temperatures are continuous
(the physics); the device's whole-degree readings are in the fake pyrealsense2 of the tests.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.board_pose import pose_metrics
from depthstation.core.camera_model import StreamInfo, pixel_rays
from depthstation.core.device import CalibrationResult
from depthstation.core.errors import CameraDisconnected, CameraError, InputError
from depthstation.core.frames import FrameSet
from depthstation.core.protocol import Streams
from depthstation.simulate.model import SensorModel, load_model
from depthstation.simulate.poses import standpoint_pose
from depthstation.simulate.scene import Scene, board_scene
from depthstation.simulate.view_renderer import ViewRenderer

# calibration errors of a fresh-from-the-shelf unit (catalogue effect -> params)
DEFAULT_CALIBRATION_ERRORS: dict[str, dict[str, float]] = {
    "disparity_offset": {"offset_px": 0.06},  # what tare calibration removes
    "lr_focal_mismatch": {"ratio": 1.5e-4},  # what on-chip calibration removes
}
ON_CHIP_EFFECTS = ("lr_focal_mismatch", "distortion_residual", "depth_scale")
TARE_EFFECTS = ("disparity_offset",)
# The effect context (and the fused sampler built on it) is rebuilt only when the temperature moved
# by this much: 0.05 degC shifts the disparity by 2e-4 px at the default drift of 0.004 px/degC,
# far below the 0.08 px noise, while a rebuild per frame costs ~70 ms at 1280x720.
CONTEXT_TEMPERATURE_STEP_C = 0.05
LATE_QUEUE_FRAMES = 2  # frames a real device buffers for a late reader before it drops them
ON_CHIP_SCALE = {"lr_focal_mismatch": ("ratio", 4e-4), "distortion_residual": ("coeff_px", 0.4),
                 "depth_scale": ("scale_error", 0.01)}


class SimulatedCamera:
    """Camera protocol implementation over the simulator (see module docstring)."""

    def __init__(self, model: SensorModel | str = "d455", *, board: Board | None = None,
                 scene: Scene | None = None, seed: int = 0, real_time: bool = False,
                 clock_scale: float = 1.0, clock: Callable[[], float] | None = None,
                 pose: NDArray[Any] | None = None,
                 pose_provider: Callable[[float], NDArray[Any]] | None = None,
                 ambient_c: float = 25.0, steady_asic_c: float = 40.0, steady_projector_c: float = 44.0,
                 thermal_time_constant_s: float = 720.0, thermal_coeff_px_per_c: float = 0.004,
                 calibration_errors: dict[str, dict[str, float]] | None = None,
                 calibration_residual: float = 0.1, disconnect_after_frames: int | None = None,
                 failed_reconnects: int = 0, start_epoch_ns: int = 1_700_000_000_000_000_000,
                 drop_late_frames: bool = False, prefetch: bool = True) -> None:
        self.base_model = load_model(model)
        self.board = board or Board()
        self.scene = scene or board_scene(self.board)
        self.seed = seed
        self.real_time = real_time
        self.clock_scale = clock_scale
        self._clock = clock
        self._clock0: float | None = None
        start_pose = pose if pose is not None else standpoint_pose(self.board, 1.5, 0.0)
        self.pose = np.asarray(start_pose, dtype=np.float64)
        self.pose_provider = pose_provider
        self.ambient_c = ambient_c
        self.steady_asic_c = steady_asic_c
        self.steady_projector_c = steady_projector_c
        self.tau_s = thermal_time_constant_s
        self.thermal_coeff = thermal_coeff_px_per_c
        self.errors = {k: dict(v) for k, v in (DEFAULT_CALIBRATION_ERRORS if calibration_errors is None
                                               else calibration_errors).items()}
        self.calibration_residual = calibration_residual
        self.disconnect_after_frames = disconnect_after_frames
        self.failed_reconnects = failed_reconnects
        self.start_epoch_ns = start_epoch_ns
        self.drop_late_frames = drop_late_frames
        self.dropped_frames = 0
        self.prefetch = prefetch
        self._executor: Any = None
        self._ahead: tuple[ViewRenderer, NDArray[Any], tuple[int, int, float, float], Any] | None = None
        self._ctx_temp: tuple[float, float] | None = None  # (quantised temperature, its context time)
        self.written_table: bytes | None = None
        self._rng = np.random.default_rng([seed, 991])
        self._renderer: ViewRenderer | None = None
        self.info: StreamInfo | None = None
        self._streams: Streams | None = None
        self._frames_total = 0
        self._frames_since_start = 0
        self._t_dev = 0.0
        self._last_wall: float | None = None
        self._disconnected = False
        self._starts_refused = 0

    # -- time and temperature -------------------------------------------------------------------
    def set_clock(self, clock: Callable[[], float]) -> None:
        """Follow another clock (seconds; the acquire stage's accelerated warm-up clock)."""
        self._clock = clock
        self._clock0 = None

    def set_pose(self, cam_to_board: NDArray[Any]) -> None:
        """Where the depth camera is (4x4 camera-to-board); used from the next frame on."""
        self.pose = np.asarray(cam_to_board, dtype=np.float64)

    def set_pose_provider(self, provider: Callable[[float], NDArray[Any]] | None) -> None:
        """A callback t_s -> camera-to-board pose, asked once per frame with the device time."""
        self.pose_provider = provider

    def _clock_time(self) -> float | None:
        clock = self._clock or (time.monotonic if self.real_time else None)
        if clock is None:
            return None
        now = clock()
        if self._clock0 is None:
            self._clock0 = now - self._t_dev / self.clock_scale
        return (now - self._clock0) * self.clock_scale

    def device_time_s(self) -> float:
        """Seconds since power-on: frames advance it by 1/fps, a (scaled) clock may move it further."""
        ct = self._clock_time()
        return self._t_dev if ct is None else max(self._t_dev, ct)

    def temperature_at(self, t_s: float) -> dict[str, float]:
        """First-order warm-up: T(t) = T_steady - (T_steady - T_ambient) exp(-t / tau)."""
        f = math.exp(-max(t_s, 0.0) / self.tau_s)
        fp = math.exp(-max(t_s, 0.0) / (0.6 * self.tau_s))
        return {"asic": self.steady_asic_c - (self.steady_asic_c - self.ambient_c) * f,
                "projector": self.steady_projector_c - (self.steady_projector_c - self.ambient_c) * fp}

    def temperatures(self) -> dict[str, float]:
        return self.temperature_at(self.device_time_s())

    # -- model of this unit ---------------------------------------------------------------------
    def effective_model(self) -> SensorModel:
        """The base model plus this unit's calibration errors and its thermal drift. The errors add to
        what the model already carries (the default d455's residual offset and scale after calibration
        stay under what the camera's own calibration routines reduce)."""
        m = self.base_model
        for name, params in self.errors.items():
            own = self.base_model.effect(name)
            m = m.with_effect(name, **{k: v + (own.params.get(k, 0.0) if own is not None else 0.0)
                                       for k, v in params.items()})
        if self.thermal_coeff and m.effect("thermal_drift") is None:
            m = m.with_effect("thermal_drift", coeff_px_per_c=self.thermal_coeff,
                              reference_c=self.steady_asic_c)
        return m

    # -- Camera protocol ------------------------------------------------------------------------
    def start(self, streams: Streams | None = None) -> StreamInfo:
        """Stream `streams`; the same streams already running keep running (as the live camera)."""
        streams = streams or self._streams or Streams()
        if self._renderer is not None and self.info is not None and streams == self._streams:
            return self.info
        if self._disconnected and self._starts_refused < self.failed_reconnects:
            self._starts_refused += 1
            raise CameraError("simulated camera: no device (still unplugged)")
        self._disconnected = False
        self._streams = streams
        info = self.base_model.camera.stream_info(streams.width, streams.height, float(streams.fps),
                                                  infrared=streams.infrared)
        if not streams.color:
            info = StreamInfo(info.depth_intrinsics, None, info.depth_to_color, info.depth_units_m,
                              False, info.infrared_intrinsics, info.baseline_m, info.fps, info.device)
        self.info = info
        self._renderer = ViewRenderer(self.scene, self.effective_model(), info, seed=self.seed,
                                      infrared=streams.infrared, color=streams.color)
        self._frames_since_start = 0
        self._last_wall = None
        return info

    def reconnect(self) -> StreamInfo:
        """Stop and start again with the last streams (what a user does after re-plugging)."""
        self.stop()
        return self.start(self._streams)

    def stop(self) -> None:
        self._drain()
        self._renderer = None

    def wait_for_frames(self, timeout_s: float = 5.0) -> FrameSet:
        if self._disconnected:
            raise CameraDisconnected("simulated camera disconnected")
        if self._renderer is None or self.info is None:
            raise CameraError("simulated camera not started")
        if (self.disconnect_after_frames is not None
                and self._frames_since_start >= self.disconnect_after_frames):
            self.disconnect_after_frames = None  # the fault happens once
            self._disconnected = True
            self._starts_refused = 0
            self._drain()
            self._renderer = None
            raise CameraDisconnected(f"simulated camera disconnected after {self._frames_since_start} frames")
        fps = float(self.info.fps or 30.0)
        if self.real_time:
            self._pace(fps)
        t = self._t_dev + (1.0 / fps if self._frames_total else 0.0)
        ct = self._clock_time()
        self._t_dev = t if ct is None else max(t, ct)
        pose = self.pose_provider(self._t_dev) if self.pose_provider is not None else self.pose
        r = self._renderer
        temp = self.temperature_at(self._t_dev)["asic"]
        stamp = self.start_epoch_ns + round(self._t_dev * 1e9)
        ctx_temp, ctx_time = self._context_temperature(temp)
        job = (self._frames_total, stamp, ctx_time, ctx_temp)
        fs = self._take_prefetched(r, pose, job)
        if fs is None:
            fs = self._render(r, pose, job)
        fs.metadata.update({"temperature_c": temp, "device_time_s": self._t_dev})
        self._frames_total += 1
        self._frames_since_start += 1
        if self.prefetch and ct is None and self.pose_provider is None:
            self._prefetch_next(r, pose, fps)
        return fs

    # -- rendering (optionally one frame ahead, as a device exposes while the host works) --------
    def _render(self, r: ViewRenderer, pose: NDArray[Any], job: tuple[int, int, float, float]) -> FrameSet:
        """One frame: geometry and colour only when the pose changed, then the per-frame noise,
        drawn from a generator of (seed, frame number) alone, so the frame never depends on timing."""
        index, stamp, ctx_time, ctx_temp = job
        r.set_pose(pose)
        rng = np.random.default_rng([self.seed, index])
        return r.frame(index, stamp, ctx_time, ctx_temp, rng=rng)

    def _prefetch_next(self, r: ViewRenderer, pose: NDArray[Any], fps: float) -> None:
        """Render the next frame in the background at the current pose; used only if the pose and
        the frame's inputs are still the same when it is asked for."""

        t_next = self._t_dev + 1.0 / fps
        temp = self.temperature_at(t_next)["asic"]
        q = round(temp / CONTEXT_TEMPERATURE_STEP_C) * CONTEXT_TEMPERATURE_STEP_C
        if self._ctx_temp is None or self._ctx_temp[0] != q:
            return  # the effect context changes: render in line
        job = (self._frames_total, self.start_epoch_ns + round(t_next * 1e9), self._ctx_temp[1], q)
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="simcam")
        pose = np.array(pose, dtype=np.float64)
        self._ahead = (r, pose, job, self._executor.submit(self._render, r, pose, job))

    def _take_prefetched(self, r: ViewRenderer, pose: NDArray[Any],
                         job: tuple[int, int, float, float]) -> FrameSet | None:
        """The frame rendered ahead if it matches (renderer, pose, frame inputs); always waits for
        a render in flight first, since the renderer is not shared between threads."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return None
        r_a, pose_a, job_a, fut = ahead
        fs: FrameSet = fut.result()
        if r_a is r and job_a == job and np.array_equal(pose_a, np.asarray(pose, dtype=np.float64)):
            return fs
        return None

    def _drain(self) -> None:
        """Wait for (and drop) a frame rendered ahead."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None:
            ahead[3].result()

    def _pace(self, fps: float) -> None:
        """Frames on a fixed schedule of 1/fps (scaled): a reader that falls behind catches up
        without waiting; with `drop_late_frames`, one more than LATE_QUEUE_FRAMES late loses the
        frames it missed, as a device's queue does (frame numbers then show gaps)."""
        period = 1.0 / (fps * self.clock_scale)
        now = time.monotonic()
        if self._last_wall is None:
            self._last_wall = now
            return
        due = self._last_wall + period
        if due > now:
            time.sleep(due - now)
        elif self.drop_late_frames:
            missed = int((now - due) / period)
            if missed > LATE_QUEUE_FRAMES:
                lost = missed - LATE_QUEUE_FRAMES
                self._frames_total += lost
                self._t_dev += lost / fps
                self.dropped_frames += lost
                due += lost * period
        elif now - due > LATE_QUEUE_FRAMES * period:
            due = now  # a long pause (the reader away): the schedule starts again, no burst
        self._last_wall = due

    def _context_temperature(self, temp_c: float) -> tuple[float, float]:
        """The temperature (and a context time) the effects see: quantised, so that a camera
        holding still re-uses one effect context and only draws the per-frame noise."""
        q = round(temp_c / CONTEXT_TEMPERATURE_STEP_C) * CONTEXT_TEMPERATURE_STEP_C
        if self._ctx_temp is None or self._ctx_temp[0] != q:
            self._ctx_temp = (q, self._t_dev)
        return self._ctx_temp

    def truth(self, margin_m: float = 0.01) -> dict[str, Any]:
        """What the simulator knows of the latest frame (never shown to the station's guidance):
        the depth camera's true board pose, its distance and inclination, and the depth noise the
        model implies on the board's squares (RMS orthogonal to the board, quantisation included)."""

        r = self._renderer
        if r is None or r.geometry is None or r._pose is None:
            raise CameraError("simulated camera: no frame rendered yet")
        cam_to_board = r._pose
        b2c = np.asarray(np.linalg.inv(cam_to_board), dtype=np.float64)
        d, inc, az = pose_metrics(self.board, b2c[:3, :3], b2c[:3, 3])
        g = r.geometry
        w, h = self.board.size_m
        p = g.points_world
        on_grid = ((p[..., 0] > margin_m) & (p[..., 0] < w - margin_m) & (p[..., 1] > margin_m)
                   & (p[..., 1] < h - margin_m) & (np.abs(p[..., 2]) < 1e-4))
        ctx = r.context(*(self._ctx_temp[::-1] if self._ctx_temp else (0.0, 40.0)))
        var = np.broadcast_to(r.model.variance_m2(ctx), g.z_m.shape)
        # a z-depth error dz moves the point along its ray by dz |ray| (ray with z = 1), which is
        # dz |ray| cos(inclination) orthogonal to the board
        ray_norm = np.linalg.norm(pixel_rays(r.info.depth_intrinsics), axis=-1)
        orth = ray_norm * np.cos(np.radians(g.inclination_deg))
        noise = float(np.sqrt(np.mean((var * orth * orth)[on_grid]))) if on_grid.any() else float("nan")
        return {"source": "simulated camera", "board_to_depth": b2c.tolist(),
                "distance_m": d, "inclination_deg": inc, "azimuth_deg": az,
                "noise_m": noise, "board_pixels": int(on_grid.sum()), "seed": self.seed}

    def device_info(self) -> dict[str, str]:
        return {k: str(v) for k, v in self.base_model.camera.device_info().items()}

    def options(self) -> dict[str, float]:
        cam = self.base_model.camera
        return {"depth_units": cam.depth_units_m, "stereo_baseline": cam.baseline_m * 1000.0,
                "emitter_enabled": 1.0, "laser_power": 150.0, "visual_preset": 0.0,
                "asic_temperature": self.temperatures()["asic"],
                "projector_temperature": self.temperatures()["projector"]}

    # -- CalibratableCamera ---------------------------------------------------------------------
    def calibration_table(self) -> bytes:
        """The unit's current calibration state (JSON; stands in for the binary D4xx table)."""
        return self._table(self.errors)

    def _table(self, errors: dict[str, dict[str, float]]) -> bytes:
        doc = {"format": "depthstation-sim-calibration", "errors": errors}
        return json.dumps(doc, sort_keys=True).encode()

    def _require_streaming(self) -> None:
        if self._renderer is None:
            raise CameraError("simulated camera: start streaming before calibrating")

    def on_chip_health(self, errors: dict[str, dict[str, float]] | None = None) -> float:
        """Intel-style health: 0 perfect, < 0.25 good, >= 0.75 calibration required."""
        errs = self.errors if errors is None else errors
        h = 0.0
        for name, (param, full) in ON_CHIP_SCALE.items():
            h += abs(errs.get(name, {}).get(param, 0.0)) / full
        return h

    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult:
        """Estimate the imagers' relative geometry anew: lr/distortion/scale errors shrink."""
        self._require_streaming()
        new = {k: dict(v) for k, v in self.errors.items()}
        for name in ON_CHIP_EFFECTS:
            if name in new:
                new[name] = {p: v * self.calibration_residual * (1 + 0.2 * float(self._rng.standard_normal()))
                             for p, v in new[name].items()}
        health = self.on_chip_health()
        return CalibrationResult("on_chip", self._table(new), (health,),
                                 {"health_after": self.on_chip_health(new), "simulated": True})

    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult:
        """Match the depth at a known distance from the depth origin: the disparity offset shrinks.
        Health = (before, after), the relative depth error at the ground truth as a fraction
        (Z / GT - 1), the device's scale."""
        self._require_streaming()
        if not 0.2 < ground_truth_m < 10.0:
            raise InputError(None, f"tare ground truth must be a distance in metres, got {ground_truth_m}")
        assert self.info is not None
        fx = self.info.depth_intrinsics.fx
        fb = fx * self.base_model.camera.baseline_m
        to_px = fx / self.base_model.camera.reference_fx   # offset_px is stated at 1280 wide

        def rel_error(errors: dict[str, dict[str, float]]) -> float:
            off = errors.get("disparity_offset", {}).get("offset_px", 0.0) * to_px
            z = fb / (fb / ground_truth_m + off)
            return (z - ground_truth_m) / ground_truth_m

        new = {k: dict(v) for k, v in self.errors.items()}
        if "disparity_offset" in new:
            off = new["disparity_offset"]["offset_px"]
            new["disparity_offset"] = {"offset_px": off * self.calibration_residual
                                       * (1 + 0.2 * float(self._rng.standard_normal()))}
        return CalibrationResult("tare", self._table(new), (rel_error(self.errors), rel_error(new)),
                                 {"ground_truth_m": ground_truth_m, "simulated": True})

    def set_calibration_table(self, table: bytes) -> None:
        """Apply a table (this session only, like the device's dynamic area)."""
        try:
            data = json.loads(bytes(table).decode())
            errors = {str(k): {str(p): float(x) for p, x in v.items()} for k, v in data["errors"].items()}
        except (ValueError, KeyError, AttributeError, TypeError) as exc:
            raise InputError(None, f"not a simulated calibration table ({exc})") from exc
        self._drain()
        self.errors = errors
        if self._renderer is not None:
            self._renderer.model = self.effective_model()
            self._renderer._ctx = None

    def write_calibration(self) -> None:
        """Persist the current table (the EEPROM write of the real device)."""
        self.written_table = self.calibration_table()
