"""TUM RGB-D folders (depth PNGs + depth.txt / associations + an intrinsics file) as recordings.

Why this format: the TUM RGB-D layout is what SLAM pipelines (ORB-SLAM3, RTAB-Map) consume, so a
scan study often starts from it.
"""

from __future__ import annotations

import json
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
    """camera.json-like (our keys or fx/fy/cx/cy, optional depth_units_m / depth_scale) or a text
    file `fx fy cx cy [width height] [depth_factor]`. Returns (intrinsics, depth units or None)."""
    if path.suffix == ".json":
        try:
            d: dict[str, Any] = json.loads(read_text(path, "intrinsics JSON"))
        except json.JSONDecodeError as exc:
            raise InputError(path, f"broken JSON ({exc})") from exc
        if "depth_intrinsics" in d:
            info = StreamInfo.from_dict(d)
            return info.depth_intrinsics, info.depth_units_m
        d = d.get("depth", d)
        units = d.get("depth_units_m", d.get("depth_scale"))
        if "factor" in d:
            units = 1.0 / float(d["factor"])
        try:
            return Intrinsics.from_dict(d), None if units is None else float(units)
        except KeyError as exc:
            raise InputError(path, f"intrinsics lack {exc}") from exc
    vals: list[float] = []
    for line in read_text(path, "intrinsics file").splitlines():
        s = line.split("#", 1)[0].strip()
        if s:
            vals += [float(x) for x in s.replace(",", " ").split()]
    if len(vals) < 4:
        raise InputError(path, "expected 'fx fy cx cy [width height] [depth_factor]'")
    fx, fy, cx, cy = vals[:4]
    w, h = (int(vals[4]), int(vals[5])) if len(vals) >= 6 else (0, 0)
    units = 1.0 / vals[6] if len(vals) >= 7 else None
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
    for line in read_text(assoc, "TUM association file").splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        # depth.txt: "t depth/x.png"; associations: "t_rgb rgb/x.png t_depth depth/y.png" (either order)
        pairs = [(parts[k], parts[k + 1]) for k in range(0, len(parts) - 1, 2)]
        pick = next((p for p in pairs if "depth" in p[1]), pairs[-1] if len(pairs) == 1 else None)
        if pick is None:
            raise InputError(assoc, f"cannot tell the depth file in line {s!r}")
        stamps.append(float(pick[0]))
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
    info = StreamInfo(depth_intrinsics=intr, color_intrinsics=None,
                      depth_units_m=units if units is not None else 1.0 / TUM_DEPTH_FACTOR)
    return TumSequence(path, files, stamps, info, name=path.name, metadata={"intrinsics_file": str(ipath)})
