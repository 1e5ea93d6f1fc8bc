"""`depthstation demo`: the whole station on the simulated D455, one step after another.

Each step calls the public Python functions of a stage (no subprocesses) and writes an ordinary
result folder, the same a user would get from the stage's own command. A step whose stage is not
part of this build says so and the demo goes on; a step that fails is reported and the others
still run. The demo never writes into an existing folder: a taken `--out` gets a numbered sibling.
"""

from __future__ import annotations

import importlib
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.table import Table

from depthstation.core.errors import DepthstationError, InputError
from depthstation.core.progress import stderr_console
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import check_out_path, write_json, write_result_info
from depthstation.simulate.model import load_model

DEMO_PROTOCOL = "demo-d455"
DEMO_MODEL = "d455"


@dataclass
class DemoContext:
    """What the steps share: where to write, how to record, what earlier steps produced."""

    out: Path
    rrd: bool = True
    spawn: bool = False
    serve: bool = False
    results: dict[str, Path] = field(default_factory=dict)
    facts: dict[str, Any] = field(default_factory=dict)

    def target(self, folder: Path, name: str) -> RerunTarget:
        """A recording per study: `<folder>/<name>.rrd` (unless --no-rrd), plus the viewer when asked."""
        return RerunTarget(folder / f"{name}.rrd" if self.rrd else None, self.spawn, self.serve)


@dataclass
class StepOutcome:
    status: str                 # 'done', 'not available', 'failed', 'skipped'
    seconds: float = 0.0
    summary: str = ""
    result: Path | None = None


@dataclass(frozen=True)
class Step:
    name: str
    title: str
    requires: tuple[str, ...]               # 'module:attribute' the step calls
    run: Callable[[DemoContext], tuple[Path, str]]   # -> (result folder, one-line summary)
    # extra requirements that depend on what earlier steps produced (e.g. a fallback input)
    needs: Callable[[DemoContext], tuple[str, ...]] | None = None


def missing_requirement(requires: tuple[str, ...],
                        done: set[str] | frozenset[str] = frozenset()) -> str | None:
    """The first 'module:attribute' this build lacks (or 'step:NAME' not done before), or None.

    Only a missing module or attribute counts; an import that fails inside an existing module is
    a bug and propagates.
    """
    for req in requires:
        mod_name, _, attr = req.partition(":")
        if mod_name == "step":
            if attr not in done:
                return f"the {attr} step"
            continue
        try:
            mod = importlib.import_module(mod_name)
        except ModuleNotFoundError as exc:
            if exc.name and (mod_name == exc.name or mod_name.startswith(exc.name + ".")):
                return req
            raise
        if attr and not hasattr(mod, attr):
            return req
    return None


def fresh_dir(path: Path) -> Path:
    """`path` if it is free (absent or empty), else the first free `path-2`, `path-3`, ..."""
    path = Path(path)
    if not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return path
    k = 2
    while True:
        cand = path.with_name(f"{path.name}-{k}")
        if not cand.exists():
            return cand
        k += 1


def run_steps(ctx: DemoContext, steps: list[Step], skip: set[str]) -> dict[str, StepOutcome]:
    """Run the steps in order; never stop early, record what happened to each."""
    outcomes: dict[str, StepOutcome] = {}
    log = ctx.out / "demo.log"
    for k, step in enumerate(steps, 1):
        head = f"[bold cyan]step {k}/{len(steps)}: {step.title}[/]"
        if step.name in skip:
            stderr_console.print(f"{head}: skipped (--skip {step.name})")
            outcomes[step.name] = StepOutcome("skipped")
            continue
        missing = missing_requirement(step.requires + (step.needs(ctx) if step.needs else ()),
                                      set(ctx.results))
        if missing is not None:
            msg = f"step {step.name}: not available in this build (needs {missing})"
            stderr_console.print(f"{head}\n  [yellow]{msg}[/]")
            outcomes[step.name] = StepOutcome("not available", summary=msg)
            continue
        stderr_console.print(head)
        t0 = time.perf_counter()
        try:
            folder, summary = step.run(ctx)
        except Exception as exc:  # the demo goes on; the log keeps the traceback
            dt = time.perf_counter() - t0
            with log.open("a") as fh:
                fh.write(f"--- step {step.name} failed after {dt:.1f} s\n{traceback.format_exc()}\n")
            kind = "error" if isinstance(exc, DepthstationError) else f"{type(exc).__name__}"
            msg = f"step {step.name} failed ({kind}: {exc}); details in {log}"
            stderr_console.print(f"  [red]{msg}[/]")
            outcomes[step.name] = StepOutcome("failed", dt, msg)
            continue
        dt = time.perf_counter() - t0
        ctx.results[step.name] = folder
        stderr_console.print(f"  [green]done[/] in {dt:.1f} s: {summary}\n  -> {folder}")
        outcomes[step.name] = StepOutcome("done", dt, summary, folder)
    return outcomes


def print_report(ctx: DemoContext, outcomes: dict[str, StepOutcome], steps: list[Step],
                 total_s: float) -> None:

    table = Table(title=f"depthstation demo: {ctx.out} ({total_s:.0f} s)")
    for head in ("step", "status", "time", "result", "open it with"):
        table.add_column(head)
    for step in steps:
        o = outcomes[step.name]
        res = str(o.result) if o.result else (o.summary if o.status != "done" else "")
        how = ""
        own = sorted(o.result.glob("*.rrd")) if o.result is not None and o.result.is_dir() else []
        if own:
            how = f"depthstation view {own[0]}"
        elif o.result is not None:
            how = (f"depthstation view {o.result}" if (o.result / "result.json").is_file()
                   else f"depthstation capture info {o.result}" if (o.result / "session.json").is_file()
                   else str(o.result))
        style = {"done": "green", "failed": "red"}.get(o.status, "yellow")
        table.add_row(step.title, f"[{style}]{o.status}[/]", f"{o.seconds:.1f} s" if o.seconds else "",
                      res, how)
    stderr_console.print(table)
    rrds = sorted(ctx.out.rglob("*.rrd"))
    if rrds:
        lines = [f"  depthstation view {p}" for p in rrds]
        # soft_wrap: a long path broken across lines by the console is a command nobody can paste
        stderr_console.print("recordings (heatmaps, blueprints, descriptions), one per study; open one with\n"
                             + "\n".join(lines) + "\n  (add --serve for a web viewer)", highlight=False,
                             soft_wrap=True)


def model_facts(name: str) -> dict[str, Any]:
    """What demo.json records of the demo's camera model: every effect with its parameters, units,
    meaning and source."""
    mdl = load_model(name)
    return {"name": mdl.name, "preset": mdl.camera.name,
            "effects": {e.name: {"params": dict(e.params), "units": dict(e.units), "meaning": e.meaning,
                                 "source": e.source} for e in mdl.effects}}


def run_demo(out: Path, *, rrd: bool = True, spawn: bool = False, serve: bool = False,
             skip: set[str] | None = None, steps: list[Step]) -> dict[str, StepOutcome]:
    """Run `steps` (the demo's are `demo_steps.DEMO_STEPS`) into a fresh folder; returns each step's
    outcome (also in `demo.json`)."""
    names = {s.name for s in steps}
    unknown = set(skip or ()) - names
    if unknown:

        raise InputError(None, f"unknown step(s) for --skip: {', '.join(sorted(unknown))} "
                               f"(steps: {', '.join(s.name for s in steps)})")
    check_out_path(Path(out))  # a file is refused as by every command (it ran into afile-2/)
    target = fresh_dir(out)
    if target != Path(out):
        stderr_console.print(f"{out} is not empty; the demo writes to {target} instead")
    target.mkdir(parents=True, exist_ok=True)
    ctx = DemoContext(target, rrd, spawn, serve)
    stderr_console.print(f"[bold]depthstation demo[/]: the station on the simulated D455, into {target}")
    t0 = time.perf_counter()
    outcomes = run_steps(ctx, steps, set(skip or ()))
    total = time.perf_counter() - t0
    write_json(target / "demo.json", {
        "total_s": total,
        "model": model_facts(DEMO_MODEL),
        "steps": {n: {"status": o.status, "seconds": o.seconds, "summary": o.summary,
                      "result": str(o.result) if o.result else None} for n, o in outcomes.items()},
        "facts": ctx.facts,
    })
    write_result_info(target, "demo", [], {"protocol": DEMO_PROTOCOL, "model": DEMO_MODEL, "rrd": rrd},
                      extra={"steps": {n: o.status for n, o in outcomes.items()}})
    print_report(ctx, outcomes, steps, total)
    failed = [n for n, o in outcomes.items() if o.status == "failed"]
    if failed:
        msg = f"demo finished with failed step(s): {', '.join(failed)} (see {target / 'demo.log'})"
        raise DepthstationError(msg)
    return outcomes
