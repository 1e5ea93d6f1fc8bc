"""The batch's ``combined/`` folder: the finished items' grids merged, their tables in one."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE, Grid
from depthstation.core.results import RESULT_FILE, RESULT_MARKER, result_folder, write_result_info
from depthstation.evaluate.batch_kinds import BatchItem
from depthstation.evaluate.batch_manifest import COMBINED_DIR, DONE_MARKER, Manifest, is_done

STANDPOINTS_FILE = "standpoints.csv"


def merge_grids(a: Grid, b: Grid) -> Grid:
    """Chan merge of two partial grids (folds into ``a``)."""
    return a.merge(b)


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
