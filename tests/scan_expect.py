"""What the simulator's model says a simulated walk's grid holds: the model's bias and variance
per cell, evaluated at the very pixels the study used (reference depth, inclination, pixel position)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.capture.registry import open_recording
from depthstation.core.grid import Grid
from depthstation.evaluate.scan.raycast import MeshCaster
from depthstation.evaluate.scan.trajectory import read_tum
from depthstation.simulate.effects.base import PixelContext


def model_grids(d: Path, model: Any, like: Grid) -> tuple[Grid, Grid]:
    """(bias, variance) grids of `model` over the walk in `d` (sequence.mcap, trajectory.txt,
    scene.ply), binned like `like`."""
    rec = open_recording(d / "sequence.mcap")
    traj = read_tum(d / "trajectory.txt")  # true poses in the mesh frame
    intr = rec.info.depth_intrinsics
    caster = MeshCaster(d / "scene.ply", intr, nthreads=1)
    bias, var = like.like(), like.like()
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    for fs in rec.frames():
        pose = traj.match(fs.timestamp_ns * 1e-9, 0.01)
        assert pose is not None and fs.depth is not None
        im = caster.images(pose, fs.depth, rec.info.depth_units_m)
        ok = (fs.depth > 0) & np.isfinite(im.reference_m)
        ctx = PixelContext(z_m=im.reference_m[ok].astype(np.float64),
                           inclination_deg=im.inclination_deg[ok].astype(np.float64), u=u[ok], v=v[ok],
                           fx=intr.fx, ppx=intr.ppx, ppy=intr.ppy, baseline_m=rec.info.baseline_m or 0.095)
        z, inc = im.reference_m[ok], im.inclination_deg[ok]
        bias.add(z, inc, np.broadcast_to(model.bias_m(ctx), z.shape))
        var.add(z, inc, np.broadcast_to(model.variance_m2(ctx), z.shape))
    return bias, var
