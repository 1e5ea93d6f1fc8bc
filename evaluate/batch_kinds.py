"""What a batch item is, and how each kind (scan, checkerboard) prepares and checks one.

A kind registers two functions: ``prepare`` (runs in the batch's process: loads what is small,
decides the chunks, returns the :class:`ItemJob`) and ``check`` (runs for every item before any
item runs: the item's input keys, its options' names and TOML types, what can be read cheaply).
``prepare`` calls the study's one prepare path (its ``run.py``), so an item and the command write
the same folder. The item types and the registry live here, below the manifest, so that reading
a manifest always finds scan and checkerboard registered.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE
from depthstation.core.protocol import load_board
from depthstation.evaluate.checkerboard.chunks import REFERENCES, StandpointOptions, checkerboard_chunk
from depthstation.evaluate.checkerboard.run import finish_checkerboard, prepare_checkerboard
from depthstation.evaluate.checkerboard.study import StandpointResult
from depthstation.evaluate.scan.budget import run_budget
from depthstation.evaluate.scan.chunks import (
    merge_scan_results,
    pack_scan_result,
    scan_chunk,
    unpack_scan_result,
)
from depthstation.evaluate.scan.reference import check_reference_file
from depthstation.evaluate.scan.report import write_scan
from depthstation.evaluate.scan.run import ScanOptions, prepare_scan
from depthstation.evaluate.scan.study import ChunkResult
from depthstation.evaluate.scan.trajectory import read_tum


# -- items and jobs --------------------------------------------------------------------------------
@dataclass
class BatchItem:
    """One evaluation of the manifest: inputs and options resolved, where its results go."""

    name: str
    kind: str
    inputs: dict[str, Any]
    options: dict[str, Any]
    out: Path

    def fingerprint(self) -> str:
        """Changes when the item's inputs or options change, so an edited item is redone."""
        text = json.dumps({"kind": self.kind, "inputs": self.inputs, "options": self.options},
                          sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class ItemJob:
    """How an item runs: chunk descriptors and their function; then ``finish`` writes the folder.

    ``merge`` given: chunk results are folded in chunk order and ``finish`` gets the merged one;
    else it gets the list. ``finish`` writes ``result.json`` and returns the name of the item's
    grid file in its folder, or None (then the item does not enter the combined grid).
    """

    fn: Callable[[Any], Any]
    chunks: Sequence[Any]
    finish: Callable[[Any], str | Path | None]
    merge: Callable[[Any, Any], Any] | None = None
    encode: Callable[[Any], Any] | None = None
    decode: Callable[[Any], Any] | None = None
    description: str = ""
    # work after `finish` that needs the batch's runner again (a scan item's --budget: its
    # refinement's frames and its second study go to the same workers as the item's chunks)
    after: Callable[[Any, Any], None] | None = None


#: kind -> function preparing the job of an item (runs in this process: loads what is small,
#: decides the chunks; the heavy reading happens in the chunk function on the workers).
KINDS: dict[str, Callable[[BatchItem], ItemJob]] = {}


@dataclass(frozen=True)
class ItemCheck:
    """What checking an item before the batch runs found: the recordings whose frames it reads
    (two items reading one count them twice in the combined result) and its grid bins (scan
    grids combine only with equal bins)."""

    recordings: tuple[Path, ...]
    bins: tuple[float, ...] | None = None


#: kind -> check of an item's inputs and options before any item runs (InputError(None, problem)
#: naming the key); kinds without one get the generic check (inputs are existing paths).
CHECKS: dict[str, Callable[[BatchItem], ItemCheck]] = {}


def register_kind(kind: str, prepare: Callable[[BatchItem], ItemJob],
                  check: Callable[[BatchItem], ItemCheck] | None = None) -> None:
    KINDS[kind] = prepare
    if check is not None:
        CHECKS[kind] = check


def _toml(value: Any) -> str:
    """A value as it was written in the manifest (true, "false", 2.7)."""
    return str(value).lower() if isinstance(value, bool) else json.dumps(value, default=str)


def _toml_type(value: Any) -> str:
    return {bool: "true/false", int: "a whole number", float: "a decimal number", str: "a string",
            list: "an array", dict: "a table"}.get(type(value), type(value).__name__)


def check_value(value: Any, hint: Any) -> str | None:
    """What `value` (read from TOML) should have been for the type `hint`, None when it fits.

    Why: Python's int(), float() and bool() accept what the user did not mean: true counted as
    1 frame, 2.7 frames as 2, distance_max_m = true as 1 m, icp = "false" turned registration on.
    A bool is not a number, a decimal is not a count, a string is not a switch."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        hint = args[0] if len(args) == 1 else hint
    if typing.get_origin(hint) is tuple:
        n = len(typing.get_args(hint))
        ok = isinstance(value, list) and len(value) == n and all(check_value(v, float) is None for v in value)
        return None if ok else f"an array of {n} numbers"
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "a whole number"
    if hint is float:
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else "a number"
    if hint is str:
        return None if isinstance(value, str) else "a string"
    return None


def _check_options(options: dict[str, Any], hints: dict[str, Any], kind: str) -> None:
    unknown = sorted(set(options) - set(hints))
    if unknown:
        close = difflib.get_close_matches(unknown[0], hints, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise InputError(None, f"unknown {kind} option '{unknown[0]}'{hint} "
                               f"(known: {', '.join(sorted(hints))})")
    for key, value in options.items():
        want = check_value(value, hints[key])
        if want is not None:
            raise InputError(None, f"option {key} must be {want}, not {_toml(value)} ({_toml_type(value)})")


def _check_input_keys(item: BatchItem, need: Sequence[str], may: Sequence[str] = (),
                      lists: Sequence[str] = ()) -> None:
    missing = [k for k in need if k not in item.inputs]
    if missing:
        raise InputError(None, f"a {item.kind} item needs inputs {', '.join(need)}; "
                               f"{', '.join(missing)} missing")
    unknown = sorted(set(item.inputs) - set(need) - set(may))
    if unknown:
        raise InputError(None, f"unknown input '{unknown[0]}' (a {item.kind} item takes "
                               f"{', '.join([*need, *may])})")
    for key, value in item.inputs.items():
        if isinstance(value, list) and key not in lists:
            raise InputError(None, f"inputs.{key} must be one path, not a list")


def _generic_check(item: BatchItem) -> ItemCheck:
    return ItemCheck(tuple(item_paths(item)))


def _overlap(a: Path, b: Path, resolved: bool = False) -> bool:
    """One path is the other or holds it (a session and one of its recordings); `resolved`: both
    are resolved already (the manifest's pairwise check resolves each path once)."""
    ra, rb = (a, b) if resolved else (a.resolve(), b.resolve())
    return ra == rb or ra in rb.parents or rb in ra.parents


# -- manifest kinds: each calls its study's one prepare / finish path -------------------------------
def item_paths(item: BatchItem) -> list[Path]:
    """Every path among an item's inputs (lists too): what its folder must not hold."""
    out: list[Path] = []
    for v in item.inputs.values():
        for x in v if isinstance(v, list) else [v]:
            if isinstance(x, (str, Path)):
                out.append(Path(x))
    return out


def _paths(item: BatchItem, keys: Sequence[str]) -> dict[str, Path]:
    return {k: Path(item.inputs[k]) for k in keys if k in item.inputs}


def _prepare_checkerboard(item: BatchItem) -> ItemJob:
    """Item inputs: ``inputs`` (path or list: sessions, recordings, PNG folders), ``board``.
    Options: those of `evaluate checkerboard` (``frames``, ``reference``)."""
    raw = item.inputs.get("inputs")
    if raw is None or "board" not in item.inputs:
        raise InputError(None, f"{item.name}: a checkerboard item needs inputs.inputs and inputs.board")
    known = {"frames", "reference"}
    unknown = sorted(set(item.options) - known)
    if unknown:
        raise InputError(None, f"{item.name}: unknown checkerboard options {', '.join(unknown)} "
                               f"(known: {', '.join(sorted(known))})")
    paths = [Path(p) for p in (raw if isinstance(raw, list) else [raw])]
    frames = item.options.get("frames")
    options = StandpointOptions(frames=None if frames is None else int(frames),
                                reference=str(item.options.get("reference", "auto")))
    job = prepare_checkerboard(paths, Path(item.inputs["board"]), options)

    def finish(results: list[StandpointResult]) -> str | None:
        finish_checkerboard(job, results, item.out)
        return None

    return ItemJob(checkerboard_chunk, job.chunks, finish, description="standpoints")


def _prepare_scan(item: BatchItem) -> ItemJob:
    """Item inputs: ``sequence``, ``poses`` (TUM), ``reference`` (mesh or cloud), optional
    ``similarity`` (4x4 text), ``pass_points`` (CSV), ``intrinsics``. Options: those of `evaluate
    scan` (``chunk_frames``, ``icp``, ``frames``, ``every``, grid bins ...)."""
    need = [k for k in ("sequence", "poses", "reference") if k not in item.inputs]
    if need:
        raise InputError(None, f"{item.name}: a scan item needs inputs {', '.join(need)}")
    paths = _paths(item, ("similarity", "pass_points", "intrinsics"))
    options = ScanOptions.from_mapping(item.options, paths, None, item.name)
    job = prepare_scan(Path(item.inputs["sequence"]), Path(item.inputs["poses"]),
                       Path(item.inputs["reference"]), item.out, options, in_process=False)

    def finish(res: ChunkResult) -> str:
        write_scan(job, res)
        return GRID_FILE

    def budget(res: ChunkResult, runner: Any) -> None:  # as `evaluate scan --budget` runs it
        run_budget(job, res, runner)

    return ItemJob(scan_chunk, job.chunks, finish, merge=merge_scan_results, encode=pack_scan_result,
                   decode=unpack_scan_result, description="frames", after=budget if options.budget else None)


CHECKERBOARD_OPTIONS = {"frames": int, "reference": str}
SCAN_PATHS = ("similarity", "pass_points", "intrinsics")


def _check_checkerboard(item: BatchItem) -> ItemCheck:
    """Inputs ``inputs`` (paths) and ``board`` (one, loadable); options typed, in range."""
    _check_input_keys(item, ("inputs", "board"), lists=("inputs",))
    _check_options(item.options, CHECKERBOARD_OPTIONS, "checkerboard")
    frames = item.options.get("frames")
    if frames is not None and frames < 1:
        raise InputError(None, f"option frames must be at least 1, not {frames}")
    if item.options.get("reference", "auto") not in REFERENCES:
        raise InputError(None, f"option reference must be one of {', '.join(REFERENCES)}, "
                               f"not {item.options['reference']!r}")
    load_board(Path(item.inputs["board"]))
    raw = item.inputs["inputs"]
    paths = [Path(p) for p in (raw if isinstance(raw, list) else [raw])]
    for j, b in enumerate(paths):
        for a in paths[:j]:
            if _overlap(a, b):
                raise InputError(None, f"inputs.inputs names {b} and {a}: one recording twice would count "
                                       "twice in the combined result")
    return ItemCheck(tuple(paths))


def _check_scan(item: BatchItem) -> ItemCheck:
    """Inputs ``sequence``, ``poses``, ``reference`` and the optional paths; options typed as
    ScanOptions' fields and checked as the command checks them."""
    _check_input_keys(item, ("sequence", "poses", "reference"), SCAN_PATHS)
    hints = typing.get_type_hints(ScanOptions)
    names = {f.name for f in dataclasses.fields(ScanOptions)} - {"target", "workers", "cluster", "force"}
    given_paths = sorted(set(item.options) & set(SCAN_PATHS))
    if given_paths:
        raise InputError(None, f"{given_paths[0]} is a path: give it in inputs (resolved against the "
                               "manifest's folder), not in options")
    _check_options(item.options, {k: hints[k] for k in names - set(SCAN_PATHS)}, "scan")
    options = ScanOptions.from_mapping(item.options, _paths(item, SCAN_PATHS), None, item.name)
    options.check()
    if options.frames is not None and options.frames < 1:
        raise InputError(None, f"option frames must be at least 1, not {options.frames}")
    # what can be read cheaply is read now: a broken pose file or an empty reference ran the items
    # before it and failed with exit 1 (the sequence is opened by the item; a reference is not meshed)
    if Path(item.inputs["poses"]).exists():  # (a missing one is said with the other missing inputs)
        read_tum(Path(item.inputs["poses"]), options.pose_convention)
    if Path(item.inputs["reference"]).exists():
        check_reference_file(Path(item.inputs["reference"]))
    return ItemCheck((Path(item.inputs["sequence"]),),
                     (options.distance_bin_m, options.inclination_bin_deg, options.distance_max_m))


register_kind("scan", _prepare_scan, _check_scan)
register_kind("checkerboard", _prepare_checkerboard, _check_checkerboard)
