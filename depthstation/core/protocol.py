"""Capture protocols (TOML): board, streams, standpoint plan, tolerances, warm-up and calibration."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from depthstation.core.board import Board
from depthstation.core.errors import InputError, ProtocolError
from depthstation.core.text_files import read_text
from depthstation.core.tomlcompat import tomllib


def _protocol_dir() -> Path:
    """`protocols/`: inside the installed package (a wheel), or at the top of the checkout (an editable
    install maps `depthstation.protocols` there, and a data folder has no module to locate it by)."""
    package = Path(__file__).resolve().parent.parent
    installed = package / "protocols"
    return installed if installed.is_dir() else package.parent / "protocols"


PROTOCOL_DIR = _protocol_dir()
# librealsense's D400 visual presets (rs2_rs400_visual_preset), as the device names them
D400_PRESETS = ("Custom", "Default", "Hand", "High Accuracy", "High Density", "Medium Density",
                "Remove IR Pattern")
# a plan is walked by an operator: the paper's is 65 standpoints; thousands are a typo (a step in
# millimetres, a range in millimetres) and would take memory and days
MAX_STANDPOINTS = 1000
MODEL_NAME = re.compile(r"D\d{3}[A-Z]?", re.IGNORECASE)  # a RealSense model as Intel names it
MAX_FRAMES_PER_STANDPOINT = 100_000  # an hour at 30 fps
MAX_WIDTH, MAX_HEIGHT, MAX_FPS = 1920, 1080, 300  # above any RealSense D400 stream profile


def preset_known(name: str) -> bool:
    """Whether `name` is a D400 visual preset, spelt as the device compares it (case, '_' for ' ')."""
    wanted = name.strip().lower().replace("_", " ")
    return any(wanted == p.lower() for p in D400_PRESETS)


@dataclass(frozen=True)
class Streams:
    width: int = 1280
    height: int = 720
    fps: int = 30
    depth: bool = True
    color: bool = True
    infrared: bool = False
    preset: str = "Default"
    emitter: bool = True


@dataclass(frozen=True)
class Standpoint:
    """One target of the plan: a distance (board centre z-depth) at an inclination."""

    name: str
    trajectory: int
    distance_m: float
    inclination_deg: float
    side: str = "left"  # which way the operator has walked round the board's normal


@dataclass(frozen=True)
class Plan:
    frames_per_standpoint: int = 150
    start_distance_m: float = 1.0
    step_m: float = 0.4
    max_distance_m: float = 6.0
    inclinations_deg: tuple[float, ...] = (0.0, 15.0, 30.0, 45.0, 60.0)
    side: str = "left"

    def standpoints(self) -> list[Standpoint]:
        """Every target in capture order: trajectory by trajectory, distance growing."""
        out: list[Standpoint] = []
        n = 0
        for t, inc in enumerate(self.inclinations_deg):
            d = self.start_distance_m
            while d <= self.max_distance_m + 1e-9:
                n += 1
                out.append(Standpoint(f"standpoint_{n:02d}", t, round(d, 4), float(inc), self.side))
                d += self.step_m
        return out


@dataclass(frozen=True)
class Tolerances:
    distance_m: float = 0.05
    inclination_deg: float = 3.0
    still_seconds: float = 1.0
    still_translation_m: float = 0.01
    still_rotation_deg: float = 0.5
    end_fill_rate: float = 0.2


@dataclass(frozen=True)
class Warmup:
    min_minutes: float = 60.0
    max_slope_c_per_min: float = 0.05
    window_minutes: float = 5.0
    max_minutes: float = 180.0


@dataclass(frozen=True)
class Calibration:
    on_chip: bool = True
    tare: bool = False
    tare_distance_m: float | None = None  # from the camera's front glass to the flat target
    min_health: float = 0.25  # on-chip: |health| above this suggests applying the new table
    # tare: apply when the relative depth error before exceeds this (fraction) and the new table
    # lowers it; our choice (Intel gives no tare bands): about a tape measure's 2 mm at 1 m
    tare_min_error: float = 0.002


@dataclass(frozen=True)
class Device:
    """The camera model the protocol is written for; a live camera of another model is refused."""

    model: str = "D455"


@dataclass(frozen=True)
class Protocol:
    name: str
    description: str = ""
    board: Board = field(default_factory=Board)
    streams: Streams = field(default_factory=Streams)
    plan: Plan = field(default_factory=Plan)
    tolerances: Tolerances = field(default_factory=Tolerances)
    warmup: Warmup = field(default_factory=Warmup)
    calibration: Calibration = field(default_factory=Calibration)
    source: str | None = None
    device: Device = field(default_factory=Device)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["board"] = self.board.to_dict()
        d.pop("source", None)
        return d


def _table(cls: type, data: Any, key: str, source: Path | None) -> Any:
    """Build one dataclass from a TOML table, naming the offending key on error."""
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ProtocolError(source, f"[{key}] must be a table")
    fields = dataclasses.fields(cls)
    names = {f.name for f in fields}
    kwargs: dict[str, Any] = {}
    for k, v in data.items():
        if k not in names:
            raise ProtocolError(source, f"unknown key '{key}.{k}'")
        default = getattr(cls(), k)
        try:
            if isinstance(default, bool):
                if not isinstance(v, bool):
                    raise TypeError("expected true or false")
                kwargs[k] = v
            elif isinstance(default, int):
                if isinstance(v, bool) or not isinstance(v, int):
                    raise TypeError("expected an integer")
                kwargs[k] = v
            elif isinstance(default, float) or (default is None and k.endswith("_m")):
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise TypeError("expected a number")
                kwargs[k] = float(v)
            elif isinstance(default, tuple):
                if not isinstance(v, list) or not all(isinstance(x, (int, float)) for x in v):
                    raise TypeError("expected a list of numbers")
                kwargs[k] = tuple(float(x) for x in v)
            else:
                if not isinstance(v, str):
                    raise TypeError("expected a string")
                kwargs[k] = v
        except TypeError as exc:
            raise ProtocolError(source, f"'{key}.{k}': {exc}, got {v!r}") from exc
    return cls(**kwargs)


# What a protocol must say itself: the board, the stream mode and the plan are what the study
# measures; a default there would run a plan nobody asked for. The other tables have defaults
# that only shape the guidance (tolerances, warm-up rule, calibration).
REQUIRED = {
    "board": (),  # its keys are Board's required ones
    "streams": ("width", "height", "fps"),
    "plan": ("frames_per_standpoint", "start_distance_m", "step_m", "max_distance_m", "inclinations_deg"),
}


def _positive(source: Path | None, table: Any, key: str, names: tuple[str, ...],
              allow_zero: bool = False) -> None:
    for n in names:
        v = getattr(table, n)
        if v is None:
            continue
        if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
            need = ">= 0" if allow_zero else "> 0"
            raise ProtocolError(source, f"'{key}.{n}' must be {need}, got {v}")


def protocol_from_dict(data: dict[str, Any], source: Path | None = None) -> Protocol:
    """Validate a parsed protocol; every error names the key."""
    known = {"name", "description", "board", "streams", "plan", "tolerances", "warmup", "calibration",
             "device"}
    for k in data:
        if k not in known:
            raise ProtocolError(source, f"unknown key '{k}'")
    if "name" not in data or not isinstance(data["name"], str):
        raise ProtocolError(source, "missing key 'name' (a string)")
    for table, keys in REQUIRED.items():
        if not isinstance(data.get(table), dict):
            raise ProtocolError(source, f"missing table [{table}]")
        missing = [k for k in keys if k not in data[table]]
        if missing:
            raise ProtocolError(source, f"missing key '{table}.{missing[0]}'")
    board_data = data["board"]
    board = Board.from_dict(board_data, source)
    proto = Protocol(
        name=data["name"],
        description=str(data.get("description", "")),
        board=board,
        streams=_table(Streams, data.get("streams"), "streams", source),
        plan=_table(Plan, data.get("plan"), "plan", source),
        tolerances=_table(Tolerances, data.get("tolerances"), "tolerances", source),
        warmup=_table(Warmup, data.get("warmup"), "warmup", source),
        calibration=_table(Calibration, data.get("calibration"), "calibration", source),
        source=None if source is None else str(source),
        device=_table(Device, data.get("device"), "device", source),
    )
    p = proto.plan
    if not 1 <= p.frames_per_standpoint <= MAX_FRAMES_PER_STANDPOINT:
        raise ProtocolError(source, f"'plan.frames_per_standpoint' must lie in 1.."
                                    f"{MAX_FRAMES_PER_STANDPOINT}, got {p.frames_per_standpoint}")
    for key in ("start_distance_m", "step_m", "max_distance_m"):
        if not math.isfinite(getattr(p, key)):
            raise ProtocolError(source, f"'plan.{key}' must be a finite number, got {getattr(p, key)}")
    if p.step_m <= 0:
        raise ProtocolError(source, "'plan.step_m' must be positive")
    if not 0 < p.start_distance_m <= p.max_distance_m:
        raise ProtocolError(source, "'plan.start_distance_m' must be positive and <= plan.max_distance_m")
    if any(not 0 <= a < 90 for a in p.inclinations_deg) or not p.inclinations_deg:
        raise ProtocolError(source, "'plan.inclinations_deg' must list angles in [0, 90)")
    if twice := sorted({a for a in p.inclinations_deg if p.inclinations_deg.count(a) > 1}):
        raise ProtocolError(source, f"'plan.inclinations_deg' lists {', '.join(f'{a:g}' for a in twice)} deg "
                                    "more than once (a typo for another angle?): list each inclination "
                                    "once; for more frames raise plan.frames_per_standpoint")
    if p.side not in ("left", "right"):
        raise ProtocolError(source, "'plan.side' must be 'left' or 'right'")
    per_trajectory = math.floor((p.max_distance_m - p.start_distance_m + 1e-9) / p.step_m) + 1
    if per_trajectory * len(p.inclinations_deg) > MAX_STANDPOINTS:
        raise ProtocolError(source, f"'plan' expands to {per_trajectory * len(p.inclinations_deg):.3g} "
                                    f"standpoints ({p.start_distance_m:g} to {p.max_distance_m:g} m by "
                                    f"{p.step_m:g} m, {len(p.inclinations_deg)} inclinations); at most "
                                    f"{MAX_STANDPOINTS}, an operator walks each one: check plan.step_m and "
                                    "plan.max_distance_m (metres)")
    if not MODEL_NAME.fullmatch(proto.device.model.strip()):
        raise ProtocolError(source, f"'device.model' {proto.device.model!r} is no RealSense model name "
                                    "(D455, D435I, D415, ...)")
    st = proto.streams
    if st.width <= 0 or st.height <= 0 or st.fps <= 0:
        raise ProtocolError(source, "'streams.width', 'streams.height' and 'streams.fps' must be positive")
    if st.width > MAX_WIDTH or st.height > MAX_HEIGHT or st.fps > MAX_FPS:
        raise ProtocolError(source, f"'streams' {st.width}x{st.height} at {st.fps} fps is beyond any "
                                    f"RealSense stream ({MAX_WIDTH}x{MAX_HEIGHT}, {MAX_FPS} fps at most)")
    if not st.depth:
        raise ProtocolError(source, "'streams.depth' must be true: depth is what the station measures")
    if not preset_known(st.preset):
        raise ProtocolError(source, f"'streams.preset' {st.preset!r} is no RealSense D400 preset "
                                    f"({', '.join(D400_PRESETS)})")
    _positive(source, proto.tolerances, "tolerances", ("distance_m", "inclination_deg", "still_seconds",
                                                       "still_translation_m", "still_rotation_deg"))
    if not 0 < proto.tolerances.end_fill_rate <= 1:
        raise ProtocolError(source, f"'tolerances.end_fill_rate' must lie in (0, 1], got "
                                    f"{proto.tolerances.end_fill_rate}")
    w = proto.warmup
    _positive(source, w, "warmup", ("min_minutes",), allow_zero=True)
    _positive(source, w, "warmup", ("max_slope_c_per_min", "window_minutes", "max_minutes"))
    if w.max_minutes < w.min_minutes:
        raise ProtocolError(source, f"'warmup.max_minutes' ({w.max_minutes}) must be >= warmup.min_minutes "
                                    f"({w.min_minutes})")
    if w.window_minutes > w.max_minutes:  # the slope is judged over a whole window: never, here
        raise ProtocolError(source, f"'warmup.window_minutes' ({w.window_minutes}) is longer than "
                                    f"warmup.max_minutes ({w.max_minutes}): the temperature could never be "
                                    "judged settled, and every warm-up would run to the maximum (set "
                                    f"window_minutes, {Warmup.window_minutes:g} when not given, to at most "
                                    "max_minutes)")
    c = proto.calibration
    _positive(source, c, "calibration", ("tare_distance_m",))
    _positive(source, c, "calibration", ("min_health", "tare_min_error"), allow_zero=True)
    if c.tare and c.tare_distance_m is None:
        raise ProtocolError(source, "'calibration.tare_distance_m' is missing: tare needs the target's "
                                    "distance from the camera's front glass (metres)")
    return proto


def check_for_acquisition(proto: Protocol) -> None:
    """What a guided capture needs beyond a valid protocol (a simulated session without colour is
    fine): colour, since the guidance finds the board in the colour image."""
    if not proto.streams.color:
        raise ProtocolError(proto.source, "'streams.color' must be true for acquire: the guidance finds "
                                          "the board in the colour image")


def drop_none(d: dict[str, Any]) -> dict[str, Any]:
    """A stored protocol without its unset (null) keys, which the TOML form leaves out."""
    return {k: drop_none(v) if isinstance(v, dict) else v for k, v in d.items() if v is not None}


def load_protocol(path_or_name: str | Path) -> Protocol:
    """A protocol from a TOML path or the name of one in `protocols/` (e.g. 'checkerboard-d455')."""
    if not str(path_or_name).strip():
        raise ProtocolError(None, "--protocol is empty: give a protocol name (as checkerboard-d455) or a "
                                  "TOML path")
    p = Path(path_or_name)
    if not p.exists() and not p.suffix:
        candidate = PROTOCOL_DIR / f"{path_or_name}.toml"
        if candidate.exists():
            p = candidate
    if p.is_dir():
        raise ProtocolError(p, "is a folder, not a protocol TOML")
    if not p.is_file():
        raise ProtocolError(p, "protocol file not found")
    try:
        data = tomllib.loads(read_text(p, "protocol TOML"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ProtocolError(p, f"not valid TOML ({exc})") from exc
    return protocol_from_dict(data, p)


def load_board(path: str | Path) -> Board:
    """A board from a board JSON or from the [board] table of a protocol TOML."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "board file not found")
    if p.suffix.lower() == ".toml":  # a capture protocol: its [board] table
        try:
            data = tomllib.loads(read_text(p, "protocol TOML"))
            table = data.get("board")
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputError(p, f"not valid TOML ({exc})") from exc
        if not isinstance(table, dict):
            raise InputError(p, "has no [board] table")
        if set(data) - {"board"}:  # a whole protocol: all of it valid, or a typo in its plan passes unseen
            return protocol_from_dict(data, p).board
        return Board.from_dict(table, p)
    try:
        data = json.loads(read_text(p, "board JSON"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(p, f"not a board JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(p, "not a board JSON (expected an object)")
    return Board.from_dict(data, p)
