"""`depthstation model fit|show` and `depthstation correct`: thin commands over the error model."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import typer
from rich.table import Table

from depthstation.core.errors import InputError
from depthstation.core.progress import progress, stdout_console
from depthstation.core.results import _jsonable, disk_error
from depthstation.evaluate.errormodel.build import fit_model
from depthstation.evaluate.errormodel.correct import correct_recording
from depthstation.evaluate.errormodel.figures import model_figure, model_table
from depthstation.evaluate.errormodel.schema import ErrorModel, load_model

model_app = typer.Typer(no_args_is_help=True, help="Fit and show a camera's depth error model.")


def register(app: typer.Typer) -> None:
    """Add `model` (fit, show) and `correct` to the root `depthstation` app."""
    app.add_typer(model_app, name="model", help="A camera's depth error model: fit it, show it.")
    app.command("correct")(correct)


def write_model(model: ErrorModel, path: Path) -> Path:
    """The model file, written under a temporary name and linked into place: never overwrites."""
    path = Path(path)
    if path.exists():
        raise InputError(path, "exists; depthstation never overwrites a model (choose another name)")
    if path.suffix.lower() != ".json":
        raise InputError(path, "a model file is JSON: give a name ending in .json")
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(_jsonable(model.to_dict()), indent=1, allow_nan=False) + "\n")
        try:
            os.link(tmp, path)   # fails where the name appeared meanwhile: nothing is replaced
        except FileExistsError as exc:
            raise InputError(path, "appeared while the model was written; nothing was replaced") from exc
    except OSError as exc:
        raise disk_error(exc, path) from exc
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _say(model: ErrorModel) -> None:
    con = stdout_console  # full width in a log, so no table cell is cut
    t = Table(title="depth error model (z in m, theta in deg)")
    for col in ("part", "term", "formula", "coefficient", "std. error"):
        t.add_column(col)
    for row in model_table(model):
        t.add_row(*row)
    con.print(t)
    for name, part in (("bias", model.bias), ("sigma", model.sigma)):
        v = part.info.get("validation") or {}
        if v.get("done"):
            con.print(f"{name}: held out by {v['unit']}: RMS {v['rms_residual_m'] * 1e3:.3g} mm against "
                      f"{v['rms_raw_m'] * 1e3:.3g} mm raw, "
                      f"{v['rms_offset_only_m'] * 1e3:.3g} mm offset alone")
        else:
            con.print(f"{name}: not validated ({v.get('why', 'no validation')})")
    z0, z1 = model.domain.z_range_m
    t0, t1 = model.domain.theta_range_deg
    con.print(f"domain: {len(model.domain.boxes)} measured cells within {z0:.2f}-{z1:.2f} m, "
              f"{t0:.0f}-{t1:.0f} deg; "
              f"{len(model.measured['rows'])} rows of the measured field in the file")


@model_app.command("fit")
def fit(
    results: list[Path] = typer.Argument(..., help="Result folders of one camera: scan studies (grid.npz) "
                                                   "and/or checkerboard studies (standpoints.csv)."),
    out: Path = typer.Option(..., "--out", help="Model file to write (.json; never overwritten)."),
    distance_bin_m: float = typer.Option(0.1, "--distance-bin-m",
                                         help="Table cell in distance (m): the scan grid is coarsened "
                                              "to it."),
    inclination_bin_deg: float = typer.Option(5.0, "--inclination-bin-deg",
                                              help="Table cell in inclination (deg)."),
    min_count: int = typer.Option(200, "--min-count", min=3,
                                  help="A table cell enters the fit and the domain with this many samples."),
) -> None:
    """Fit a camera's depth error model (bias and sigma over distance x inclination) to its studies."""
    model = fit_model(results, distance_bin_m=distance_bin_m, inclination_bin_deg=inclination_bin_deg,
                      min_count=min_count)
    write_model(model, out)
    _say(model)
    typer.echo(f"-> {out}")


@model_app.command("show")
def show(
    model_file: Path = typer.Argument(..., help="A model file written by `model fit`."),
    png: Path | None = typer.Option(None, "--png", help="Figure to write (default: beside the model, "
                                                        "<name>.png; never overwritten)."),
) -> None:
    """Print the model's table and draw it beside the measured field (PNG)."""
    model = load_model(model_file)
    _say(model)
    target = png or model_file.with_suffix(".png")
    if target.exists():
        raise InputError(target, "exists; give --png another name (figures are never overwritten)")
    tmp = target.with_name(f".{target.stem}.partial-{os.getpid()}.png")
    try:
        model_figure(model, tmp)
        tmp.rename(target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise disk_error(exc, target) from exc
    typer.echo(f"-> {target}")


def correct(
    sequence: Path = typer.Argument(..., help="Recording to correct (.mcap/.bag/.db3, PNG set, TUM folder)."),
    model_file: Path = typer.Option(..., "--model", help="The camera's model file (`model fit`)."),
    out: Path = typer.Option(..., "--out", help="Folder to write (new or empty; written whole or not "
                                                "at all)."),
    sigma: bool = typer.Option(False, "--sigma", help="Also write the model's per-pixel standard deviation "
                                                      "(32FC1 metres, topic /camera/depth/sigma)."),
    compression: str = typer.Option("lz4", "--compression", help="MCAP chunk compression: none, lz4, zstd."),
) -> None:
    """Remove the model's depth bias from every pixel of a recording (inclination from the depth's own
    normals); the result is a recording in the station's format."""
    with progress(transient=True) as bar:
        tasks: list[Any] = []

        def step(i: int, total: int | None) -> None:
            if not tasks:   # the bar starts with the first frame, once the inputs were checked
                tasks.append(bar.add_task("correcting", total=total, status=""))
            bar.update(tasks[0], completed=i + 1, total=total)

        s = correct_recording(sequence, model_file, out, sigma=sigma, compression=compression, on_frame=step)
    st = s["stats"]
    share = st["corrected"] / max(st["pixels"], 1)
    typer.echo(f"{st['frames']} frames, {100 * share:.1f} % of the depth pixels corrected "
               f"({st['outside_domain']} outside the model's domain, {st['no_normal']} without a normal: "
               "kept raw) "
               f"in {st['seconds']:.1f} s -> {out / s['output']}")
