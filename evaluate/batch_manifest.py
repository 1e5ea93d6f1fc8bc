"""The batch manifest: read whole and checked before any item runs; when an item counts as done.

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

The kinds, their items and their checks: :mod:`depthstation.evaluate.batch_kinds`.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from depthstation.core.errors import InputError
from depthstation.core.results import RESULT_FILE, RESULT_MARKER
from depthstation.core.text_files import read_text
from depthstation.core.tomlcompat import tomllib
from depthstation.evaluate.batch_kinds import (
    CHECKS,
    KINDS,
    BatchItem,
    ItemCheck,
    _generic_check,
    _overlap,
    item_paths,
)

DONE_MARKER = ".done"
COMBINED_DIR = "combined"
BATCH_FILE = "batch.json"


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
