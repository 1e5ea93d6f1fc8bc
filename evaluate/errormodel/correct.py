"""`depthstation correct`: a recording with the error model's bias removed from every depth pixel,
written in the station's capture format (MCAP) with the same frames, stamps, colour and metadata.

The folder is written under a hidden temporary name and renamed when complete; an existing
folder is never written into. Depth keeps the source's units where they are 1 mm or finer (16UC1;
a 0.1 mm source stays 0.1 mm, so nothing the source resolved is lost), coarser sources are
written in millimetres. `--sigma` adds the model's standard deviation per pixel as 32FC1 metres
on its own topic (NaN where the model has none), which the station's readers skip.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.camera_model import StreamInfo, ray_planes
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture.mcap_reader import cut_source
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import check_lenses, open_recording
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.results import COMMAND_LINE, folder_written_whole, write_json
from depthstation.core.run_warnings import warn
from depthstation.evaluate.errormodel.inputs import device_model
from depthstation.evaluate.errormodel.kernels import Corrector
from depthstation.evaluate.errormodel.schema import ErrorModel, load_model

SIGMA_TOPIC = "/camera/depth/sigma"
CORRECTION_FILE = "correction.json"
THREADS = 2                 # kernel threads (the machines this runs on have two cores)
OUTSIDE_WARN_SHARE = 0.01   # warn when more of the valid pixels than this fall outside the domain


class SigmaWriter(mw.McapFileWriter):
    """The station's writer with one more image per frame set: the per-pixel sigma (32FC1, m)."""

    def write_sigma(self, fs: FrameSet, sigma: np.ndarray[Any, Any]) -> None:
        t, seq = int(fs.timestamp_ns), int(fs.index) & 0xFFFFFFFF
        frame_id = mw.COLOR_FRAME_ID if self.info.depth_aligned_to_color else mw.DEPTH_FRAME_ID
        self._image(SIGMA_TOPIC, sigma, "32FC1", t, frame_id, seq)


def check_camera(model: ErrorModel, model_path: Path, rec: Recording) -> list[str]:
    """Refuse a model of another camera or resolution (bad input, naming the file and the key);
    the differences of mode (firmware, preset, depth units) are returned to be warned."""
    cam = model.camera
    intr = rec.info.depth_intrinsics
    res = cam.get("resolution")
    if res is not None and list(res) != [intr.width, intr.height]:
        raise InputError(model_path, f"'camera.resolution' is {res[0]}x{res[1]}, but {rec.path} holds depth "
                                     f"of {intr.width}x{intr.height}: the model is for another resolution")
    dev = dict(rec.metadata.get("device") or rec.info.device or {})
    mine, theirs = cam.get("model"), device_model(dev.get("name"))
    if mine and theirs and mine != theirs:
        raise InputError(model_path, f"'camera.model' is {mine}, but {rec.path} was recorded by a {theirs}: "
                                     "the model is for another camera")
    ser, rser = cam.get("serial_number"), dev.get("serial_number")
    if ser and rser and str(ser) != str(rser):
        raise InputError(model_path, f"'camera.serial_number' is {ser}, but {rec.path} was recorded by "
                                     f"serial {rser}: the model is for another camera (fit one for it)")
    notes = []
    for key, have in (("firmware_version", dev.get("firmware_version")), ("preset", dev.get("preset"))):
        want = cam.get(key)
        if want is not None and have is not None and str(want) != str(have):
            notes.append(f"the model's {key} is {want}, the recording's {have}")
    if res is None:
        notes.append("the model names no resolution: it was not checked against the recording's")
    return notes


@dataclass
class CorrectionStats:
    frames: int = 0
    pixels: int = 0           # with depth
    corrected: int = 0
    outside_domain: int = 0
    no_normal: int = 0
    out_of_range: int = 0
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _out_name(rec: Recording) -> str:
    return f"{rec.name}.mcap"


def correct_recording(sequence: Path, model_path: Path, out: Path, *, sigma: bool = False,
                      compression: str = mw.CAPTURE_COMPRESSION,
                      on_frame: Callable[[int, int | None], None] | None = None) -> dict[str, Any]:
    """Write DIR/<name>.mcap (and correction.json): the recording with the model's bias removed."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "exists and is not empty; a corrected recording never overwrites anything")
    model = load_model(Path(model_path))
    rec = open_recording(Path(sequence))
    if rec.stream_counts.get("depth", 1) == 0 or rec.frame_count == 0:
        raise InputError(rec.path, "holds no depth frame to correct")
    check_lenses(rec, ("depth",))
    for note in check_camera(model, Path(model_path), rec):
        warn(note, str(model_path), "error-model-camera")
    info = rec.info
    out_units = min(info.depth_units_m, 0.001)
    out_info: StreamInfo = replace(info, depth_units_m=out_units) if out_units != info.depth_units_m else info
    x, y = ray_planes(info.depth_intrinsics)
    corr = Corrector(model, np.asarray(x), np.asarray(y), info.depth_units_m, out_units,
                     threads=min(THREADS, os.cpu_count() or 1))
    meta = {k: v for k, v in rec.metadata.items() if k != "format"}
    cut = cut_source(rec)
    meta["source"] = dict(rec.metadata.get("source") or {}, path=str(rec.path))
    if cut is not None:
        meta["source"].update(truncated=True, cut_path=cut["path"], recovered_frames=cut["recovered_frames"])
    meta["correction"] = {"model": str(model_path), "model_camera": model.camera,
                          "bias_terms": list(model.bias.terms),
                          "bias_coefficients": [float(c) for c in model.bias.coefficients],
                          "sigma_topic": SIGMA_TOPIC if sigma else None,
                          "depth_units_m": out_units, "command_line": COMMAND_LINE.get()}
    fmt_doc = rec.metadata.get("format")
    fmt: dict[str, Any] = fmt_doc if isinstance(fmt_doc, dict) else {}
    enc = str(fmt.get("color_encoding", "rgb8"))
    enc = enc if enc in mw.COLOR_ENCODINGS else "rgb8"
    out.parent.mkdir(parents=True, exist_ok=True)
    stats = CorrectionStats()
    t0 = time.perf_counter()
    try:
        with folder_written_whole(out, what="the corrected recording") as tmp:
            w = SigmaWriter(tmp / _out_name(rec), out_info, meta, compression=compression, color_encoding=enc)
            with w:
                for name, (times, values) in rec.temperatures().items():
                    for t, v in zip(times, values, strict=True):
                        w.write_temperature(t, {name: v})
                def emit(i: int, fs: FrameSet, job: Future[Any]) -> None:
                    depth, sig, _, counts = job.result()
                    w.write(replace(fs, depth=depth))
                    if sigma:
                        w.write_sigma(fs, sig)
                    stats.frames += 1
                    stats.pixels += int(counts.sum())   # every pixel with depth falls in one count
                    stats.corrected += int(counts[0])
                    stats.outside_domain += int(counts[1])
                    stats.no_normal += int(counts[2])
                    stats.out_of_range += int(counts[3])
                    if on_frame is not None:
                        on_frame(i, rec.frame_count)

                # the next frame is corrected while this one is written (the kernels release the GIL,
                # the writer's compression too): reading and writing no longer wait for the kernels
                with ThreadPoolExecutor(1) as ahead:
                    pending: tuple[int, FrameSet, Future[Any]] | None = None
                    for i, fs in enumerate(rec.frames()):
                        if fs.depth is None:
                            raise InputError(rec.path, f"frame {fs.index} has no depth")
                        job = ahead.submit(corr, fs.depth, sigma)
                        if pending is not None:
                            emit(*pending)
                        pending = (i, fs, job)
                    if pending is not None:
                        emit(*pending)
            if stats.frames == 0:
                raise InputError(rec.path, "holds no frame with depth to correct")
            stats.seconds = time.perf_counter() - t0
            summary = {"sequence": str(rec.path), "model": str(model_path), "output": _out_name(rec),
                       "sigma_topic": SIGMA_TOPIC if sigma else None, "depth_units_m": out_units,
                       "stats": stats.to_dict(),
                       "domain": model.domain.to_dict(),
                       "left_uncorrected": "pixels outside the model's domain or without a normal keep their "
                                           "raw depth (the model does not extrapolate); sigma is NaN there"}
            write_json(tmp / CORRECTION_FILE, summary)
    finally:
        corr.close()
    share = stats.outside_domain / max(stats.pixels, 1)
    if share > OUTSIDE_WARN_SHARE:
        warn(f"{100 * share:.1f} % of the depth pixels lie outside the model's domain (distance "
             f"{model.domain.z_range_m[0]:.2f}-{model.domain.z_range_m[1]:.2f} m, inclination "
             f"{model.domain.theta_range_deg[0]:.0f}-{model.domain.theta_range_deg[1]:.0f} deg, measured "
             "cells only): they keep their raw depth", str(rec.path), "error-model-domain")
    return summary
