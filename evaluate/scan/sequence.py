"""Opening the depth sequence of a scan study: our captures via the capture reader, or a TUM RGB-D
folder (depth PNGs + depth.txt / associations + an intrinsics file), read here.

Why a reader here: the TUM RGB-D layout is what SLAM pipelines (ORB-SLAM3) consume, so a study
often starts from it; the capture reader covers MCAP, .bag, .db3 and our PNG standpoint folders.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from depthstation.camera import Intrinsics, StreamInfo
from depthstation.errors import InputError
from depthstation.frames import FrameSet

TUM_DEPTH_FACTOR = 5000.0  # TUM RGB-D depth PNGs: 5000 counts per metre
_INTRINSICS_NAMES = ("camera.json", "intrinsics.json", "intrinsics.txt", "camera.txt", "calibration.txt")
_ASSOC_NAMES = ("associations.txt", "association.txt", "associate.txt", "depth.txt")


class FrameSource(Protocol):
    """What the study needs of a sequence (a `depthstation.capture.reader.Recording` fits)."""

    name: str
    info: StreamInfo

    @property
    def frame_count(self) -> int | None: ...

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]: ...


def _read_intrinsics(path: Path) -> tuple[Intrinsics, float | None]:
    """camera.json-like (our keys or fx/fy/cx/cy, optional depth_units_m / depth_scale) or a text
    file `fx fy cx cy [width height] [depth_factor]`. Returns (intrinsics, depth units or None)."""
    if path.suffix == ".json":
        try:
            d: dict[str, Any] = json.loads(path.read_text())
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
    for line in path.read_text().splitlines():
        s = line.split("#", 1)[0].strip()
        if s:
            vals += [float(x) for x in s.replace(",", " ").split()]
    if len(vals) < 4:
        raise InputError(path, "expected 'fx fy cx cy [width height] [depth_factor]'")
    fx, fy, cx, cy = vals[:4]
    w, h = (int(vals[4]), int(vals[5])) if len(vals) >= 6 else (0, 0)
    units = 1.0 / vals[6] if len(vals) >= 7 else None
    return Intrinsics(w, h, fx, fy, cx, cy), units


@dataclass
class TumSequence:
    """A TUM RGB-D style folder; picklable, so workers can reopen it by value."""

    path: Path
    depth_files: list[Path]
    timestamps_s: list[float]
    info: StreamInfo
    name: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def frame_count(self) -> int | None:
        return len(self.depth_files)

    def frames(self, limit: int | None = None, start: int = 0) -> Iterator[FrameSet]:
        import cv2

        stop = len(self.depth_files) if limit is None else min(len(self.depth_files), start + limit)
        for i in range(start, stop):
            img = cv2.imread(str(self.depth_files[i]), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != np.uint16 or img.ndim != 2:
                raise InputError(self.depth_files[i], "not a 16-bit single-channel depth PNG")
            t_ns = round(self.timestamps_s[i] * 1e9)
            yield FrameSet(index=i, timestamp_ns=t_ns, depth=img.astype(np.uint16))


def open_tum_folder(path: Path, intrinsics: Path | None = None) -> TumSequence:
    """Read the list of depth frames and their time stamps; image size from the first PNG."""
    path = Path(path)
    assoc = next((path / n for n in _ASSOC_NAMES if (path / n).is_file()), None)
    if assoc is None:
        raise InputError(path, f"no {' / '.join(_ASSOC_NAMES)} in this TUM RGB-D folder")
    stamps: list[float] = []
    files: list[Path] = []
    for line in assoc.read_text().splitlines():
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
    if intr.width == 0 or intr.height == 0:
        import cv2

        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError(files[0], "cannot read depth PNG")
        intr = Intrinsics(first.shape[1], first.shape[0], intr.fx, intr.fy, intr.ppx, intr.ppy,
                          intr.model, intr.coeffs)
    info = StreamInfo(depth_intrinsics=intr, color_intrinsics=None,
                      depth_units_m=units if units is not None else 1.0 / TUM_DEPTH_FACTOR)
    return TumSequence(path, files, stamps, info, name=path.name)


def open_sequence(path: Path, intrinsics: Path | None = None) -> FrameSource:
    """A TUM RGB-D folder (has depth.txt or associations) or anything the capture reader opens."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "sequence not found")
    if path.is_dir() and any((path / n).is_file() for n in _ASSOC_NAMES):
        return open_tum_folder(path, intrinsics)
    try:
        from depthstation.capture.reader import open_recording
    except ImportError as exc:
        raise InputError(path, "reading captures needs depthstation.capture.reader "
                               f"(not available: {exc})") from exc
    rec: FrameSource = open_recording(path)
    return rec
