"""Which triangles of a cloud's Poisson mesh count as surface nobody scanned: the rule the study
uses (a vertex beyond the gap) against the centroid, the mean of the vertices and all three,
judged pixel by pixel against the true room (not a speed benchmark: docs/scan-study.md quotes it).

The room's table was never scanned from the side (its side and the floor under it are cut out of
the cloud), so Poisson closes it with a surface of its own. For each rule: the pixels left out, how
many of them have a reference more than 10 mm off the true room's, and how many such pixels stay
in the grid.

Run by hand: .venv/bin/python benchmarks/unmeasured_rules.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from depthstation.core.lazy_open3d import open3d
from depthstation.evaluate.scan.rasterise import make_renderer
from depthstation.evaluate.scan.reference import PoissonParams, reference_mesh, vertex_offsets
from depthstation.evaluate.scan.synthetic import Room, make_sequence

GAP_M = 0.01
OFF_M = 0.01


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="unmeasured_rules_") as tmp:
        run(Path(tmp))


def run(root: Path) -> None:
    o3d = open3d()
    room = Room()
    truth_mesh = room.mesh(segments=128)
    o3d.utility.random.seed(0)
    pts = np.asarray(truth_mesh.sample_points_uniformly(100_000).points)
    r = np.hypot(pts[:, 0] - room.table_center_m[0], pts[:, 1] - room.table_center_m[1])
    side = (np.abs(r - room.table_radius_m) < 0.02) & (pts[:, 2] < room.table_height_m - 0.02)
    side |= (r < room.table_radius_m) & (pts[:, 2] < 0.01)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[~side]))
    o3d.io.write_point_cloud(str(root / "cloud.ply"), cloud)
    params = PoissonParams(depth=8, density_quantile=0.0)
    inside = np.array([[3.0, 2.5, 1.5]])  # the cloud's normals face the room's middle
    mesh, _, _ = reference_mesh(root / "cloud.ply", root / "mesh", params, viewpoints=inside)
    cloud = o3d.io.read_point_cloud(str(root / "cloud.ply"))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    pts, nrm = np.asarray(cloud.points), np.asarray(cloud.normals)
    per_vertex = vertex_offsets(v, pts, nrm)[t]
    rules = {"a vertex beyond (the rule)": per_vertex.max(axis=1) > GAP_M,
             "centroid beyond": vertex_offsets(v[t].mean(axis=1), pts, nrm) > GAP_M,
             "mean of the vertices beyond": per_vertex.mean(axis=1) > GAP_M,
             "all three vertices beyond": per_vertex.min(axis=1) > GAP_M}
    seq = make_sequence(frames=6, width=80, height=60, seed=2)
    intr, units = seq.info.depth_intrinsics, seq.info.depth_units_m
    true_r = make_renderer("raster", truth_mesh, intr, 1)
    truth = [true_r.images(p, fs.depth, units) for fs, p in zip(seq.frames(), seq.poses, strict=True)]
    print(f"{'rule':30s} {'triangles':>9s} {'left out':>8s} {'of them off':>11s} {'off, kept':>9s} "
          f"{'kept':>6s}")
    for name, mask in rules.items():
        ren = make_renderer("raster", mesh, intr, 1, unmeasured=mask)
        off_left = off_kept = n_left = n_kept = 0
        for (fs, pose), b in zip(zip(seq.frames(), seq.poses, strict=True), truth, strict=True):
            a = ren.images(pose, fs.depth, units)
            off = np.abs(a.reference_m - b.reference_m) > OFF_M
            left, kept = a.unmeasured, np.isfinite(a.inclination_deg)
            off_left += int(np.sum(off & left))
            off_kept += int(np.sum(off & kept))
            n_left += int(left.sum())
            n_kept += int(kept.sum())
        print(f"{name:30s} {int(mask.sum()):9d} {n_left:8d} {off_left:6d} ({off_left / max(n_left, 1):3.0%}) "
              f"{off_kept:9d} {n_kept:6d}")


if __name__ == "__main__":
    main()
