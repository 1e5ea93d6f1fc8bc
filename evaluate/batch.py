"""Many evaluations in one run: a manifest of items, a result folder each, a combined grid.

Why a manifest: a mapping campaign (dozens of sequences) or a fleet of cameras (several sessions
each) is run overnight, on a cluster, and must survive an interruption. Each item is one scan or
checkerboard evaluation; its frames or standpoints go out as chunks through
:mod:`depthstation.parallel`; an item counts as finished only when its folder holds
``result.json`` *and* the done marker, which is written last, so a restart redoes exactly the
items that were not finished, an item whose manifest entry changed and an item whose inputs
changed (size, time or the SHA-256 of their first and last MiB: cheap on a GB recording).

Manifest (TOML; relative paths are relative to the manifest's folder)::

    out = "campaign"                    # result root (default: <manifest stem>-results)
    [defaults.scan]                     # options every scan item starts from
    chunk_frames = 100
    [[items]]
    kind = "scan"                       # scan | checkerboard
    out = "seq01"                       # folder under the result root (default: the name)
    name = "seq01"                      # default: the stem of the first input
    inputs = { sequence = "seq01.mcap", poses = "seq01.txt", reference = "room.ply" }
    options = { chunk_frames = 50 }
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import hashlib
import json
import math
import os
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from depthstation.core.errors import DepthstationError, EvaluationError, InputError
from depthstation.core.grid import GRID_FILE, Grid
from depthstation.core.parallel import ChunkRunner, ProgressFn, progress_bar
from depthstation.core.protocol import load_board
from depthstation.core.results import (
    RESULT_FILE,
    RESULT_MARKER,
    check_out_path,
    fingerprint,
    result_folder,
    write_json,
    write_result_info,
)
from depthstation.core.run_warnings import collecting, warn
from depthstation.core.text_files import read_text
from depthstation.core.tomlcompat import tomllib
from depthstation.evaluate.checkerboard.chunks import REFERENCES, StandpointOptions, checkerboard_chunk
from depthstation.evaluate.checkerboard.run import finish_checkerboard, prepare_checkerboard
from depthstation.evaluate.checkerboard.study import StandpointResult
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

DONE_MARKER = ".done"
COMBINED_DIR = "combined"
BATCH_FILE = "batch.json"
STANDPOINTS_FILE = "standpoints.csv"


def merge_grids(a: Grid, b: Grid) -> Grid:
    """Chan merge of two partial grids (folds into ``a``)."""
    return a.merge(b)


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


@dataclass
class Manifest:
    path: Path
    out: Path
    items: list[BatchItem] = field(default_factory=list)


def _resolve_inputs(inputs: dict[str, Any], base: Path) -> dict[str, Any]:
    def one(v: Any) -> Any:
        if isinstance(v, str):
            p = Path(v).expanduser()
            return str(p if p.is_absolute() else (base / p))
        if isinstance(v, list):
            return [one(x) for x in v]
        return v

    return {k: one(v) for k, v in inputs.items()}


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


def _check_item(path: Path, k: int, raw: Any, base: Path, out: Path,
                defaults: dict[str, Any]) -> tuple[BatchItem, ItemCheck]:
    """One [[items]] entry resolved and checked (keys, option types, existing paths, the kind's
    own rules); every problem an InputError naming the manifest and items[k]."""
    where = f"items[{k}]"
    if not isinstance(raw, dict):
        raise InputError(path, f"{where} is not a table")
    bad = sorted(set(raw) - {"kind", "name", "out", "inputs", "options"})
    if bad:
        raise InputError(path, f"{where}: unknown key '{bad[0]}' (kind, name, out, inputs, options)")
    if not isinstance(raw.get("options", {}), dict):
        raise InputError(path, f"{where}.options must be a table")
    kind = raw.get("kind")
    if kind not in KINDS:
        known = ", ".join(sorted(KINDS)) or "none"
        raise InputError(path, f"{where}: kind {kind!r} is not one of {known}")
    inputs = raw.get("inputs", {})
    if not isinstance(inputs, dict) or not inputs:
        raise InputError(path, f"{where}: inputs must be a non-empty table")
    for key, v in inputs.items():
        if not (isinstance(v, str) or (isinstance(v, list) and v and all(isinstance(x, str) for x in v))):
            raise InputError(path, f"{where}: inputs.{key} must be a path or a list of paths, not {v!r}")
    for key in ("name", "out"):
        if key in raw and not (isinstance(raw[key], str) and raw[key]):
            raise InputError(path, f"{where}.{key} must be a non-empty string, not {raw[key]!r}")
    options = dict(defaults.get(kind, {}))
    options.update(raw.get("options", {}))
    inputs = _resolve_inputs(inputs, base)
    first = next(iter(inputs.values()))
    first = first[0] if isinstance(first, list) else first
    name = str(raw.get("name", raw.get("out", Path(str(first)).stem)))
    item_out = out / str(raw.get("out", name))
    if not item_out.resolve().is_relative_to(out.resolve()) or item_out.resolve() == out.resolve():
        key = "out" if "out" in raw else "name"
        raise InputError(path, f"{where}.{key}: {raw.get(key)!r} would write outside the batch's "
                               f"result folder {out}")
    if item_out.resolve().parts[len(out.resolve().parts)] in (COMBINED_DIR, BATCH_FILE, RESULT_MARKER):
        key = "out" if "out" in raw else "name"
        raise InputError(path, f"{where}.{key}: {raw.get(key)!r} is the batch's own {COMBINED_DIR}/ or "
                               f"{BATCH_FILE}; give the item another out")
    item = BatchItem(name, kind, inputs, options, item_out)
    where = f"{where} ({name})"
    try:
        facts = CHECKS.get(kind, _generic_check)(item)
        for p in item_paths(item):
            if not p.exists():
                raise InputError(None, f"input {p} not found")
    except InputError as exc:
        raise InputError(path, f"{where}: {exc}") from exc
    return item, facts


def load_manifest(path: Path) -> Manifest:
    """Parse and check a whole manifest before anything runs: every problem (an option's type or
    name, a missing input, a board that does not load, two items on one recording, scan items
    with different grid bins) is an InputError naming the manifest and the item. Why: found at
    the item's turn, earlier items had run for hours first, and batch.json was not written."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "manifest not found")
    try:
        data = tomllib.loads(read_text(path, "batch manifest TOML"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(path, f"broken TOML ({exc})") from exc
    unknown = sorted(set(data) - {"out", "defaults", "items"})
    if unknown:
        raise InputError(path, f"unknown key '{unknown[0]}' (a manifest has out, [defaults.*], [[items]])")
    base = path.parent.resolve()
    if not isinstance(data.get("out", ""), str):
        raise InputError(path, "out must be a folder path (a string)")
    out = Path(str(data.get("out", f"{path.stem}-results"))).expanduser()
    out = out if out.is_absolute() else base / out
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict) or not all(isinstance(v, dict) for v in defaults.values()):
        raise InputError(path, "[defaults] must hold one table per kind ([defaults.scan], ...)")
    for kind in defaults:
        if kind not in KINDS:
            close = difflib.get_close_matches(kind, KINDS, n=1)
            hint = f"did you mean [defaults.{close[0]}]? " if close else ""
            raise InputError(path, f"[defaults.{kind}]: no kind '{kind}' ({hint}kinds: "
                                   f"{', '.join(sorted(KINDS))}); its options would apply to no item")
    raw_items = data.get("items", [])
    if not isinstance(raw_items, list) or not raw_items:
        raise InputError(path, "no [[items]] in the manifest")
    checked = [_check_item(path, k, raw, base, out, defaults) for k, raw in enumerate(raw_items)]
    for k, (item, _) in enumerate(checked):  # the batch writing into an input changes it under the item
        inside = next((p for p in item_paths(item) if _overlap(out, p)), None)
        if inside is not None:
            raise InputError(path, f"items[{k}] ({item.name}): the batch's out {out} is (or holds, or lies "
                                   f"in) its input {inside}: every rerun would find the input changed and "
                                   "redo it; give the batch an out beside its inputs")
    outs = [a.out.resolve() for a, _ in checked]
    reads = [[x.resolve() for x in fa.recordings] for _, fa in checked]
    for j, (b, fb) in enumerate(checked):
        for i, (a, fa) in enumerate(checked[:j]):
            wa, wb = f"items[{i}] ({a.name})", f"items[{j}] ({b.name})"
            if a.name == b.name:
                raise InputError(path, f"{wb}: the name {b.name!r} is also {wa}'s; batch.json and the "
                                       "combined tables know items by name: give each its own")
            if _overlap(outs[i], outs[j], resolved=True):
                raise InputError(path, f"{wb}: out folder {b.out} is (or holds, or lies in) the one of {wa}")
            shared = next((x for x in reads[i] for y in reads[j] if _overlap(x, y, resolved=True)), None)
            if a.kind == b.kind and shared is not None:
                raise InputError(path, f"{wa} and {wb} both read {shared}: the combined result would count "
                                       "its frames twice (double counts, too small U95); one item per "
                                       "recording (to compare options on one recording, use separate "
                                       "batches)")
            if fa.bins is not None and fb.bins is not None and not all(
                    math.isclose(x, y) for x, y in zip(fa.bins, fb.bins, strict=True)):
                raise InputError(path, f"{wb}: grid bins {fb.bins} differ from those of {wa} {fa.bins} "
                                       "(distance_bin_m, inclination_bin_deg, distance_max_m): their grids "
                                       "cannot be combined; set them in [defaults.scan]")
    return Manifest(path, out, [item for item, _ in checked])


# -- running ---------------------------------------------------------------------------------------
def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object from a file of ours, {} when missing or broken (then the item is redone)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def is_done(item: BatchItem) -> bool:
    """Finished = result.json present and the done marker names this item's fingerprint."""
    marker = item.out / DONE_MARKER
    if not (item.out / RESULT_FILE).is_file() or not marker.is_file():
        return False
    return bool(_read_json(marker).get("fingerprint") == item.fingerprint())


def _what_changed(then: dict[str, Any], now: dict[str, Any]) -> str:
    if not now.get("exists", True):
        return "it is gone"
    parts = [what for key, what in (("bytes", "size"), ("mtime_ns", "modification time"),
                                    ("sha256_head_tail", "content"), ("files", "number of files"),
                                    ("sha256_listing", "file names, sizes or times"))
             if then.get(key) != now.get(key)]
    return ", ".join(parts) or "fingerprint"


def changed_inputs(item: BatchItem) -> list[tuple[str, str]]:
    """(path, what changed) for each input of a finished item that differs from the fingerprint
    taken when it ran. Why: the manifest text alone said 'finished' for an item whose recording
    was replaced, and the combined result kept the old numbers. Cheap: size, time and the first
    and last MiB (results.fingerprint), not the whole file. A marker from before the inputs were
    kept in it falls back to result.json's input_fingerprints."""
    stored = _read_json(item.out / DONE_MARKER).get("inputs")
    if not isinstance(stored, list):
        mine = {str(p) for p in item_paths(item)}
        recorded = _read_json(item.out / RESULT_FILE).get("input_fingerprints")
        stored = [f for f in recorded or [] if isinstance(f, dict) and f.get("path") in mine]
    out: list[tuple[str, str]] = []
    for then in stored:
        if not isinstance(then, dict) or "path" not in then:
            continue
        now = fingerprint(then["path"])
        if now != then:
            out.append((str(then["path"]), _what_changed(then, now)))
    return out


def run_item(item: BatchItem, runner: ChunkRunner, progress: ProgressFn | None = None) -> Path | None:
    """Evaluate one item through the runner and write its folder; the done marker comes last."""
    marker = item.out / DONE_MARKER
    marker.unlink(missing_ok=True)
    # taken before reading: an input that changes while the item runs is seen changed next time
    inputs = [fingerprint(p) for p in item_paths(item)]
    # the item's own warnings: its result.json lists them, not those of the items before it (they
    # reach the batch's collector when the item ends)
    with collecting(forward=True) as own_warnings, \
            result_folder(item.out, force=True, inputs=item_paths(item), kind=item.kind) as tmp:
        # the item's folder is written under a temporary name and replaces an unfinished one whole
        job = KINDS[item.kind](replace(item, out=tmp))
        prog = progress or (lambda d, t: None)
        if job.merge is not None:
            if not job.chunks:
                raise EvaluationError(f"{item.name}: nothing to evaluate")
            result: Any = runner.reduce(job.fn, job.chunks, job.merge, progress=prog, encode=job.encode,
                                        decode=job.decode)
        else:
            result = runner.map(job.fn, job.chunks, progress=prog, encode=job.encode, decode=job.decode)
        grid_name = job.finish(result)
        if not (tmp / RESULT_FILE).is_file():
            raise EvaluationError(f"{item.name}: the {item.kind} evaluation wrote no {RESULT_FILE}")
    grid_path = None if grid_name is None else item.out / Path(grid_name).name
    own = [w.to_dict() for w in own_warnings]
    write_json(marker, {"fingerprint": item.fingerprint(), "grid": grid_path, "inputs": inputs,
                        "warnings": own})
    return grid_path


def warn_again(item: BatchItem) -> int:
    """The warnings a finished, skipped item had when it ran, warned again (how many). Why: a
    rerun that only skips said nothing, so --strict passed and combined/result.json listed no
    warning for numbers that carry one."""
    recorded = _read_json(item.out / DONE_MARKER).get("warnings")
    if not isinstance(recorded, list):  # a marker from before warnings were kept in it
        recorded = _read_json(item.out / RESULT_FILE).get("warnings")
    n = 0
    for w in recorded if isinstance(recorded, list) else []:
        if isinstance(w, dict) and isinstance(w.get("message"), str):
            warn(w["message"], w.get("where"), str(w.get("code") or "general"))
            n += 1
    return n


def _item_grid(item: BatchItem) -> Path | None:
    try:
        g = json.loads((item.out / DONE_MARKER).read_text()).get("grid")
    except (OSError, json.JSONDecodeError):
        return None
    return Path(g) if g else None


def combine_grids(paths: Sequence[Path]) -> Grid | None:
    """The items' grids (manifest order) merged into one (Chan), None without any."""
    grid: Grid | None = None
    for p in paths:
        g = Grid.load(p)
        if grid is None:
            grid = g
        elif not grid.compatible(g):
            raise InputError(p, "grid bins differ from the other items' (cannot combine)")
        else:
            grid.merge(g)
    return grid


def combine_tables(tables: Sequence[tuple[str, Path]], out: Path) -> Path:
    """All items' standpoints.csv in one table, an ``item`` column first (fleet comparisons)."""

    rows: list[dict[str, str]] = []
    columns: list[str] = ["item"]
    for name, path in tables:
        with path.open(newline="") as f:
            for row in csv.DictReader(f):
                rows.append({"item": name, **row})
                columns += [c for c in row if c not in columns]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(out)
    return out


COMBINED_FILES = {GRID_FILE, STANDPOINTS_FILE, RESULT_FILE}


def write_combined(man: Manifest) -> Path | None:
    """``combined/``, always with its result.json: the merged grid of the finished scan items,
    their standpoints tables in one, and every warning of the batch (skipped items' included).
    Written whole under a temporary name (no stale grid from an earlier run stays). Returns the
    combined grid's path, None without one."""
    done = [it for it in man.items if is_done(it)]
    grids = [(it.name, g) for it in done if (g := _item_grid(it)) is not None]
    tables = [(it.name, it.out / STANDPOINTS_FILE) for it in done if (it.out / STANDPOINTS_FILE).is_file()]
    grid = combine_grids([g for _, g in grids])
    target = man.out / COMBINED_DIR
    if (target.is_dir() and not (target / RESULT_MARKER).is_file()
            and {p.name for p in target.iterdir()} <= COMBINED_FILES):
        # combined/ of a batch run before it had a marker (a table-only one had no result.json)
        (target / RESULT_MARKER).write_text(json.dumps({"kind": "combined"}) + "\n")
    with result_folder(target, force=True) as tmp:
        if grid is not None:
            grid.save(tmp / GRID_FILE)
        if tables:
            combine_tables(tables, tmp / STANDPOINTS_FILE)
        kind = "combined-grid" if grid is not None else "combined-standpoints" if tables else "combined"
        write_result_info(tmp, kind, [str(g) for _, g in grids] + [str(t) for _, t in tables],
                          {"items": [it.name for it in done], "grid_items": [n for n, _ in grids],
                           "table_items": [n for n, _ in tables]},
                          extra={"summary": grid.summary()} if grid is not None else None)
    return None if grid is None else target / GRID_FILE


BATCH_KIND = "batch"


def claim_out(man: Manifest) -> None:
    """Make sure ``out`` is this manifest's own batch folder (or empty), then mark it so.

    Why: a batch writes batch.json, combined/ and the items' folders into ``out``; pointed at a
    folder of the user's own files, or at another manifest's results, it overwrote them. Its own
    earlier output (the marker naming this manifest, or a batch.json of a batch run before the
    marker existed) is updated; anything else is refused before any item runs."""
    out, mine = man.out, man.path.resolve()
    check_out_path(out, f"the batch's out (in {man.path}) ")
    if out.is_dir() and any(out.iterdir()):
        marker = _read_json(out / RESULT_MARKER)
        legacy = _read_json(out / BATCH_FILE)
        if marker:
            if marker.get("kind") != BATCH_KIND:
                raise InputError(out, f"holds an earlier '{marker.get('kind')}' result, not a batch's; "
                                      f"give the batch in {man.path} another out")
            theirs = Path(str(marker.get("manifest", "")))
            # the same manifest: by its path, or by its place beside out (the campaign folder was
            # copied or moved with its results); one that is gone was renamed or moved
            moved = out.resolve() / str(marker.get("manifest_from_out", ""))
            if theirs != mine and moved.resolve() != mine and theirs.is_file():
                raise InputError(out, f"is the result folder of another manifest ({theirs}); two "
                                      "manifests sharing one out overwrite each other's combined/ and "
                                      f"batch.json: give the batch in {man.path} its own out")
        elif not ({"manifest", "items"} <= set(legacy) and Path(str(legacy["manifest"])).name == mine.name):
            raise InputError(out, f"holds files depthstation did not write (no {RESULT_MARKER}); a "
                                  "batch updates only its own earlier output: give the batch in "
                                  f"{man.path} another out")
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / RESULT_MARKER, {"kind": BATCH_KIND, "manifest": str(mine),
                                     "manifest_from_out": os.path.relpath(mine, out.resolve())})


@dataclass
class BatchReport:
    out: Path
    done: list[str] = field(default_factory=list)      # evaluated in this run
    skipped: list[str] = field(default_factory=list)   # finished before, not redone
    failed: dict[str, str] = field(default_factory=dict)
    combined: Path | None = None


def batch(manifest: Path, cluster: str | None = None, workers: int = 1, *,
          progress: bool = False, log: Callable[[str], None] | None = None) -> BatchReport:
    """Run every unfinished item of the manifest, then merge all items' grids into ``combined/``.

    One pool (or one cluster connection) serves all items; the items run one after another and
    each spreads its chunks over the workers. An item that fails (an input error of its data
    included) is reported, the batch goes on and ends with an EvaluationError (exit 1); an
    interruption (Ctrl-C, a killed process) leaves the unfinished items without their done
    marker, so the next run does them and only them.
    """

    man = load_manifest(manifest)
    say = log or (lambda s: None)
    report = BatchReport(man.out)
    claim_out(man)
    with ChunkRunner(workers, cluster) as runner:
        for item in man.items:
            if is_done(item):
                changed = changed_inputs(item)
                if not changed:
                    report.skipped.append(item.name)
                    n = warn_again(item)
                    said = f" ({n} warning(s) of its run)" if n else ""
                    say(f"{item.name}: finished before, skipped{said}")
                    continue
                for path, what in changed:
                    warn(f"changed since item '{item.name}' finished ({what}): the item is evaluated "
                         "again", path, "batch-input-changed")
                    say(f"{item.name}: input {path} changed ({what}), evaluated again")
            try:
                with progress_bar(f"{item.name} ({item.kind})", progress) as prog:
                    run_item(item, runner, prog)
            except DepthstationError as exc:
                # the manifest was checked whole before: what fails now is this item's data (no
                # usable frame, a board found nowhere), and the other items still have theirs
                report.failed[item.name] = str(exc)
                say(f"{item.name}: failed: {exc}")
                continue
            report.done.append(item.name)
            say(f"{item.name}: done")
    report.combined = write_combined(man)
    write_json(man.out / BATCH_FILE, {
        "manifest": str(man.path), "cluster": cluster, "workers": workers,
        "items": [{"name": it.name, "kind": it.kind, "out": str(it.out), "done": is_done(it),
                   "error": report.failed.get(it.name)} for it in man.items],
        "evaluated": report.done, "skipped": report.skipped,
        "combined_grid": report.combined,
    })
    if report.failed:
        names = ", ".join(report.failed)
        raise EvaluationError(f"{len(report.failed)} item(s) failed: {names} (see {man.out / BATCH_FILE});"
                              " run again to retry them")
    return report


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

    return ItemJob(scan_chunk, job.chunks, finish, merge=merge_scan_results, encode=pack_scan_result,
                   decode=unpack_scan_result, description="frames")


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
