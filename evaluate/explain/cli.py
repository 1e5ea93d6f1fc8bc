"""Top-level commands of this part; `register` adds them to the root app."""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.core.capture.topics import ColorTopic, DepthTopic, InfraredTopic, TopicChoice, topic_choice
from depthstation.core.errors import InputError
from depthstation.core.parallel import check_cluster_address
from depthstation.core.progress import stderr_console
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import ForceOption, check_out_path, result_folder
from depthstation.evaluate.explain.run import EXPLAIN_FRAMES, run_explain
from depthstation.evaluate.explain.scan_form import explain_scan, write_scan_outputs
from depthstation.evaluate.scan.run import ScanOptions
from depthstation.simulate.model import check_seed, load_model


def register(app: typer.Typer) -> None:
    """Add this part's commands to the root `depthstation` app."""
    app.command("explain")(explain)


def explain(
    real: list[Path] = typer.Argument(..., help="Real captures: sessions, MCAP/.bag/.db3, PNG sets "
                                      "(with --scan: the one sequence)."),
    board: Path | None = typer.Option(None, "--board", help="board.json or a protocol TOML with \\[board]."),
    model: str = typer.Option(
        "d455-ideal", "--model",
        help="The model to start from: a preset (d455-ideal: the clean camera, the starting point for a "
             "unit of unknown calibration; d455: the paper's unit; d435, d415 and their -ideal forms) "
             "or a model TOML."),
    out: Path = typer.Option(..., "--out", help="Result folder (must be new or empty)."),
    frames: int | None = typer.Option(None, "--frames", show_default=False,
                                      help="Frames per standpoint to use [default: up to 30; a standpoint "
                                           "with fewer is warned of only when --frames is given]."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulation."),
    scan: bool = typer.Option(False, "--scan",
                              help="REAL is a reference-scan sequence (needs --poses, --reference)."),
    poses: Path | None = typer.Option(None, "--poses", help="--scan: TUM trajectory of the sequence."),
    reference: Path | None = typer.Option(None, "--reference", help="--scan: reference mesh or cloud."),
    similarity: Path | None = typer.Option(None, "--similarity", help="--scan: 4x4 trajectory-to-reference."),
    register: str = typer.Option("none", "--register",
                                 help="--scan: none (trajectory as given), rigid or similarity (its scale "
                                      "is reported as the depth-scale error it absorbs)."),
    pose_convention: str = typer.Option("tum", "--pose-convention",
                                        help="--scan: how the pose file's lines are meant (tum, wxyz, "
                                             "inverse, inverse-wxyz), as evaluate scan."),
    pose_offset_s: float = typer.Option(0.0, "--pose-offset-s",
                                        help="--scan: seconds added to the trajectory's time stamps."),
    poses_of: str = typer.Option("depth", "--poses-of",
                                 help="--scan: the camera the trajectory describes, 'depth' or 'color' "
                                      "(RGB-D SLAM on depth aligned to colour), as evaluate scan."),
    icp: bool | None = typer.Option(None, "--icp/--no-icp", help="--scan, deprecated: --icp is --register "
                                                                 "similarity, --no-icp --register none."),
    block_frames: int | None = typer.Option(None, "--block-frames",
                                            help="--scan: frames per block (unit of independence; 8 when "
                                                 "not given, fewer in a short sequence)."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Also write a rerun recording here."),
    spawn: bool = typer.Option(False, "--spawn", help="Open a rerun viewer."),
    serve: bool = typer.Option(False, "--serve", help="Serve a local rerun web viewer."),
    no_resimulate: bool = typer.Option(False, "--no-resimulate", help="Skip the check with the new model."),
    discover: bool = typer.Option(True, "--discover/--no-discover",
                                  help="Search the library of generic terms for physics outside the "
                                       "catalogue."),
    workers: int = typer.Option(1, "--workers", help="Local worker processes for the real-side evaluation."),
    cluster: str | None = typer.Option(None, "--cluster", help="Dask scheduler address (tcp://host:8786)."),
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
    force: ForceOption = False,
) -> None:
    """Locate where simulation and real data differ, name the missing physics, refit, show the gain."""

    for p in real:
        if not p.exists():
            raise InputError(p, "not found")
    check_out_path(out)
    check_seed(seed)
    if cluster is not None:
        check_cluster_address(cluster)
    if out.exists() and any(out.iterdir()) and not force:
        raise InputError(out, "is not empty; explain never overwrites results (--force replaces it)")
    topics = topic_choice(depth_topic, color_topic, infrared_topic)
    if frames is not None and frames < 3:
        raise InputError(None, f"--frames must be at least 3, not {frames} (the noise tests need a temporal "
                               "variance over 3 frames or more)")
    if scan:
        scan_opt = ScanOptions(register=register, icp=icp, poses_of=poses_of, pose_convention=pose_convention,
                               pose_offset_s=pose_offset_s)
        scan_opt.check()
        mode = scan_opt.register_mode
        if mode == "pass-points":   # evaluate scan's --pass-points has no counterpart here
            raise InputError(None, "explain --scan registers with none, rigid or similarity; pass-points "
                                   "registration is evaluate scan's (--pass-points FILE): give the "
                                   "trajectory in the reference frame, or --similarity M")
        _explain_scan(real, poses, reference, model, out, frames or EXPLAIN_FRAMES, seed, similarity, mode,
                      block_frames, not no_resimulate, force, topics, discover, scan_opt)
        return
    if board is None:
        raise InputError(None, "--board is needed for checkerboard sessions")
    if workers < 1:
        raise InputError(None, "--workers must be at least 1")
    mdl = load_model(model)

    def tick(msg: str) -> None:
        stderr_console.print(f"[bold]explain[/]: {msg}")

    data = run_explain(real, board, mdl, out, frames=frames, seed=seed, resimulate=not no_resimulate,
                       workers=workers, cluster=cluster, topics=topics, discovery=discover,
                       parameters={"board": str(board), "model": model,
                                   "frames": frames if frames is not None else f"up to {EXPLAIN_FRAMES}",
                                   "seed": seed,
                                   "workers": workers, "cluster": cluster, "discover": discover},
                       target=RerunTarget(rrd, spawn, serve, force), tick=tick, force=force,
                       model_file=model_file(model))
    verdict = ("significant mismatch" if data["mismatch"]["significant"] else "no significant mismatch")
    typer.echo(f"{verdict}; selected: {', '.join(data['selected']) or 'nothing'}; "
               f"missing physics: {', '.join(data['missing_physics']) or 'none'}; "
               f"discovered: {_discovered_text(data)}; results in {out}")


def model_file(model: str) -> Path | None:
    """The model TOML a --model names (None for a preset name): an input of the run."""
    p = Path(model)
    return p if p.is_file() else None


def _discovered_text(data: dict[str, object]) -> str:
    found = data.get("discovered") or []
    assert isinstance(found, list)
    return ", ".join(f"{d['quantity']} along {'/'.join(d['axes'])}" for d in found) or "none"


def _explain_scan(real: list[Path], poses: Path | None, reference: Path | None, model: str, out: Path,
                  frames: int, seed: int, similarity: Path | None, register: str, block_frames: int | None,
                  resimulate: bool, force: bool, topics: TopicChoice | None = None,
                  discover: bool = True, pose_opt: ScanOptions | None = None) -> None:
    """`explain --scan`: a reference-scan sequence against its simulation along the same trajectory.
    `pose_opt`: how the trajectory is read (--poses-of, --pose-convention, --pose-offset-s)."""
    pose_opt = pose_opt or ScanOptions()

    if len(real) != 1:
        raise InputError(None, "--scan takes exactly one sequence")
    if poses is None or reference is None:
        raise InputError(None, "--scan needs --poses (TUM trajectory) and --reference (mesh or cloud)")
    for p in (poses, reference):
        if not p.exists():
            raise InputError(p, "not found")
    if block_frames is not None and block_frames < 1:
        raise InputError(None, "--block-frames must be at least 1")
    mdl = load_model(model)

    def tick(msg: str) -> None:
        stderr_console.print(f"[bold]explain --scan[/]: {msg}")

    given = model_file(model)
    inputs = [*real, poses, reference, *([similarity] if similarity else []), *([given] if given else [])]
    with result_folder(out, force=force, inputs=inputs, kind="explain-scan") as tmp:
        ex = explain_scan(real[0], poses, reference, mdl, tmp, frames=frames, block_frames=block_frames,
                          seed=seed, register=register, similarity=similarity, resimulate=resimulate,
                          discovery=discover, tick=tick, topics=topics, pose_opt=pose_opt)
        data = write_scan_outputs(ex, tmp, [str(p) for p in inputs],
                                  {"model": model, "frames": frames, "seed": seed, "register": register,
                                   "poses_of": pose_opt.poses_of, "pose_convention": pose_opt.pose_convention,
                                   "pose_offset_s": pose_opt.pose_offset_s,
                                   "block_frames": block_frames, "discover": discover,
                                   "similarity": str(similarity) if similarity else None})
    verdict = "significant mismatch" if data["mismatch"]["significant"] else "no significant mismatch"
    typer.echo(f"{verdict}; selected: {', '.join(data['selected']) or 'nothing'}; "
               f"missing physics: {', '.join(data['missing_physics']) or 'none'}; "
               f"discovered: {_discovered_text(data)}; results in {out}")
