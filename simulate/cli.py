"""Commands of this stage (thin: load, call the pure functions, write results)."""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.core.capture.mcap_writer import COLOR_ENCODINGS, SIMULATION_COLOR_ENCODING
from depthstation.core.errors import InputError
from depthstation.core.results import ForceOption, result_folder, write_result_info
from depthstation.simulate.checkerboard_session import load_truth, simulate_checkerboard
from depthstation.simulate.model import SensorModel, load_model
from depthstation.simulate.scan_sequence import simulate_scan
from depthstation.simulate.units import draw_unit

MODEL_HELP = "preset (d455, d435, d415; d455-ideal, d435-ideal, d415-ideal: a clean camera) or a model TOML"
UNIT_SEED_HELP = ("another unit of the model: its depth scale, disparity offset and static pattern drawn "
                  "from the population over units (docs/simulator.md, 'Units'); default: the preset's unit")


def _model(model: str, unit_seed: int | None) -> SensorModel | str:
    """The model as given, or another unit of it (`--unit-seed`)."""
    return model if unit_seed is None else draw_unit(load_model(model), unit_seed)


app = typer.Typer(no_args_is_help=True, help="Render captures with the simulated D455 (or D435, D415).")


@app.command("checkerboard")
def checkerboard_cmd(
    protocol: str = typer.Option("checkerboard-d455", "--protocol", "-p",
                                 help="protocol name in protocols/ or a protocol TOML"),
    model: str = typer.Option("d455", "--model", "-m", help=MODEL_HELP),
    out: Path = typer.Option(..., "--out", "-o", help="new (or empty) output folder"),
    fmt: str = typer.Option("mcap", "--format", help="mcap (capture session) or db3 (RealSense recordings)"),
    seed: int = typer.Option(0, "--seed", help="random seed of the sensor noise"),
    frames: int | None = typer.Option(None, "--frames",
                                      help="frames per standpoint (default: the protocol's)"),
    standpoint: list[str] | None = typer.Option(None, "--standpoint",
                                                help="only these standpoints (repeatable)"),
    unit_seed: int | None = typer.Option(None, "--unit-seed", help=UNIT_SEED_HELP),
    force: ForceOption = False,
) -> None:
    """Simulate every standpoint of a checkerboard protocol, with truth.json beside the captures."""

    with result_folder(out, force=force, inputs=[protocol, model], kind="simulate-checkerboard") as tmp:
        simulate_checkerboard(protocol, _model(model, unit_seed), tmp, fmt=fmt, seed=seed, frames=frames,
                              standpoints=standpoint or None, progress=True)
        truth = load_truth(tmp)
        write_result_info(tmp, "simulate-checkerboard", [protocol, model],
                          {"protocol": protocol, "model": model, "format": fmt, "seed": seed,
                           "frames": frames, "unit_seed": unit_seed},
                          device=truth["stream_info"]["device"],
                          extra={"standpoints": [s["name"] for s in truth["standpoints"]]})
    n = len(truth["standpoints"])
    typer.echo(f"{n} standpoints simulated into {out} (truth in {out / 'truth.json'})")


@app.command("scan")
def scan_cmd(
    scene: str = typer.Option("room", "--scene", "-s", help="'room' (procedural) or a PLY/OBJ mesh"),
    trajectory: str = typer.Option("walk", "--trajectory", "-t",
                                   help="'walk' (round the table) or a TUM trajectory file"),
    model: str = typer.Option("d455", "--model", "-m", help=MODEL_HELP),
    out: Path = typer.Option(..., "--out", "-o", help="new (or empty) output folder"),
    seed: int = typer.Option(0, "--seed", help="random seed of the sensor noise"),
    frames: int | None = typer.Option(None, "--frames", help="limit the number of frames"),
    width: int = typer.Option(640, "--width"),
    height: int = typer.Option(480, "--height"),
    fps: float = typer.Option(30.0, "--fps"),
    color_encoding: str = typer.Option(
        SIMULATION_COLOR_ENCODING, "--color-encoding",
        help="colour as the D455 sends it over USB, YUYV 4:2:2 ('yuv422_yuy2', ~0.55 of the size), "
             "or 'rgb8' as librealsense hands it on; every reader gives RGB either way"),
    unit_seed: int | None = typer.Option(None, "--unit-seed", help=UNIT_SEED_HELP),
    force: ForceOption = False,
) -> None:
    """Simulate a scan sequence: sequence.mcap, trajectory.txt (TUM), scene.ply, truth.json."""

    if color_encoding not in COLOR_ENCODINGS:
        raise InputError(None, f"--color-encoding {color_encoding!r}: use one of "
                               f"{', '.join(COLOR_ENCODINGS)}")
    with result_folder(out, force=force, inputs=[scene, trajectory, model], kind="simulate-scan") as tmp:
        simulate_scan(scene, trajectory, _model(model, unit_seed), tmp, seed=seed, frames=frames, width=width,
                      height=height, fps=fps, progress=True, color_encoding=color_encoding)
        truth = load_truth(tmp)
        write_result_info(tmp, "simulate-scan", [scene, trajectory, model],
                          {"scene": scene, "trajectory": trajectory, "model": model, "seed": seed,
                           "frames": frames, "width": width, "height": height, "fps": fps,
                           "color_encoding": color_encoding, "unit_seed": unit_seed},
                          device=truth["stream_info"]["device"])
    typer.echo(f"{truth['frames']} frames simulated into {out}")


@app.command("model")
def model_cmd(model: str = typer.Argument("d455", help="preset or model TOML"),
              unit_seed: int | None = typer.Option(None, "--unit-seed", help=UNIT_SEED_HELP)) -> None:
    """Print a model as TOML: every effect with its meaning, source, parameters and units."""

    mdl = load_model(model) if unit_seed is None else draw_unit(load_model(model), unit_seed)
    typer.echo(mdl.to_toml(), nl=False)
