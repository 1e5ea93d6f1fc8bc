"""Concealed-effect sessions for the explain tests, generated WITHOUT the fitting code's forms.

Frames come from the simulator with the plain D455 model; the hidden effect is then written into
the depth maps here, in its own physical parameterisation (z error in mm per m^2, a per-column
disparity term, a reflectance-dependent range error, a warm-up exponential in time), never through
`simulate.effects` or `evaluate.explain.basis`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.board import Board
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.registry import open_inputs
from depthstation.core.frames import FrameSet

# hidden(z, u, v, black, t_s, temperature, cam) -> z error (m); cam holds fx, ppx, ppy, baseline_m
Hidden = Callable[..., Any]
WARM_C = 40.0
DITHER_SEED = 20240


def board_black(board: Board, cam_to_board: np.ndarray, fx: float, fy: float, ppx: float, ppy: float,
                shape: tuple[int, int]) -> np.ndarray:
    """Which depth pixels see a black square: rays intersected with the board plane z = 0."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    rays = np.stack([(u - ppx) / fx, (v - ppy) / fy, np.ones_like(u)], axis=-1)
    r, t = cam_to_board[:3, :3], cam_to_board[:3, 3]
    d = rays @ r.T
    s = -t[2] / d[..., 2]
    p = t + d * s[..., None]
    return board.is_black(p[..., 0], p[..., 1])


def wide_protocol(width: int = 640, height: int = 360) -> Any:
    """The demo protocol spread over 1-5 m (the span of the issue's studies), 0 and 30 deg.

    z^2 (disparity offset) and z (depth scale) differ by a factor 5 in shape over this span, and
    the board is still found at 5 m at 640x360.
    """
    from depthstation.core.protocol import load_protocol

    p = load_protocol("demo-d455")
    plan = replace(p.plan, start_distance_m=1.0, step_m=1.0, max_distance_m=5.0, inclinations_deg=(0.0, 30.0))
    return replace(p, plan=plan, streams=replace(p.streams, width=width, height=height))


def conceal(sim_dir: Path, out_dir: Path, hidden: Hidden | None, *, warmup_tau_s: float | None = None,
            warmup_rise_c: float = 0.0, frame_period_s: float | None = None,
            standpoint_period_s: float | None = None, noise_seed: int | None = None) -> Path:
    """Copy a simulated session into `out_dir` as plain MCAP files with the hidden effect added.

    With `noise_seed`, `hidden` is random: it is called with a generator as a last argument
    (seeded per standpoint and frame) and may draw per-pixel or per-frame noise.

    With `warmup_tau_s`, the device temperature rises as T = 40 - rise exp(-t / tau) over the
    session (an unfinished warm-up) and every frame carries it in its metadata, as the simulator
    and the capture do. `frame_period_s` / `standpoint_period_s` re-time the frames (a standpoint
    held for a while, the operator walking between standpoints), so the warm-up shows both
    across and within standpoints.
    """
    truth = json.loads((sim_dir / "truth.json").read_text())
    board = Board.from_dict(truth["board"])
    out_dir.mkdir(parents=True, exist_ok=True)
    recs = open_inputs([sim_dir])
    t_start = None
    for k, rec in enumerate(recs):
        sp = next(s for s in truth["standpoints"] if s["name"] == rec.name)
        intr = rec.info.depth_intrinsics
        units = rec.info.depth_units_m
        cam = {"fx": intr.fx, "ppx": intr.ppx, "ppy": intr.ppy, "baseline_m": rec.info.baseline_m}
        black = board_black(board, np.asarray(sp["depth_camera_to_board"]), intr.fx, intr.fy, intr.ppx,
                            intr.ppy, (intr.height, intr.width))
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        frames: list[FrameSet] = []
        for i, fs in enumerate(rec.frames()):
            if t_start is None:
                t_start = fs.timestamp_ns
            if frame_period_s is not None and standpoint_period_s is not None:
                fs.timestamp_ns = int(t_start + (k * standpoint_period_s + i * frame_period_s) * 1e9)
            t_s = (fs.timestamp_ns - t_start) / 1e9
            temp = WARM_C if warmup_tau_s is None else WARM_C - warmup_rise_c * np.exp(-t_s / warmup_tau_s)
            assert fs.depth is not None
            z = fs.depth.astype(np.float64) * units
            valid = fs.depth > 0
            out_units = units
            if hidden is not None:
                # the simulated depth is already rounded to 1 mm; adding an error below half a unit
                # to it and rounding again would erase it (at a flat 1 m standpoint 0.3 mm became 0
                # on every pixel, 1.2 mm became 1 mm). The concealed camera reports 0.1 mm units
                # (a D4xx setting), with uniform dither of that unit so its rounding is unbiased.
                out_units = units / 10
                rng = np.random.default_rng([DITHER_SEED, k, i])
                args = (z, u, v, black, t_s, temp, cam)
                if noise_seed is not None:
                    args = (*args, np.random.default_rng([noise_seed, k, i]))
                with np.errstate(divide="ignore", invalid="ignore"):   # z = 0 where there is no depth
                    z = z + hidden(*args) + out_units * (rng.random(z.shape) - 0.5)
            counts = np.rint(z / out_units)
            depth = np.where(valid & (counts < 65535), np.clip(counts, 1, 65535), 0).astype(np.uint16)
            frames.append(FrameSet(fs.index, fs.timestamp_ns, depth, fs.color, fs.infrared,
                                   {**fs.metadata, "temperature_c": float(temp)}))
        meta = dict(rec.metadata)
        info = rec.info
        if hidden is not None:
            info = replace(rec.info, depth_units_m=units / 10)
            meta["device"] = {**(meta.get("device") or {}), "depth_units_m": units / 10}
        write_mcap(out_dir / f"{rec.name}.mcap", info, frames, meta)
    return out_dir
