"""Top-level commands of this part; `register` adds them to the root app."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add this part's commands to the root `depthstation` app."""
    app.command("explain")(explain)


def explain(
    real: list[Path] = typer.Argument(..., help="Real captures: sessions, MCAP/.bag/.db3, PNG sets."),
    board: Path = typer.Option(..., "--board", help="board.json or a protocol TOML with [board]."),
    model: str = typer.Option("d455", "--model", help="Preset (d455, d435, d415) or a model TOML."),
    out: Path = typer.Option(..., "--out", help="Result folder (must be new or empty)."),
    frames: int = typer.Option(30, "--frames", help="Frames per standpoint to use."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulation."),
    scan: bool = typer.Option(False, "--scan", help="Reference-scan sequences (not supported yet)."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Also write a rerun recording here."),
    spawn: bool = typer.Option(False, "--spawn", help="Open a rerun viewer."),
    serve: bool = typer.Option(False, "--serve", help="Serve a local rerun web viewer."),
    no_resimulate: bool = typer.Option(False, "--no-resimulate", help="Skip the check with the new model."),
    workers: int = typer.Option(1, "--workers", help="Local worker processes for the real-side evaluation."),
    cluster: str | None = typer.Option(None, "--cluster", help="Dask scheduler address (tcp://host:8786)."),
) -> None:
    """Locate where simulation and real data differ, name the missing physics, refit, show the gain."""
    from depthstation.board import load_board
    from depthstation.errors import InputError
    from depthstation.progress import stderr_console
    from depthstation.viz import RerunTarget
    from evaluate.explain.pipeline import evaluate_real, explain_sides, simulate_like
    from evaluate.explain.report import write_outputs
    from simulate.model import load_model

    if scan:
        raise InputError(None, "--scan: explain for reference-scan sequences is not implemented yet")
    for p in real:
        if not p.exists():
            raise InputError(p, "not found")
    if out.exists() and any(out.iterdir()):
        raise InputError(out, "is not empty; explain never overwrites results")
    if workers < 1:
        raise InputError(None, "--workers must be at least 1")
    if frames < 2:
        raise InputError(None, "--frames must be at least 2 (noise needs several frames)")
    brd = load_board(board)
    mdl = load_model(model)

    def tick(msg: str) -> None:
        stderr_console.print(f"[bold]explain[/]: {msg}")

    real_side = evaluate_real(real, brd, frames=frames, baseline_m=mdl.camera.baseline_m, tick=tick,
                              workers=workers, cluster=cluster)
    sim_side = simulate_like(real_side, brd, mdl, seed=seed, tick=tick)
    ex = explain_sides(real_side, sim_side, mdl, brd, seed=seed, resimulate=not no_resimulate, tick=tick)
    data = write_outputs(ex, out, [str(p) for p in real],
                         {"board": str(board), "model": model, "frames": frames, "seed": seed,
                          "workers": workers, "cluster": cluster})
    target = RerunTarget(rrd, spawn, serve)
    if target.enabled:
        from evaluate.explain.rerun_log import log_explanation

        log_explanation(ex, target)
    verdict = ("significant mismatch" if data["mismatch"]["significant"] else "no significant mismatch")
    typer.echo(f"{verdict}; selected: {', '.join(data['selected']) or 'nothing'}; "
               f"missing physics: {', '.join(data['missing_physics']) or 'none'}; results in {out}")
