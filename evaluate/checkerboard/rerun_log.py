"""What the checkerboard study streams to rerun while it runs: images, board mask, per-frame figures."""

from __future__ import annotations

from typing import Any

import numpy as np

from depthstation.core.frames import FrameSet
from depthstation.core.rerun_bridge import (
    blueprint,
    image_view,
    send_scalar,
    send_table,
    send_text,
    series_view,
)
from depthstation.evaluate.checkerboard.frame import FrameResult
from depthstation.evaluate.checkerboard.study import StandpointResult

DESCRIPTION = """# Checkerboard study (paper Section 3.1)
Per standpoint and frame: the colour image with the detected board corners, the depth image,
and the per-frame figures (noise = RMS to the frame's fitted plane, accuracy = signed distance
to the reference plane from the board pose, + = too far; in mm). Time line `frame` counts every
frame read across standpoints; `standpoint` steps once per standpoint.
"""


def study_blueprint() -> Any:
    return blueprint(image_view("camera/color", "colour + corners"),
                     image_view("camera/depth", "depth"),
                     series_view("figures", "noise / accuracy per frame (mm)"),
                     series_view("progress", "progress"))


def start(rec: Any) -> None:
    send_text(rec, "description", DESCRIPTION)


def log_frame(rec: Any, step: int, name: str, fs: FrameSet, res: FrameResult,
              depth_units_m: float, every: int = 5) -> None:
    """Per-frame figures every frame; images every `every`-th frame (an .rrd stays small)."""
    if rec is None:
        return
    import rerun as rr

    rec.set_time("frame", sequence=step)
    if res.ok:
        rec.log("figures/noise_mm", rr.Scalars(res.noise_m * 1000))
        rec.log("figures/reference_distance_m", rr.Scalars(res.reference_distance_m))
        rec.log("figures/fill_rate", rr.Scalars(res.fill_rate))
    send_scalar(rec, "progress/frames_ok", float(res.ok), step=step, timeline="frame")
    if step % every == 0:
        if fs.color is not None:
            rec.log("camera/color", rr.Image(fs.color[::2, ::2]))
        if fs.depth is not None:
            rec.log("camera/depth", rr.DepthImage(fs.depth[::2, ::2], meter=1.0 / depth_units_m))
        rec.log("camera/status", rr.TextLog(f"{name} frame {fs.index}: {res.status}"))


def log_standpoint(rec: Any, index: int, r: StandpointResult) -> None:
    """The standpoint's figures on the `standpoint` time line and its averaged camera pose in 3D."""
    if rec is None:
        return
    import rerun as rr

    rec.set_time("standpoint", sequence=index)
    for key in ("noise_m", "accuracy_m", "reference_distance_std_m"):
        v = r.figures.get(key, float("nan"))
        if np.isfinite(v):
            rec.log(f"standpoints/{key.replace('_m', '_mm')}", rr.Scalars(v * 1000))
    if r.camera_in_board is not None:
        path = f"board/cameras/{r.name}"
        rec.log(path, rr.Transform3D(translation=r.camera_in_board[:3, 3],
                                     mat3x3=r.camera_in_board[:3, :3]), static=True)
        rec.log(path, rr.TransformAxes3D(0.2), static=True)


def log_table(rec: Any, rows: list[dict[str, Any]]) -> None:
    send_table(rec, "standpoints/table", rows)
