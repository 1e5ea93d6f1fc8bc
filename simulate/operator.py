"""A simulated operator who walks a camera to the standpoints by following the station's guidance.

The operator sees only what the screen says (`acquire.guidance.Guidance`: step back so many cm,
walk round so many degrees, turn, tilt), never the truth, so a guided session with this operator
tests the guidance loop end to end. Human imperfections: reaction time, walking takes time,
moves overshoot (a fraction of the step, more for long steps), footing errors, and hand tremor on
every frame. The pose is the depth camera's, relative to the board (board frame: origin at the
outer top-left corner, x along the columns, y along the rows (down), z into the board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.geometry import look_at, rodrigues


class Instructions(Protocol):
    """What the operator reads off the station's screen (`depthstation.acquire.guidance.Guidance`
    satisfies it; the simulator cannot import the acquisition, which stands above it)."""

    @property
    def seen(self) -> bool: ...
    @property
    def in_tolerance(self) -> bool: ...
    @property
    def distance_ok(self) -> bool: ...
    @property
    def inclination_ok(self) -> bool: ...
    @property
    def aim_ok(self) -> bool: ...
    @property
    def delta_distance_m(self) -> float: ...  # + = step back
    @property
    def delta_azimuth_deg(self) -> float: ...  # + = walk round to your left
    @property
    def aim_yaw_deg(self) -> float: ...  # + = turn the camera right
    @property
    def aim_pitch_deg(self) -> float: ...  # + = tilt the camera down

FloatArray = NDArray[np.float64]


def _rot_y(deg: float) -> FloatArray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _rot_x(deg: float) -> FloatArray:
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


@dataclass
class Stance:
    """Where the operator stands and how the camera is held: range to the board centre (m),
    azimuth round the board normal (degrees, + = operator's left), camera height above the
    board centre (m), and aim offsets (degrees: + yaw = turned right, + pitch = tilted down)."""

    range_m: float = 1.5
    azimuth_deg: float = 0.0
    height_m: float = 0.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    def as_array(self) -> FloatArray:
        return np.array([self.range_m, self.azimuth_deg, self.height_m, self.yaw_deg, self.pitch_deg])

    @classmethod
    def from_array(cls, a: FloatArray) -> Stance:
        return cls(*(float(x) for x in a))

    def camera_to_board(self, board: Board) -> FloatArray:
        """4x4 pose of the depth camera in the board frame (OpenCV axes)."""
        c = board.center
        a = math.radians(self.azimuth_deg)
        eye = c + np.array([-self.range_m * math.sin(a), -self.height_m, -self.range_m * math.cos(a)])
        pose = look_at(eye, c, up=(0.0, -1.0, 0.0))
        pose[:3, :3] = pose[:3, :3] @ _rot_y(self.yaw_deg) @ _rot_x(-self.pitch_deg)
        return pose


@dataclass
class OperatorSettings:
    """Imperfections of the simulated operator (SI units; degrees for angles)."""

    reaction_s: float = 0.4  # from reading the screen to starting to move
    walk_speed_m_s: float = 0.6
    turn_speed_deg_s: float = 30.0
    overshoot: float = 0.25  # mean overshoot as a share of each step
    footing_m: float = 0.01  # random error of each step
    footing_deg: float = 0.7
    tremor_m: float = 0.0015  # hand tremor per frame (std per axis)
    tremor_deg: float = 0.08
    update_hz: float = 30.0  # how often the held pose changes while walking (each change is a re-render)
    still_update_hz: float = 0.0  # the same while standing still; 0 = the tremor is drawn once per stop,
    # so a camera held still shows one view (the simulated camera then only draws per-frame noise)


@dataclass
class SimulatedOperator:
    """Moves a simulated camera in response to guidance; call `step(guidance, t_s)` once per frame."""

    board: Board
    stance: Stance = field(default_factory=Stance)
    settings: OperatorSettings = field(default_factory=OperatorSettings)
    seed: int = 0
    _rng: np.random.Generator = field(init=False)
    _move: tuple[float, float, FloatArray, FloatArray] | None = field(default=None, init=False)
    _next_look_s: float = field(default=0.0, init=False)
    moves: int = field(default=0, init=False)
    _held: tuple[float, FloatArray] | None = field(default=None, init=False)
    _held_still: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def pose(self, t_s: float) -> FloatArray:
        """Camera-to-board pose at time t (the walk in progress, plus tremor), held for
        1 / `update_hz` seconds while walking, and for 1 / `still_update_hz` (by default the
        whole stop) while standing, so a ray-casting renderer is not asked for a new view every
        frame. Time is the caller's (frame time), never the wall clock: a seed repeats a run."""
        st = self._current(t_s)
        s = self.settings
        still = self._move is None
        if self._held is not None:
            hz = s.still_update_hz if (still and self._held_still) else s.update_hz
            if hz <= 0 or t_s < self._held[0] + 1.0 / hz - 1e-9:
                return self._held[1].copy()
        pose = st.camera_to_board(self.board)
        if s.tremor_m > 0 or s.tremor_deg > 0:
            pose[:3, 3] += self._rng.normal(0.0, s.tremor_m, 3)
            pose[:3, :3] = pose[:3, :3] @ rodrigues(np.radians(self._rng.normal(0.0, s.tremor_deg, 3)))
        self._held = (t_s, pose.copy())
        self._held_still = still
        return pose

    def board_to_camera(self, t_s: float) -> FloatArray:
        """The same pose the other way round (p_cam = T p_board), as a renderer wants it."""
        return np.asarray(np.linalg.inv(self.pose(t_s)), dtype=np.float64)

    def _current(self, t_s: float) -> Stance:
        if self._move is None:
            return self.stance
        t0, t1, a, b = self._move
        if t_s >= t1:
            self.stance = Stance.from_array(b)
            self._move = None
            return self.stance
        f = (t_s - t0) / (t1 - t0)
        f = 0.5 - 0.5 * math.cos(math.pi * f)  # smooth start and stop
        return Stance.from_array(a + f * (b - a))

    @property
    def moving(self) -> bool:
        return self._move is not None

    def lapse(self, t_s: float, *, range_m: float = 0.0, azimuth_deg: float = 0.0, yaw_deg: float = 0.0,
              pitch_deg: float = 0.0, duration_s: float = 0.5) -> None:
        """An unprompted move (attention lapses, a step to keep balance) by these offsets from the
        current stance, whatever the screen says: what the station's check of a take must catch."""
        self._current(t_s)
        cur = self.stance.as_array()
        goal = cur + np.array([range_m, azimuth_deg, 0.0, yaw_deg, pitch_deg])
        self._move = (t_s, t_s + max(duration_s, 1e-3), cur, goal)
        self._held_still = False
        self._next_look_s = t_s + duration_s + self.settings.reaction_s
        self.moves += 1

    def step(self, guidance: Instructions, t_s: float) -> None:
        """Read the screen (when not walking and the reaction time has passed) and start a move."""
        self._current(t_s)
        if self._move is not None or t_s < self._next_look_s:
            return
        s = self.settings
        goal = self.stance.as_array().copy()
        rng = self._rng
        if not guidance.seen:
            # lost the board: face the board again
            goal[3] = goal[4] = 0.0
        elif guidance.in_tolerance:
            return  # hold still (tremor only)
        else:
            dd = float(guidance.delta_distance_m)
            daz = float(guidance.delta_azimuth_deg)
            if not guidance.distance_ok:
                over = 1.0 + max(0.0, rng.normal(s.overshoot, s.overshoot / 3)) * min(1.0, abs(dd) / 0.2)
                goal[0] += dd * over + rng.normal(0.0, s.footing_m)
            if not guidance.inclination_ok:
                over = 1.0 + max(0.0, rng.normal(s.overshoot, s.overshoot / 3)) * min(1.0, abs(daz) / 5.0)
                goal[1] += daz * over + rng.normal(0.0, s.footing_deg)
                goal[3] = goal[4] = 0.0  # walking round, then facing the board again
            elif not guidance.aim_ok:
                goal[3] += float(guidance.aim_yaw_deg)
                goal[4] += float(guidance.aim_pitch_deg)
        goal[0] = max(goal[0], 0.3)
        cur = self.stance.as_array()
        walk = abs(goal[0] - cur[0]) + math.radians(abs(goal[1] - cur[1])) * cur[0]
        turn = float(np.abs(goal[3:] - cur[3:]).max())
        duration = max(0.3, walk / s.walk_speed_m_s, turn / s.turn_speed_deg_s)
        self._move = (t_s, t_s + duration, cur, goal)
        self._held_still = False
        self._next_look_s = t_s + duration + s.reaction_s
        self.moves += 1
