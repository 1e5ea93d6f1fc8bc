"""The checkerboard study (paper Section 3.1): per-frame board pose, board mask, noise and accuracy.

Public entry points: `evaluate_recording` (one standpoint -> `StandpointResult`),
`write_study` (tables, summary and figures of many standpoints).
"""

from depthstation.evaluate.checkerboard.study import (
    FrameResult,
    PixelSamples,
    StandpointResult,
    evaluate_frames,
    evaluate_recording,
)

__all__ = [
    "FrameResult",
    "PixelSamples",
    "StandpointResult",
    "evaluate_frames",
    "evaluate_recording",
]
