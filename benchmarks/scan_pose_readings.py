"""What reading a trajectory as the wrong camera of the rig or in the wrong convention does to the
scan study, and what the study says (not a speed benchmark: docs/scan-study.md quotes it).

A walk whose recording carries a D455-like depth-to-colour transform (59 mm); its trajectory
written as the depth camera's (the truth), as the colour camera's, and as COLMAP writes poses
(world-to-camera, qw first). Each is studied as given and as it should be read; printed: the fit
check's median |error| and share off, the grid's count-weighted mean error, and the warnings.

Run by hand: .venv/bin/python benchmarks/scan_pose_readings.py
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from depthstation.core.camera_model import Extrinsics
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.geometry import rodrigues
from depthstation.core.lazy_open3d import open3d
from depthstation.core.parallel import ChunkRunner
from depthstation.core.run_warnings import collecting
from depthstation.evaluate.scan.run import ScanOptions, prepare_scan, run_prepared
from depthstation.evaluate.scan.synthetic import Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="scan_pose_readings_") as tmp:
        run(Path(tmp))


def run(root: Path) -> None:
    seq = make_sequence(frames=12, width=80, height=60, seed=2)
    rig = np.eye(4)
    rig[:3, :3] = rodrigues([0.002, -0.003, 0.001])
    rig[:3, 3] = [-0.0591, 0.0001, 0.0003]
    write_mcap(root / "seq.mcap", dataclasses.replace(seq.info, depth_to_color=Extrinsics.from_matrix(rig)),
               seq.frames())
    t = np.asarray(seq.timestamps_ns) * 1e-9
    write_tum(root / "depth.txt", t, seq.poses)
    write_tum(root / "colour.txt", t, seq.poses @ np.linalg.inv(rig))
    w2c = np.linalg.inv(seq.poses)
    q = Rotation.from_matrix(w2c[:, :3, :3]).as_quat()
    np.savetxt(root / "colmap.txt", np.column_stack([t, w2c[:, :3, 3], q[:, 3], q[:, :3]]), fmt="%.9f")
    np.savetxt(root / "identity.txt", np.eye(4))
    open3d().io.write_triangle_mesh(str(root / "room.ply"), Room().mesh(segments=128))
    cases = [("depth poses", "depth.txt", {}), ("colour poses read as depth", "colour.txt", {}),
             ("colour poses, --poses-of color", "colour.txt", {"poses_of": "color"}),
             ("COLMAP poses read as TUM", "colmap.txt", {}),
             ("COLMAP, --pose-convention inverse-wxyz", "colmap.txt", {"pose_convention": "inverse-wxyz"})]
    for k, (name, poses, kw) in enumerate(cases):
        opt = ScanOptions(similarity=root / "identity.txt", distance_bin_m=0.25, inclination_bin_deg=5.0,
                          min_count_sequence=20, **kw)
        with collecting() as said, ChunkRunner(1) as runner:
            job = prepare_scan(root / "seq.mcap", root / poses, root / "room.ply", root / f"r{k}", opt)
            g = run_prepared(job, runner).grid
        fit = job.fit
        has = g.count > 0
        mean = float(np.average(g.mean[has], weights=g.count[has])) if g.total else float("nan")
        fit_s = ("none" if fit is None
                 else f"{1000 * fit.median_abs_error_m:7.1f} mm, {100 * fit.off_share:3.0f} % off")
        print(f"{name:40s} fit {fit_s}; grid mean {1000 * mean:7.2f} mm; "
              f"warnings {sorted({w.code for w in said})}")


if __name__ == "__main__":
    main()
