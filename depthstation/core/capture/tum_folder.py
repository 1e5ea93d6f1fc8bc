"""TUM RGB-D folders (depth PNGs + depth.txt / associations + an intrinsics file) as recordings.

Why this format: the TUM RGB-D layout is what SLAM pipelines (ORB-SLAM3, RTAB-Map) consume, so a
scan study often starts from it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from depthstation.core.camera_model import Intrinsics, StreamInfo
from depthstation.core.capture.recording import Recording, size_problem
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.text_files import read_text

TUM_DEPTH_FACTOR = 5000.0  # TUM RGB-D depth PNGs: 5000 counts per metre
_INTRINSICS_NAMES = ("camera.json", "intrinsics.json", "intrinsics.txt", "camera.txt", "calibration.txt")
_ASSOC_NAMES = ("associations.txt", "association.txt", "associate.txt", "depth.txt")


def _read_intrinsics(path: Path) -> tuple[Intrinsics, float | None]:
    """camera.json-like (our keys or fx/fy/cx/cy, optional depth_units_m / depth_scale in metres per
    count, or `factor` in counts per metre) or a text file `fx fy cx cy [width height] [depth_factor]`.
    Returns (intrinsics, depth units or None). Every value is checked: a bad one is bad input
    naming the file and the key (it was a ZeroDivisionError, or a grid in kilometres)."""
    try:
        if path.suffix == ".json":
            return _read_intrinsics_json(path)
        return _read_intrinsics_text(path)
    except (ValueError, TypeError) as exc:  # Intrinsics' own checks: focal lengths, principal point
        raise InputError(path, str(exc)) from exc


def _units(path: Path, key: str, value: Any) -> float:
    """Metres per depth count, within what a depth camera can mean."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"{key} must be a number, got {value!r}")
    if key in ("factor", "depth_factor"):
        if value <= 0:
            raise InputError(path, f"{key} must be depth counts per metre (e.g. 5000 for TUM RGB-D, 1000 "
                                   f"for millimetres), got {value!r}")
        units = 1.0 / float(value)
    else:
        units = float(value)
    if not 1e-6 <= units <= 0.1:
        hint = (f" (a count-per-metre value, Open3D's depth_scale? write depth_units_m = 1/{value:g})"
                if key != "factor" and units > 1 else "")
        raise InputError(path, f"{key} {value!r} gives {units:g} m per depth count: metres per count must "
                               f"lie in 1e-6 to 0.1{hint}")
    return units


def _read_intrinsics_json(path: Path) -> tuple[Intrinsics, float | None]:
    try:
        d: dict[str, Any] = json.loads(read_text(path, "intrinsics JSON"))
    except json.JSONDecodeError as exc:
        raise InputError(path, f"broken JSON ({exc})") from exc
    if not isinstance(d, dict):
        raise InputError(path, "expected a JSON object of intrinsics")
    if "depth_intrinsics" in d:
        info = StreamInfo.from_dict(d)
        return info.depth_intrinsics, _units(path, "depth_units_m", info.depth_units_m)
    d = d.get("depth", d)
    given = {key: _units(path, key, d[key]) for key in ("depth_units_m", "depth_scale", "factor") if key in d}
    units = next(iter(given.values()), None)
    if units is not None and any(not math.isclose(u, units, rel_tol=1e-6) for u in given.values()):
        raise InputError(path, "the depth units disagree: " + ", ".join(f"{k} {d[k]!r}" for k in given)
                         + " (keep one)")
    try:
        return Intrinsics.from_dict(d), units
    except KeyError as exc:
        raise InputError(path, f"intrinsics lack {exc}") from exc


def _read_intrinsics_text(path: Path) -> tuple[Intrinsics, float | None]:
    vals: list[float] = []
    for n, line in enumerate(read_text(path, "intrinsics file").splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        for x in s.replace(",", " ").split():
            try:
                vals.append(float(x))
            except ValueError:
                raise InputError(path, f"line {n}: {x!r} is no number (expected 'fx fy cx cy [width height] "
                                       "[depth_factor]'; comments start with #)") from None
    if len(vals) < 4:
        raise InputError(path, "expected 'fx fy cx cy [width height] [depth_factor]'")
    if not all(math.isfinite(v) for v in vals):
        raise InputError(path, "holds a value that is not a finite number")
    fx, fy, cx, cy = vals[:4]
    if len(vals) >= 6 and not all(v > 0 and v == int(v) for v in vals[4:6]):
        raise InputError(path, f"width and height must be whole positive numbers of pixels, got "
                               f"{vals[4]:g} {vals[5]:g}")
    w, h = (int(vals[4]), int(vals[5])) if len(vals) >= 6 else (0, 0)
    units = _units(path, "depth_factor", vals[6]) if len(vals) >= 7 else None
    return Intrinsics(w, h, fx, fy, cx, cy), units


class TumSequence(Recording):
    """A TUM RGB-D style folder: depth PNGs in time order (picklable: workers reopen it by value)."""

    def __init__(self, path: Path, depth_files: list[Path], timestamps_s: list[float], info: StreamInfo,
                 name: str = "", metadata: dict[str, Any] | None = None) -> None:
        super().__init__(name or Path(path).name, Path(path), info, dict(metadata or {}), len(depth_files),
                         {"depth": len(depth_files)})
        self.depth_files = list(depth_files)
        self.timestamps_s = list(timestamps_s)

    def _iter(self, start: int) -> Iterator[FrameSet]:
        for i in range(start, len(self.depth_files)):
            f = self.depth_files[i]
            if not f.is_file():
                raise InputError(f, "listed in the association file but not found")
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != np.uint16 or img.ndim != 2:
                raise InputError(f, "not a 16-bit single-channel depth PNG")
            where = self.metadata.get("intrinsics_file", "intrinsics")
            problem = size_problem(img, self.info.depth_intrinsics, f"the intrinsics ({where}) give")
            if problem:
                raise InputError(f, problem)
            t_ns = round(self.timestamps_s[i] * 1e9)
            yield FrameSet(index=i, timestamp_ns=t_ns, depth=img.astype(np.uint16))


def is_tum_folder(path: Path) -> bool:
    """A folder with depth.txt or an associations file."""
    return path.is_dir() and any((path / n).is_file() for n in _ASSOC_NAMES)


def open_tum_folder(path: Path, intrinsics: Path | None = None) -> TumSequence:
    """Read the list of depth frames and their time stamps; image size from the first PNG."""
    path = Path(path)
    assoc = next((path / n for n in _ASSOC_NAMES if (path / n).is_file()), None)
    if assoc is None:
        raise InputError(path, f"no {' / '.join(_ASSOC_NAMES)} in this TUM RGB-D folder")
    stamps: list[float] = []
    files: list[Path] = []
    first_line: dict[float, int] = {}
    for n, line in enumerate(read_text(assoc, "TUM association file").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        # depth.txt: "t depth/x.png"; associations: "t_rgb rgb/x.png t_depth depth/y.png" (either order)
        pairs = [(parts[k], parts[k + 1]) for k in range(0, len(parts) - 1, 2)]
        pick = next((p for p in pairs if "depth" in p[1]), pairs[-1] if len(pairs) == 1 else None)
        if pick is None:
            raise InputError(assoc, f"cannot tell the depth file in line {s!r}")
        try:
            t = float(pick[0])
        except ValueError:
            raise InputError(assoc, f"line {n}: {pick[0]!r} is no time stamp (seconds)") from None
        if t in first_line:  # two images at one time: one of them would be posed with the other's pose
            raise InputError(assoc, f"lines {first_line[t]} and {n} have the same time stamp {pick[0]} "
                                    "(two depth images at one time: one of them is misnamed)")
        first_line[t] = n
        stamps.append(t)
        files.append(path / pick[1])
    if not files:
        raise InputError(assoc, "no frames listed")
    ipath = intrinsics or next((path / n for n in _INTRINSICS_NAMES if (path / n).is_file()), None)
    if ipath is None:
        raise InputError(path, f"no intrinsics file ({', '.join(_INTRINSICS_NAMES)})")
    intr, units = _read_intrinsics(Path(ipath))
    if not files[0].is_file():
        raise InputError(files[0], f"listed in {assoc.name} but not found")
    first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise InputError(files[0], "cannot read depth PNG")
    if intr.width == 0 or intr.height == 0:
        intr = Intrinsics(first.shape[1], first.shape[0], intr.fx, intr.fy, intr.ppx, intr.ppy,
                          intr.model, intr.coeffs)
    elif first.shape[:2] != (intr.height, intr.width):
        raise InputError(Path(ipath), f"gives {intr.width}x{intr.height} pixels, but the depth images are "
                                      f"{first.shape[1]}x{first.shape[0]} ({files[0].name})")
    try:
        intr.check()  # focal lengths, principal point: also of a text file without an image size
    except ValueError as exc:
        raise InputError(Path(ipath), str(exc)) from exc
    info = StreamInfo(depth_intrinsics=intr, color_intrinsics=None,
                      depth_units_m=units if units is not None else 1.0 / TUM_DEPTH_FACTOR)
    return TumSequence(path, files, stamps, info, name=path.name, metadata={"intrinsics_file": str(ipath)})
