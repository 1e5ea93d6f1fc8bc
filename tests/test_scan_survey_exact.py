"""A georeferenced study bins every pixel as the local one: the reference hits refined in float64
(`evaluate/scan/hit_refine.py`) do not depend on where the scene sits."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.core.grid import Grid
from depthstation.evaluate.scan.rasterise import make_renderer
from depthstation.evaluate.scan.raycast import STAT_NAMES, CellAccumulator
from depthstation.evaluate.scan.synthetic import ErrorModel, Room, make_sequence

SURVEY = np.array([412345.6, 5523456.7, 110.0])


def _grids(renderer: str) -> tuple[Grid, Grid]:
    """The same frames binned in the room's frame and in survey coordinates shifted back by whole
    metres (what the study does with a far-away reference), on fine bins (2 mm, 0.5 deg) where a
    micrometre or a thousandth of a degree moves a sample into the next cell."""
    o3d = pytest.importorskip("open3d")
    seq = make_sequence(frames=4, width=160, height=120, model=ErrorModel(), depth_units_m=1e-4, seed=4)
    mesh = Room().mesh(segments=512, subdivide_walls=6)
    v = np.asarray(mesh.vertices)
    shift = np.round((v.min(0) + v.max(0)) / 2 + SURVEY)
    moved = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector((v + SURVEY) - shift), mesh.triangles)
    grid = Grid.empty(0.002, 0.5, 6.0, 90.0)
    out = []
    for m, local in ((mesh, False), (moved, True)):
        r = make_renderer(renderer, m, seq.info.depth_intrinsics, 1)
        cells, stats = CellAccumulator.for_grid(grid), np.zeros(len(STAT_NAMES), np.int64)
        for pose, fs in zip(seq.poses, seq.frames(), strict=True):
            p = np.array(pose, dtype=np.float64)
            if local:
                p[:3, 3] = (p[:3, 3] + SURVEY) - shift
            r.bin_frame(p, fs.depth, seq.info.depth_units_m, cells, stats)
        out.append(cells.to_grid())
    return out[0], out[1]


@pytest.mark.parametrize("renderer", ["raster", "raycast"])
def test_survey_coordinates_bin_every_sample_as_the_local_study(renderer: str) -> None:
    """Same counts in every cell and cell means within 1e-6 m: at most a float32 step of one depth
    (2.4e-7 m, a float64 depth that rounds the other way). With the renderer's float32 hits and
    normals the same frames gave cell means up to 2.0 mm apart."""
    a, b = _grids(renderer)
    assert a.count.sum() > 40_000
    assert np.array_equal(a.count, b.count)
    both = a.count > 0
    assert np.max(np.abs(a.mean[both] - b.mean[both])) < 1e-6
