"""Many evaluations in one run: a manifest of items, a result folder each, a combined grid.

Why a manifest: a mapping campaign (dozens of sequences) or a fleet of cameras (several sessions
each) is run overnight, on a cluster, and must survive an interruption. Each item is one scan or
checkerboard evaluation; its frames or standpoints go out as chunks through
:mod:`depthstation.parallel`; an item counts as finished only when its folder holds
``result.json`` *and* the done marker, which is written last, so a restart redoes exactly the
items that were not finished, an item whose manifest entry changed and an item whose inputs
changed (size, time or the SHA-256 of their first and last MiB: cheap on a GB recording).

The manifest and its checks: :mod:`depthstation.evaluate.batch_manifest`; the kinds (scan,
checkerboard) and their items: :mod:`depthstation.evaluate.batch_kinds`; the combined folder:
:mod:`depthstation.evaluate.batch_combine`. Here: running a batch (claiming its folder, resuming).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from depthstation.core.errors import DepthstationError, EvaluationError, InputError
from depthstation.core.parallel import ChunkRunner, ProgressFn, progress_bar
from depthstation.core.results import (
    RESULT_FILE,
    RESULT_MARKER,
    check_out_path,
    fingerprint,
    result_folder,
    write_json,
)
from depthstation.core.run_warnings import collecting, warn
from depthstation.evaluate.batch_combine import (
    COMBINED_FILES,
    STANDPOINTS_FILE,
    combine_grids,
    combine_tables,
    merge_grids,
    write_combined,
)
from depthstation.evaluate.batch_kinds import (
    CHECKERBOARD_OPTIONS,
    CHECKS,
    KINDS,
    SCAN_PATHS,
    BatchItem,
    ItemCheck,
    ItemJob,
    check_value,
    item_paths,
    register_kind,
)
from depthstation.evaluate.batch_manifest import (
    BATCH_FILE,
    COMBINED_DIR,
    DONE_MARKER,
    Manifest,
    _read_json,
    is_done,
    load_manifest,
)

# the batch's names as they were before the split into batch_kinds, batch_manifest, batch_combine
__all__ = [
    "BATCH_FILE", "BATCH_KIND", "CHECKERBOARD_OPTIONS", "CHECKS", "COMBINED_DIR", "COMBINED_FILES",
    "DONE_MARKER", "KINDS", "SCAN_PATHS", "STANDPOINTS_FILE", "BatchItem", "BatchReport", "ItemCheck",
    "ItemJob", "Manifest", "batch", "changed_inputs", "check_value", "claim_out", "combine_grids",
    "combine_tables", "is_done", "item_paths", "load_manifest", "merge_grids", "register_kind",
    "run_item", "warn_again", "write_combined",
]


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
        if job.after is not None:
            job.after(result, runner)
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
