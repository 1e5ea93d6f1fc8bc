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
from depthstation.core.capture.recording import Recording
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet


def _png_frames(folder: Path) -> list[tuple[int, Path, Path | None]]:

    out = []
    for p in folder.iterdir():
        m = re.fullmatch(r"frame(\d+)_depth\.png", p.name)
        if m:
            k = int(m.group(1))
            c = folder / f"frame{k}_color.png"
            out.append((k, p, c if c.is_file() else None))
    return sorted(out)


class PngRecording(Recording):
    """A folder of `frameK_depth.png` (16 bit, aligned to colour) and `frameK_color.png`."""

    def _iter(self, start: int) -> Iterator[FrameSet]:

        fps = self.info.fps or 30.0
        for k, dpath, cpath in _png_frames(self.path)[start:]:
            depth = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
                raise InputError(dpath, "is no 16-bit single-channel depth PNG")
            color = None
            if cpath is not None:
                bgr = cv2.imread(str(cpath), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise InputError(cpath, "is no readable colour image")
                color = np.ascontiguousarray(bgr[..., ::-1])
            yield FrameSet(
                index=k,
                timestamp_ns=round(k * 1e9 / fps),
                depth=depth.astype(np.uint16, copy=False),
                color=None if color is None else color.astype(np.uint8, copy=False),
                metadata={"source_file": dpath.name, "timestamp_source": "nominal fps"},
            )


def _png_camera_json(folder: Path) -> Path | None:
    for d in (folder, folder.parent):
        if (d / "camera.json").is_file():
            return d / "camera.json"
    return None


def open_png(folder: Path) -> PngRecording:
    cam_path = _png_camera_json(folder)
    if cam_path is None:
        raise InputError(folder, "PNG folder without camera.json (here or one level up)")
    try:
        cam = json.loads(cam_path.read_text())
        color = Intrinsics.from_dict(cam["color"])
    except (ValueError, KeyError) as exc:
        raise InputError(cam_path, f"bad camera.json: {exc}") from exc
    aligned = bool(cam.get("depth_aligned_to_color", True))
    depth_intr = color if aligned else Intrinsics.from_dict(cam["depth"])
    frames = _png_frames(folder)
    if not frames:
        raise InputError(folder, "has no frameK_depth.png files")
    device = {"name": cam.get("sensor", "unknown")}
    baseline = cam.get("stereo_baseline_m", cam.get("stereo_baseline_m_nominal"))
    info = StreamInfo(
        depth_intrinsics=depth_intr,
        color_intrinsics=color,
        depth_to_color=Extrinsics(),
        depth_units_m=float(cam.get("depth_units_m", 0.001)),
        depth_aligned_to_color=aligned,
        baseline_m=None if baseline is None else float(baseline),
        fps=float(cam.get("fps", 30.0)),
        device=device,
        # aligned depth: disparity physics lives in the stereo imager's own pixels
        stereo_intrinsics=(Intrinsics.from_dict(cam["depth_unaligned"])
                           if aligned and isinstance(cam.get("depth_unaligned"), dict) else None),
    )
    meta: dict[str, Any] = {"device": device, "source": {"kind": "png", "camera_json": str(cam_path)}}
    if (cam_path.parent / "board.json").is_file():
        meta["board"] = json.loads((cam_path.parent / "board.json").read_text())
    if "depth_unaligned" in cam:
        meta["depth_unaligned_intrinsics"] = cam["depth_unaligned"]
    n_color = sum(1 for f in frames if f[2] is not None)
    return PngRecording(
        folder.name, folder, info, meta, len(frames), {"depth": len(frames), "color": n_color}
    )


def is_png_folder(path: Path) -> bool:
    return path.is_dir() and any(path.glob("frame*_depth.png"))
