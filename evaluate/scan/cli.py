"""`depthstation evaluate scan`: a thin typer command over `evaluate.scan.run.run_scan`.

Registered by `evaluate/cli.py` with `app.command("scan")(scan)`.
"""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.core.capture.topics import ColorTopic, DepthTopic, InfraredTopic
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import ForceOption
from depthstation.evaluate.scan.rasterise import DEFAULT_RENDERER
from depthstation.evaluate.scan.run import ScanOptions, run_scan


def scan(
    sequence: Path = typer.Option(..., "--sequence", help="Depth sequence: .mcap/.bag/.db3 capture or a "
                                                          "TUM RGB-D folder (depth.txt or associations)."),
    poses: Path = typer.Option(..., "--poses", help="TUM trajectory (timestamp tx ty tz qx qy qz qw), "
                                                    "camera-to-world, e.g. from ORB-SLAM3."),
    reference: Path = typer.Option(..., "--reference", help="Reference cloud (PLY/PCD/XYZ, E57/LAS with "
                                                            "pye57/laspy) or mesh."),
    out: Path = typer.Option(..., "--out", help="Result folder (created)."),
    similarity: Path | None = typer.Option(None, "--similarity",
                                           help="4x4 similarity text file: trajectory -> reference."),
    pass_points: Path | None = typer.Option(None, "--pass-points",
                                            help="CSV x,y,z,x_ref,y_ref,z_ref (Umeyama with scale)."),
    register: str = typer.Option("none", "--register",
                                 help="none (the trajectory as given, checked against the reference), "
                                      "rigid (ICP + mesh refinement), similarity (with a scale: reported as "
                                      "the depth-scale error it absorbs) or pass-points (Umeyama)."),
    icp: bool | None = typer.Option(None, "--icp/--no-icp",
                                    help="Deprecated: --icp is --register similarity, "
                                         "--no-icp --register none."),
    icp_min_m: float = typer.Option(0.5, "--icp-min-m", help="Depth band for the ICP cloud: lower (m)."),
    icp_max_m: float = typer.Option(2.0, "--icp-max-m", help="Depth band for the ICP cloud: upper (m)."),
    frames: int | None = typer.Option(None, "--frames", min=1, help="Evaluate at most N frames."),
    every: int = typer.Option(1, "--every", min=1, help="Use every N-th frame."),
    per_frame_grids: bool = typer.Option(False, "--per-frame-grids",
                                         help="Also save one grid per frame (frame_grids/)."),
    workers: int = typer.Option(1, "--workers", min=1, help="Processes (one ray-casting thread each "
                                                            "when > 1)."),
    cluster: str | None = typer.Option(None, "--cluster",
                                       help="Address of a Dask distributed scheduler (tcp://host:8786)."),
    chunk_frames: int = typer.Option(64, "--chunk-frames", min=1, help="Frames per task."),
    tolerance_s: float = typer.Option(0.01, "--pose-tolerance-s", help="Max |t_frame - t_pose| (s)."),
    pose_offset_s: float = typer.Option(0.0, "--pose-offset-s",
                                        help="Seconds added to the trajectory's time stamps (its clock onto "
                                             "the frames'); the study suggests one when the poses fit better "
                                             "shifted by a frame or two."),
    intrinsics: Path | None = typer.Option(None, "--intrinsics",
                                           help="Intrinsics file for a TUM folder (camera.json or "
                                                "'fx fy cx cy \\[w h] \\[factor]')."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Write a rerun recording."),
    force: ForceOption = False,
    spawn: bool = typer.Option(False, "--spawn", help="Stream to a rerun viewer."),
    serve: bool = typer.Option(False, "--serve", help="Serve a local rerun web viewer."),
    distance_bin_m: float = typer.Option(0.005, "--distance-bin-m", help="Grid distance bin (m)."),
    inclination_bin_deg: float = typer.Option(0.1, "--inclination-bin-deg",
                                              help="Grid inclination bin (deg)."),
    distance_max_m: float = typer.Option(6.0, "--distance-max-m", help="Grid distance range (m)."),
    min_count_frame: int = typer.Option(10, "--min-count-frame",
                                        help="Cells shown in the one-frame figure need this many samples."),
    min_count_sequence: int = typer.Option(2000, "--min-count-sequence",
                                           help="Cells shown in the sequence figure need this many."),
    figure_frame: int | None = typer.Option(None, "--figure-frame",
                                            help="Frame index for the Fig. 8/9 pictures (default: middle)."),
    poisson_depth: int = typer.Option(9, "--poisson-depth", help="Poisson octree depth for a cloud."),
    density_quantile: float = typer.Option(0.05, "--density-quantile",
                                           help="Drop Poisson vertices below this density quantile."),
    poisson_threads: int = typer.Option(1, "--poisson-threads",
                                        help="Threads for meshing a cloud: 1 gives the same mesh from "
                                             "the same cloud on every run; 0 uses all cores (faster, "
                                             "but the mesh differs by micrometres from run to run)."),
    pose_convention: str = typer.Option("tum", "--pose-convention",
                                        help="How the pose file's lines are meant: tum (camera-to-world, "
                                             "qx qy qz qw), wxyz (qw first), inverse (world-to-camera), "
                                             "inverse-wxyz (COLMAP's). The study names another that fits "
                                             "where the given one does not."),
    poses_of: str = typer.Option("depth", "--poses-of",
                                 help="The camera the trajectory describes: 'depth' (the depth stream's) or "
                                      "'color' (RGB-D SLAM on depth aligned to colour, e.g. ORB-SLAM3 on a "
                                      "RealSense); moved to the depth camera by the recording's extrinsics."),
    surface_gap_m: float = typer.Option(0.01, "--surface-gap-m",
                                        help="A cloud's meshed triangles with a vertex this far (m) off the "
                                             "scanned points' planes are surface nobody measured: they still "
                                             "hide what lies behind them, but the pixels that see them are "
                                             "left out of the grid. 0 keeps them."),
    reference_mode: str = typer.Option("points", "--reference-mode",
                                       help="A cloud reference: 'points' (each pixel's reference depth "
                                            "from a plane fitted to the scanned points around the surface "
                                            "its ray meets; pixels the points do not support are left out "
                                            "and counted) or 'mesh' (the cloud's Poisson mesh itself). A "
                                            "mesh reference is always used as it is."),
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
    renderer: str = typer.Option(DEFAULT_RENDERER, "--renderer",
                                 help="Reference depth: 'raster' (the mesh rasterised into each frame, "
                                      "bit for bit what ray casting gives, several times faster) or "
                                      "'raycast' (Open3D ray casting, the reference implementation). "
                                      "Streams with lens distortion are always ray cast."),
    budget: bool = typer.Option(False, "--budget",
                                help="Also split the error into the sensor's, the poses' (per frame), the "
                                     "registration's and the reference's parts: per-frame pose corrections "
                                     "fitted jointly with a smooth sensor field; writes sensor_grid.npz, "
                                     "budget.json, pose_corrections.csv/.tum and fig_budget.png "
                                     "(docs/scan-study.md, 'Error budget')."),
) -> None:
    """The reference-scan study (paper Section 3.2): per-pixel depth error against a TLS reference,
    gridded over distance x inclination."""

    opts = ScanOptions(similarity=similarity, pass_points=pass_points, register=register, icp=icp,
                       icp_band_m=(icp_min_m, icp_max_m), frames=frames, every=every,
                       per_frame_grids=per_frame_grids, workers=workers, cluster=cluster,
                       chunk_frames=chunk_frames, tolerance_s=tolerance_s, pose_offset_s=pose_offset_s,
                       distance_bin_m=distance_bin_m, inclination_bin_deg=inclination_bin_deg,
                       distance_max_m=distance_max_m, min_count_frame=min_count_frame,
                       min_count_sequence=min_count_sequence, figure_frame=figure_frame,
                       intrinsics=intrinsics, poisson_depth=poisson_depth,
                       density_quantile=density_quantile, poisson_threads=poisson_threads,
                       surface_gap_m=surface_gap_m, reference_mode=reference_mode, poses_of=poses_of,
                       pose_convention=pose_convention, force=force, depth_topic=depth_topic,
                       color_topic=color_topic, infrared_topic=infrared_topic, renderer=renderer,
                       budget=budget,
                       target=RerunTarget(rrd, spawn, serve, force))
    s = run_scan(sequence, poses, reference, out, opts)
    typer.echo(f"{s['frames']['used']} frames, {s['pixels']['evaluated']} pixels evaluated; "
               f"{s['registration_caption']} -> {out / 'grid.npz'}")
    cu = s["grid"].get("cell_uncertainty") or {}
    if cu.get("cells"):
        typer.echo(f"cell means: median 95% uncertainty {cu['median_u95_m'] * 1e3:.2f} mm over "
                   f"{cu['cells']} cells (frames as clusters; design effect "
                   f"{cu['median_design_effect']:.2g}: se_m, u95_m in grid.npz)")
