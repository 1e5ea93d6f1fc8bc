"""Pure guidance: from the measured board pose to 'how to move' against the next target.

Everything here works on numbers (poses, timestamps, fill rates), so the guided loop, the
operator's panel and the simulated operator all read the same `Guidance` record.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from depthstation.core.protocol import Standpoint, Tolerances

# Where the board centre should sit in the image: within this share of the half-width of centre.
AIM_TOLERANCE = 0.25


def signed_target_deg(target: Standpoint) -> float:
    """The target inclination signed by side (+ = operator's left of the board normal)."""
    return target.inclination_deg if target.side == "left" else -target.inclination_deg


@dataclass(frozen=True)
class Guidance:
    """What the screen says for one frame, and the numbers behind it (for the simulated operator)."""

    seen: bool
    target: Standpoint
    distance_m: float | None = None
    inclination_deg: float | None = None
    azimuth_deg: float | None = None
    delta_distance_m: float = 0.0  # + = step back
    delta_azimuth_deg: float = 0.0  # + = walk round to your left
    aim_yaw_deg: float = 0.0  # + = turn the camera right to centre the board
    aim_pitch_deg: float = 0.0  # + = tilt the camera down
    in_tolerance: bool = False
    distance_ok: bool = False
    inclination_ok: bool = False
    aim_ok: bool = False
    still: bool = False
    fill_rate: float | None = None
    messages: tuple[str, ...] = ()

    @property
    def text(self) -> str:
        return "; ".join(self.messages)


def _cm(x_m: float) -> str:
    return f"{abs(x_m) * 100:.0f} cm"


def guide(target: Standpoint, tol: Tolerances, *, distance_m: float | None, inclination_deg: float | None,
          azimuth_deg: float | None, center_px: tuple[float, float] | None = None,
          image_size: tuple[int, int] | None = None, fx: float | None = None,
          still: bool = False, fill: float | None = None) -> Guidance:
    """Compare the measured standpoint with the target and say how to move.

    Distance is the board centre's z-depth, so 'step back' moves along the viewing ray. The
    inclination changes only by walking round the board (an arc at the current distance), after
    which the operator turns to face it again; the aim hint keeps the board in the middle of
    the image, where the depth camera sees it whole.
    """
    if distance_m is None or inclination_deg is None or azimuth_deg is None:
        return Guidance(False, target, fill_rate=fill,
                        messages=("board not found: point the camera at the whole board",))
    want_az = signed_target_deg(target)
    dd = target.distance_m - distance_m
    # at 0 degrees the side does not matter; at any other target the side does
    daz = want_az - azimuth_deg
    if target.inclination_deg == 0.0:
        daz = -azimuth_deg
    dist_ok = abs(dd) <= tol.distance_m
    inc_ok = abs(daz) <= tol.inclination_deg
    yaw = pitch = 0.0
    aim_ok = True
    if center_px is not None and image_size is not None and fx is not None:
        w, h = image_size
        du = center_px[0] - (w - 1) / 2
        dv = center_px[1] - (h - 1) / 2
        yaw = math.degrees(math.atan2(du, fx))
        pitch = math.degrees(math.atan2(dv, fx))
        aim_ok = abs(du) <= AIM_TOLERANCE * w / 2 and abs(dv) <= AIM_TOLERANCE * h / 2
    msgs: list[str] = []
    head = (f"{distance_m:.2f} m -> {target.distance_m:.2f} m, "
            f"{inclination_deg:.1f}° -> {target.inclination_deg:.1f}°")
    if not dist_ok:
        msgs.append(f"step {'back' if dd > 0 else 'closer'} {_cm(dd)}")
    if not inc_ok:
        arc = math.radians(abs(daz)) * distance_m
        msgs.append(f"walk {_cm(arc)} round the board to your {'left' if daz > 0 else 'right'} "
                    f"({abs(daz):.0f}°) and face it again")
    if not aim_ok:
        if abs(yaw) > 1.0:
            msgs.append(f"turn {abs(yaw):.0f} degrees {'right' if yaw > 0 else 'left'}")
        if abs(pitch) > 1.0:
            msgs.append(f"tilt {abs(pitch):.0f} degrees {'down' if pitch > 0 else 'up'}")
    in_tol = dist_ok and inc_ok and aim_ok
    if in_tol:
        msgs.append("in position: hold still" if not still else "in position and still: recording")
    return Guidance(True, target, distance_m, inclination_deg, azimuth_deg, dd, daz, yaw, pitch,
                    in_tol, dist_ok, inc_ok, aim_ok, still, fill, (head, *msgs))


@dataclass
class StillnessTracker:
    """Pose stable over `still_seconds`, judged on frame timestamps (not wall time).

    Judged on the board as the camera sees it (`BoardPose.stillness_points`: the centre, then the
    grid's outer corners, camera frame; or the centre alone): every point within `translation_m`
    and the centre's bearing within `rotation_deg` of the latest frame. The board's own tilt from
    EPnP is not compared as an angle: it jitters by tenths of a degree at a few metres even for a
    camera on a tripod; at the corners that is millimetres, while a walk round the board (which
    leaves the centre in place) moves them by centimetres.

    The latest frame must also sit where the camera has been standing: within half the tolerances
    of the window's median centre. Without this, the first frames of a move (a step starts
    slowly: 7 mm in its first frame) still agree with a window of frames taken standing, and
    recording started just as the operator stepped off (standpoint_01 of the demo, recorded
    while walking from 0.95 to 1.02 m).
    """

    seconds: float
    translation_m: float
    rotation_deg: float
    grace_frames: int = 3  # a detection missed on this many frames in a row does not restart the window
    _samples: deque[tuple[int, NDArray[np.float64]]] = field(default_factory=deque)
    _missed: int = 0

    @classmethod
    def from_tolerances(cls, tol: Tolerances) -> StillnessTracker:
        return cls(tol.still_seconds, tol.still_translation_m, tol.still_rotation_deg)

    def reset(self) -> None:
        self._samples.clear()

    def _agrees(self, a: NDArray[np.float64], b: NDArray[np.float64], share: float = 1.0) -> bool:
        return points_agree(a, b, share * self.translation_m, share * self.rotation_deg)

    def update(self, t_ns: int, center: NDArray[np.float64] | None) -> bool:
        """Add one frame's board centre, or centre then corners (camera frame; None = board lost,
        which restarts the window); True when the board stayed put for the whole window."""
        if center is None:
            self._missed += 1
            if self._missed > self.grace_frames:
                self._samples.clear()
            return False
        self._missed = 0
        c = np.asarray(center, dtype=np.float64)
        self._samples.append((t_ns, c))
        # keep the longest run of recent samples that all agree with the latest one
        keep = 0
        for _, c_i in reversed(self._samples):
            if not self._agrees(c_i, c):
                break
            keep += 1
        while len(self._samples) > keep:
            self._samples.popleft()
        # no need to remember more than the window (one sample at or before its start)
        while len(self._samples) > 1 and t_ns - self._samples[1][0] >= self.seconds * 1e9:
            self._samples.popleft()
        if (t_ns - self._samples[0][0]) / 1e9 < self.seconds - 1e-6:
            return False
        # settled: the latest frame has not started to leave where the camera stood in the window
        median = np.median(np.stack([c_i for _, c_i in self._samples]), axis=0)
        return self._agrees(median, c, 0.5)


def points_agree(a: NDArray[np.float64], b: NDArray[np.float64], translation_m: float,
                 rotation_deg: float) -> bool:
    """Two views of the board (centre, or centre then corners, camera frame; 3 or k x 3) agree:
    every point within `translation_m` and the centre seen within `rotation_deg` of the same
    bearing. The stillness measure of the tracker and of a recording."""
    pa, pb = np.reshape(a, (-1, 3)), np.reshape(b, (-1, 3))
    if float(np.linalg.norm(pa - pb, axis=1).max()) > translation_m:
        return False
    ca, cb = pa[0], pb[0]
    cos = float(np.dot(ca, cb) / (np.linalg.norm(ca) * np.linalg.norm(cb)))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos)))) <= rotation_deg


def end_of_range(fill_rates: list[float], threshold: float, frames: int = 5) -> bool:
    """The board's depth fill rate stayed below the protocol's threshold over the last frames:
    the camera has reached the end of its range on this trajectory (paper §3.1.1)."""
    if len(fill_rates) < frames:
        return False
    return all(f < threshold for f in fill_rates[-frames:])
