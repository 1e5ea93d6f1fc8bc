"""PNG standpoint folders (the layout of alr-d435-charuco): `frameK_depth.png` + `frameK_color.png`
with a `camera.json` here or one level up."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from depthstation.core.camera_model import Extrinsics, Intrinsics, StreamInfo
from depthstation.core.capture.recording import Recording, size_problem
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.run_warnings import warn
from depthstation.core.text_files import read_text


def _png_files(folder: Path) -> tuple[list[tuple[int, Path, Path | None]], list[int]]:
    """(frame number, depth PNG, colour PNG or None) per depth image, in frame order, and the frame
    numbers that have a colour image but no depth image; one listing of the folder."""
    depth: dict[int, Path] = {}
    colour: dict[int, Path] = {}
    for p in folder.iterdir():
        m = re.fullmatch(r"frame(\d+)_(depth|color)\.png", p.name)
        if m:
            (depth if m.group(2) == "depth" else colour)[int(m.group(1))] = p
    frames = sorted((k, d, colour.get(k)) for k, d in depth.items())
    return frames, sorted(k for k in colour if k not in depth)


def _png_frames(folder: Path) -> list[tuple[int, Path, Path | None]]:
    return _png_files(folder)[0]


class PngRecording(Recording):
    """A folder of `frameK_depth.png` (16 bit, aligned to colour) and `frameK_color.png`."""

    def _iter(self, start: int) -> Iterator[FrameSet]:

        fps = self.info.fps or 30.0
        for k, dpath, cpath in _png_frames(self.path)[start:]:
            depth = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
                raise InputError(dpath, "is no 16-bit single-channel depth PNG")
            _check_size(dpath, depth, self.info.depth_intrinsics,
                        "the colour stream's (depth_aligned_to_color)" if self.info.depth_aligned_to_color
                        else "the depth stream's")
            color = None
            if cpath is not None:
                bgr = cv2.imread(str(cpath), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise InputError(cpath, "is no readable colour image")
                _check_size(cpath, bgr, self.info.color_intrinsics, "the colour stream's")
                color = np.ascontiguousarray(bgr[..., ::-1])
            yield FrameSet(
                index=k,
                timestamp_ns=round(k * 1e9 / fps),
                depth=depth.astype(np.uint16, copy=False),
                color=None if color is None else color.astype(np.uint8, copy=False),
                metadata={"source_file": dpath.name, "timestamp_source": "nominal fps"},
            )


def _check_size(path: Path, image: np.ndarray, intr: Intrinsics | None, whose: str) -> None:
    problem = size_problem(image, intr, f"camera.json gives {whose} size as")
    if problem:
        raise InputError(path, problem)


def _png_camera_json(folder: Path) -> Path | None:
    for d in (folder, folder.parent):
        if (d / "camera.json").is_file():
            return d / "camera.json"
    return None


def _intrinsics(cam: dict[str, Any], key: str, path: Path) -> Intrinsics:
    """One stream's intrinsics from camera.json; errors name the key."""
    table = cam.get(key)
    if not isinstance(table, dict):
        raise InputError(path, f"missing key '{key}' (the stream's width, height, fx, fy, cx, cy)")
    try:
        return Intrinsics.from_dict(table)
    except KeyError as exc:
        raise InputError(path, f"missing key '{key}.{exc.args[0]}'") from exc
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"{key}: {exc}") from exc


def _depth_to_color(cam: dict[str, Any], path: Path) -> Extrinsics:
    """The depth -> colour transform of unaligned depth (row-major `rotation`, `translation` in
    m, as capture-format.md). Never assumed: with identity, every depth pixel would be looked up
    at the wrong colour pixel, the baseline (~5 cm) off."""
    table = cam.get("depth_to_color")
    if not isinstance(table, dict):
        raise InputError(path, "missing key 'depth_to_color' (depth_aligned_to_color is false: the depth -> "
                               "colour transform, row-major 'rotation' (9 values) and 'translation' (m))")
    try:
        rot = tuple(float(x) for x in table["rotation"])
        trans = tuple(float(x) for x in table["translation"])
    except KeyError as exc:
        raise InputError(path, f"missing key 'depth_to_color.{exc.args[0]}'") from exc
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"depth_to_color: {exc}") from exc
    r = np.asarray(rot)
    if r.size != 9 or len(trans) != 3 or not np.all(np.isfinite(r)) or not np.all(np.isfinite(trans)) \
            or not np.allclose(r.reshape(3, 3) @ r.reshape(3, 3).T, np.eye(3), atol=1e-4):
        raise InputError(path, "depth_to_color needs a rotation (9 values, orthonormal) and a translation "
                               "(3 values, m)")
    return Extrinsics(rot, (trans[0], trans[1], trans[2]))


def open_png(folder: Path) -> PngRecording:
    cam_path = _png_camera_json(folder)
    if cam_path is None:
        raise InputError(folder, "PNG folder without camera.json (here or one level up)")
    try:
        cam = json.loads(read_text(cam_path, "camera JSON"))
    except ValueError as exc:
        raise InputError(cam_path, f"broken JSON ({exc})") from exc
    if not isinstance(cam, dict):
        raise InputError(cam_path, "expected a JSON object")
    color = _intrinsics(cam, "color", cam_path)
    aligned = cam.get("depth_aligned_to_color", True)
    if not isinstance(aligned, bool):
        raise InputError(cam_path, f"depth_aligned_to_color must be true or false, got {aligned!r}")
    depth_intr = color if aligned else _intrinsics(cam, "depth", cam_path)
    to_color = Extrinsics() if aligned else _depth_to_color(cam, cam_path)
    if "depth_units_m" not in cam:  # the scale of every depth value: never assumed
        raise InputError(cam_path, "missing key 'depth_units_m' (metres per depth count, e.g. 0.001)")
    units = cam["depth_units_m"]
    if isinstance(units, bool) or not isinstance(units, (int, float)) or not 1e-6 <= float(units) <= 0.1:
        raise InputError(cam_path, f"depth_units_m must be metres per count (1e-6 to 0.1), got {units!r}")
    fps = cam.get("fps", 30.0)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0:
        raise InputError(cam_path, f"fps must be positive, got {fps!r}")
    frames, colour_only = _png_files(folder)
    if not frames:
        raise InputError(folder, "has no frameK_depth.png files")
    if colour_only:  # a frame whose depth file is gone was not even counted as read
        warn(f"{len(colour_only)} frame(s) have a colour image but no depth image (frame "
             f"{', '.join(map(str, colour_only[:10]))}{', ...' if len(colour_only) > 10 else ''}): left out",
             str(folder), "frames-rejected")
    device = {"name": cam.get("sensor", "unknown")}
    baseline = cam.get("stereo_baseline_m", cam.get("stereo_baseline_m_nominal"))
    info = StreamInfo(
        depth_intrinsics=depth_intr,
        color_intrinsics=color,
        depth_to_color=to_color,
        depth_units_m=float(units),
        depth_aligned_to_color=aligned,
        baseline_m=None if baseline is None else float(baseline),
        fps=float(fps),
        device=device,
        # aligned depth: disparity physics lives in the stereo imager's own pixels
        stereo_intrinsics=(_intrinsics(cam, "depth_unaligned", cam_path)
                           if aligned and isinstance(cam.get("depth_unaligned"), dict) else None),
    )
    meta: dict[str, Any] = {"device": device, "source": {"kind": "png", "camera_json": str(cam_path)}}
    if (cam_path.parent / "board.json").is_file():
        meta["board"] = json.loads(read_text(cam_path.parent / "board.json", "board JSON"))
    if "depth_unaligned" in cam:
        meta["depth_unaligned_intrinsics"] = cam["depth_unaligned"]
    n_color = sum(1 for f in frames if f[2] is not None)
    return PngRecording(
        folder.name, folder, info, meta, len(frames), {"depth": len(frames), "color": n_color}
    )


def is_png_folder(path: Path) -> bool:
    return path.is_dir() and any(path.glob("frame*_depth.png"))
