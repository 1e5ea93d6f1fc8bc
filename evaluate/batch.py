"""Many evaluations in one run: a manifest of items, a result folder each, a combined grid.

Why a manifest: a mapping campaign (dozens of sequences) or a fleet of cameras (several sessions
each) is run overnight, on a cluster, and must survive an interruption. Each item is one scan or
checkerboard evaluation; its frames or standpoints go out as chunks through
:mod:`depthstation.parallel`; an item counts as finished only when its folder holds
``result.json`` *and* the done marker, which is written last, so a restart redoes exactly the
items that were not finished (and an item whose manifest entry changed).

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

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from numpy.typing import NDArray

from depthstation.errors import DepthstationError, EvaluationError, InputError
from depthstation.parallel import ChunkRunner, ProgressFn
from depthstation.results import RESULT_FILE, write_json, write_result_info
from evaluate.grid import GRID_FILE, Grid

DONE_MARKER = ".done"
COMBINED_DIR = "combined"
BATCH_FILE = "batch.json"
STANDPOINTS_FILE = "standpoints.csv"


# -- what travels: a grid as its non-empty cells ---------------------------------------------------
@dataclass
class PackedGrid:
    """The non-empty cells of a :class:`Grid`: a partial grid of one chunk fills a few percent of
    the 1200 x 900 cells, so this is ~28 bytes per used cell instead of 26 MB dense."""

    distance_edges_m: NDArray[np.float64]
    inclination_edges_deg: NDArray[np.float64]
    cells: NDArray[np.int32]  # flat (distance, inclination) index, C order
    count: NDArray[np.int64]
    mean: NDArray[np.float64]
    m2: NDArray[np.float64]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.distance_edges_m, self.inclination_edges_deg, self.cells,
                                      self.count, self.mean, self.m2))


def pack_grid(grid: Grid) -> PackedGrid:
    """Keep only the cells with samples (exact: the same floats come back)."""
    cells = np.flatnonzero(grid.count).astype(np.int32)
    return PackedGrid(grid.distance_edges_m, grid.inclination_edges_deg, cells,
                      grid.count.ravel()[cells], grid.mean.ravel()[cells], grid.m2.ravel()[cells])


def unpack_grid(packed: PackedGrid) -> Grid:
    grid = Grid.with_edges(packed.distance_edges_m, packed.inclination_edges_deg)
    grid.count.ravel()[packed.cells] = packed.count
    grid.mean.ravel()[packed.cells] = packed.mean
    grid.m2.ravel()[packed.cells] = packed.m2
    return grid


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
    else it gets the list. ``finish`` writes ``result.json`` and returns the item's grid file or
    None (then the item does not enter the combined grid).
    """

    fn: Callable[[Any], Any]
    chunks: Sequence[Any]
    finish: Callable[[Any], Path | None]
    merge: Callable[[Any, Any], Any] | None = None
    encode: Callable[[Any], Any] | None = None
    decode: Callable[[Any], Any] | None = None
    description: str = ""


#: kind -> function preparing the job of an item (runs in this process: loads what is small,
#: decides the chunks; the heavy reading happens in the chunk function on the workers).
KINDS: dict[str, Callable[[BatchItem], ItemJob]] = {}


def register_kind(kind: str, prepare: Callable[[BatchItem], ItemJob]) -> None:
    KINDS[kind] = prepare


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


def load_manifest(path: Path) -> Manifest:
    """Parse and check a manifest; every problem is an InputError naming the item."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "manifest not found")
    try:
        data = tomllib.loads(path.read_text())
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(path, f"broken TOML ({exc})") from exc
    base = path.parent.resolve()
    out = Path(str(data.get("out", f"{path.stem}-results"))).expanduser()
    out = out if out.is_absolute() else base / out
    defaults = data.get("defaults", {})
    raw_items = data.get("items", [])
    if not isinstance(raw_items, list) or not raw_items:
        raise InputError(path, "no [[items]] in the manifest")
    items: list[BatchItem] = []
    seen: set[Path] = set()
    for k, raw in enumerate(raw_items):
        where = f"items[{k}]"
        if not isinstance(raw, dict):
            raise InputError(path, f"{where} is not a table")
        kind = raw.get("kind")
        if kind not in KINDS:
            known = ", ".join(sorted(KINDS)) or "none"
            raise InputError(path, f"{where}: kind {kind!r} is not one of {known}")
        inputs = raw.get("inputs", {})
        if not isinstance(inputs, dict) or not inputs:
            raise InputError(path, f"{where}: inputs must be a non-empty table")
        options = dict(defaults.get(kind, {}))
        options.update(raw.get("options", {}))
        inputs = _resolve_inputs(inputs, base)
        first = next(iter(inputs.values()))
        first = first[0] if isinstance(first, list) else first
        name = str(raw.get("name", raw.get("out", Path(str(first)).stem)))
        item_out = out / str(raw.get("out", name))
        if item_out in seen:
            raise InputError(path, f"{where}: out folder {item_out} is used by another item")
        seen.add(item_out)
        items.append(BatchItem(name, kind, inputs, options, item_out))
    return Manifest(path, out, items)


# -- running ---------------------------------------------------------------------------------------
def is_done(item: BatchItem) -> bool:
    """Finished = result.json present and the done marker names this item's fingerprint."""
    marker = item.out / DONE_MARKER
    if not (item.out / RESULT_FILE).is_file() or not marker.is_file():
        return False
    try:
        return bool(json.loads(marker.read_text()).get("fingerprint") == item.fingerprint())
    except (json.JSONDecodeError, AttributeError):
        return False


def run_item(item: BatchItem, runner: ChunkRunner, progress: ProgressFn | None = None) -> Path | None:
    """Evaluate one item through the runner and write its folder; the done marker comes last."""
    marker = item.out / DONE_MARKER
    marker.unlink(missing_ok=True)
    job = KINDS[item.kind](item)
    prog = progress or (lambda d, t: None)
    if job.merge is not None:
        if not job.chunks:
            raise EvaluationError(f"{item.name}: nothing to evaluate")
        result: Any = runner.reduce(job.fn, job.chunks, job.merge, progress=prog, encode=job.encode,
                                    decode=job.decode)
    else:
        result = runner.map(job.fn, job.chunks, progress=prog, encode=job.encode, decode=job.decode)
    grid_path = job.finish(result)
    if not (item.out / RESULT_FILE).is_file():
        raise EvaluationError(f"{item.name}: the {item.kind} evaluation wrote no {RESULT_FILE}")
    write_json(marker, {"fingerprint": item.fingerprint(), "grid": grid_path})
    return grid_path


def _item_grid(item: BatchItem) -> Path | None:
    try:
        g = json.loads((item.out / DONE_MARKER).read_text()).get("grid")
    except (OSError, json.JSONDecodeError):
        return None
    return Path(g) if g else None


def combine_grids(paths: Sequence[Path], out_dir: Path, inputs: Sequence[str]) -> Grid | None:
    """Merge the items' grids (manifest order) into ``out_dir/grid.npz`` with its result.json."""
    grid: Grid | None = None
    for p in paths:
        g = Grid.load(p)
        if grid is None:
            grid = g
        elif not grid.compatible(g):
            raise InputError(p, "grid bins differ from the other items' (cannot combine)")
        else:
            grid.merge(g)
    if grid is None:
        return None
    grid.save(out_dir / GRID_FILE)
    write_result_info(out_dir, "combined-grid", [str(p) for p in paths], {"items": list(inputs)},
                      extra={"summary": grid.summary()})
    return grid


def combine_tables(tables: Sequence[tuple[str, Path]], out: Path) -> Path:
    """All items' standpoints.csv in one table, an ``item`` column first (fleet comparisons)."""
    import csv

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
    each spreads its chunks over the workers. An item that fails is reported and the batch goes
    on; an interruption (Ctrl-C, a killed process) leaves the unfinished items without their
    done marker, so the next run does them and only them.
    """
    from depthstation.parallel import progress_bar

    man = load_manifest(manifest)
    say = log or (lambda s: None)
    report = BatchReport(man.out)
    man.out.mkdir(parents=True, exist_ok=True)
    with ChunkRunner(workers, cluster) as runner:
        for item in man.items:
            if is_done(item):
                report.skipped.append(item.name)
                say(f"{item.name}: finished before, skipped")
                continue
            try:
                with progress_bar(f"{item.name} ({item.kind})", progress) as prog:
                    run_item(item, runner, prog)
            except InputError:
                raise
            except DepthstationError as exc:
                report.failed[item.name] = str(exc)
                say(f"{item.name}: failed: {exc}")
                continue
            report.done.append(item.name)
            say(f"{item.name}: done")
    grids = [(it.name, g) for it in man.items if is_done(it) and (g := _item_grid(it)) is not None]
    if grids:
        combine_grids([g for _, g in grids], man.out / COMBINED_DIR, [n for n, _ in grids])
        report.combined = man.out / COMBINED_DIR / GRID_FILE
    tables = [(it.name, it.out / STANDPOINTS_FILE) for it in man.items
              if is_done(it) and (it.out / STANDPOINTS_FILE).is_file()]
    if tables:
        combine_tables(tables, man.out / COMBINED_DIR / STANDPOINTS_FILE)
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


# -- the reference-scan study in chunks ------------------------------------------------------------
@dataclass(frozen=True)
class ScanChunk:
    """Frames [start, start+limit) of a sequence: paths and poses travel, pixels are read there."""

    sequence: str
    mesh: str
    trajectory: Any  # evaluate.scan.trajectory.Trajectory, camera-to-reference (registration applied)
    config: Any      # evaluate.scan.study.StudyConfig
    start: int
    limit: int
    intrinsics: str | None = None


# One mesh scene and one open sequence per worker process, reused by its following chunks: the
# mesh is loaded once per worker, not per chunk; only one is kept (bounded memory).
_SCAN_CACHE: dict[str, Any] = {}


def _scan_context(chunk: ScanChunk) -> tuple[Any, Any]:
    from evaluate.scan.raycast import MeshCaster
    from evaluate.scan.sequence import open_sequence

    key_src = (chunk.sequence, chunk.intrinsics)
    if _SCAN_CACHE.get("source_key") != key_src:
        _SCAN_CACHE["source"] = open_sequence(Path(chunk.sequence),
                                              Path(chunk.intrinsics) if chunk.intrinsics else None)
        _SCAN_CACHE["source_key"] = key_src
    source = _SCAN_CACHE["source"]
    key_mesh = (chunk.mesh, source.info.depth_intrinsics, chunk.config.nthreads)
    if _SCAN_CACHE.get("mesh_key") != key_mesh:
        _SCAN_CACHE.pop("caster", None)
        _SCAN_CACHE["caster"] = MeshCaster(Path(chunk.mesh), source.info.depth_intrinsics,
                                           chunk.config.nthreads)
        _SCAN_CACHE["mesh_key"] = key_mesh
    return _SCAN_CACHE["caster"], source


def scan_chunk(chunk: ScanChunk) -> Any:
    """Partial scan result (grid + pixel counts + frames used) of one chunk, on the worker."""
    from evaluate.scan.study import evaluate_chunk

    caster, source = _scan_context(chunk)
    return evaluate_chunk(caster, source, chunk.trajectory, chunk.config, chunk.start, chunk.limit)


@dataclass
class PackedScanResult:
    grid: PackedGrid
    stats: NDArray[np.int64]
    used: list[int]
    no_pose: list[int]
    no_depth: list[int]


def pack_scan_result(res: Any) -> PackedScanResult:
    return PackedScanResult(pack_grid(res.grid), res.stats, res.used, res.no_pose, res.no_depth)


def unpack_scan_result(p: PackedScanResult) -> Any:
    from evaluate.scan.study import ChunkResult

    return ChunkResult(unpack_grid(p.grid), p.stats, p.used, p.no_pose, p.no_depth)


def merge_scan_results(a: Any, b: Any) -> Any:
    return a.merge(b)


def scan_chunks(sequence: Path, mesh: Path, trajectory: Any, config: Any, *, chunk_frames: int = 64,
                intrinsics: Path | None = None) -> list[ScanChunk]:
    """The chunks of a scan evaluation (the frame count comes from the sequence's index only)."""
    from evaluate.scan.sequence import open_sequence
    from evaluate.scan.study import chunk_ranges

    source = open_sequence(Path(sequence), intrinsics)
    n = source.frame_count
    if n is None:
        raise InputError(sequence, "the sequence does not say how many frames it holds; "
                                   "cannot split it into chunks")
    if config.max_frames is not None:
        n = min(n, config.max_frames * config.every)
    return [ScanChunk(str(sequence), str(mesh), trajectory, config, s, lim,
                      None if intrinsics is None else str(intrinsics))
            for s, lim in chunk_ranges(n, chunk_frames)]


def run_scan(sequence: Path, mesh: Path, trajectory: Any, config: Any, *, chunk_frames: int = 64,
             workers: int = 1, cluster: str | None = None, intrinsics: Path | None = None,
             progress: ProgressFn | None = None, runner: ChunkRunner | None = None) -> Any:
    """The scan study's ChunkResult over the whole sequence, chunks run serially, in local
    processes or on a Dask cluster; partial grids travel as their non-empty cells."""
    chunks = scan_chunks(sequence, mesh, trajectory, config, chunk_frames=chunk_frames,
                         intrinsics=intrinsics)
    own = runner is None
    run = runner if runner is not None else ChunkRunner(workers, cluster)
    try:
        if own:
            run.__enter__()
        return run.reduce(scan_chunk, chunks, merge_scan_results, progress=progress or (lambda d, t: None),
                          encode=pack_scan_result, decode=unpack_scan_result)
    finally:
        if own:
            run.close()


# -- the checkerboard study in chunks: one standpoint per task ---------------------------------------
@dataclass(frozen=True)
class CheckerboardChunk:
    """One standpoint: the recording's path (opened and read by the worker) and the study options."""

    path: str
    board: Any  # depthstation.board.Board (a small dataclass)
    frames: int = 150
    options: tuple[tuple[str, Any], ...] = ()


def checkerboard_chunk(chunk: CheckerboardChunk) -> Any:
    """StandpointResult of one standpoint, evaluated where it is read."""
    from depthstation.capture.reader import open_recording
    from evaluate.checkerboard.study import evaluate_recording

    rec = open_recording(Path(chunk.path))
    return evaluate_recording(rec, chunk.board, frames=chunk.frames, **dict(chunk.options))


def checkerboard_chunks(inputs: Sequence[Path], board: Any, *, frames: int = 150,
                        **options: Any) -> list[CheckerboardChunk]:
    """Expand sessions / dataset roots into standpoints (index only, no frames read here)."""
    from depthstation.capture.reader import open_inputs

    recs = open_inputs([Path(p) for p in inputs])
    if not recs:
        raise InputError(None, "no standpoint recordings found in the inputs")
    opts = tuple(sorted(options.items()))
    return [CheckerboardChunk(str(r.path), board, frames, opts) for r in recs]


def run_checkerboard(inputs: Sequence[Path], board: Any, *, frames: int = 150, workers: int = 1,
                     cluster: str | None = None, progress: ProgressFn | None = None,
                     runner: ChunkRunner | None = None, **options: Any) -> list[Any]:
    """StandpointResults of every standpoint in input order, standpoints spread over the workers.

    ``options`` go to ``evaluate_recording`` (collect_samples, refine, reference, ...).
    """
    chunks = checkerboard_chunks(inputs, board, frames=frames, **options)
    if runner is not None:
        return runner.map(checkerboard_chunk, chunks, progress=progress or (lambda d, t: None))
    with ChunkRunner(workers, cluster) as run:
        return run.map(checkerboard_chunk, chunks, progress=progress or (lambda d, t: None))


# -- manifest kinds --------------------------------------------------------------------------------
def _prepare_checkerboard(item: BatchItem) -> ItemJob:
    """Item inputs: ``inputs`` (path or list: sessions, recordings, PNG folders), ``board``.
    Options: ``frames`` (150), ``reference`` (auto|average|frame)."""
    from depthstation.board import load_board
    from depthstation.capture.reader import open_recording
    from evaluate.checkerboard.report import write_study

    raw = item.inputs.get("inputs")
    if raw is None or "board" not in item.inputs:
        raise InputError(None, f"{item.name}: a checkerboard item needs inputs.inputs and inputs.board")
    paths = [Path(p) for p in (raw if isinstance(raw, list) else [raw])]
    board_path = Path(item.inputs["board"])
    board = load_board(board_path)
    frames = int(item.options.get("frames", 150))
    reference = str(item.options.get("reference", "auto"))
    chunks = checkerboard_chunks(paths, board, frames=frames, reference=reference)

    def finish(results: list[Any]) -> Path | None:
        if not any(r.usable for r in results):
            raise EvaluationError(f"{item.name}: no usable frame in any of {len(results)} standpoints")
        first = open_recording(Path(chunks[0].path))
        device = dict(first.metadata.get("device") or first.info.device or {})
        params = {"board": str(board_path), "frames": frames, "reference": reference}
        write_study(item.out, results, board, [str(p) for p in paths], params, device)
        return None

    return ItemJob(checkerboard_chunk, chunks, finish, description="standpoints")


def _prepare_scan(item: BatchItem) -> ItemJob:
    """Item inputs: ``sequence``, ``poses`` (TUM), ``reference`` (mesh or cloud), optional
    ``similarity`` (4x4 text), ``pass_points`` (CSV), ``intrinsics``. Options: ``chunk_frames``
    (64), ``icp`` (true), grid bins and frame selection of the scan study's StudyConfig."""
    from dataclasses import fields

    from evaluate.scan.reference import reference_mesh, sample_reference_points
    from evaluate.scan.registration import read_pass_points, read_similarity, register
    from evaluate.scan.sequence import open_sequence
    from evaluate.scan.study import StudyConfig
    from evaluate.scan.trajectory import read_tum

    need = [k for k in ("sequence", "poses", "reference") if k not in item.inputs]
    if need:
        raise InputError(None, f"{item.name}: a scan item needs inputs {', '.join(need)}")
    opts = dict(item.options)
    chunk_frames = int(opts.pop("chunk_frames", 64))
    icp = bool(opts.pop("icp", True))
    names = {f.name for f in fields(StudyConfig)} - {"per_frame_dir"}
    unknown = sorted(set(opts) - names)
    if unknown:
        raise InputError(None, f"{item.name}: unknown scan options {', '.join(unknown)}")
    config = StudyConfig(**opts)
    seq_path = Path(item.inputs["sequence"])
    intr = Path(item.inputs["intrinsics"]) if "intrinsics" in item.inputs else None
    item.out.mkdir(parents=True, exist_ok=True)
    mesh, mesh_path, mesh_info = reference_mesh(Path(item.inputs["reference"]), item.out)
    trajectory = read_tum(Path(item.inputs["poses"]))
    sim = read_similarity(Path(item.inputs["similarity"])) if "similarity" in item.inputs else None
    pp = read_pass_points(Path(item.inputs["pass_points"])) if "pass_points" in item.inputs else None
    if icp or pp is not None or sim is None:
        source = open_sequence(seq_path, intr)
        reg = register(source, trajectory, mesh, sample_reference_points(mesh), similarity=sim,
                       pass_points=pp, icp=icp, tolerance_s=config.tolerance_s)
        matrix, registration = reg.matrix, reg.to_dict()
    else:
        matrix, registration = sim, {"method": "given", "matrix": sim.tolist()}
    posed = trajectory.transformed(matrix)
    chunks = scan_chunks(seq_path, mesh_path, posed, config, chunk_frames=chunk_frames, intrinsics=intr)

    def finish(res: Any) -> Path:
        grid_path = res.grid.save(item.out / GRID_FILE)
        summary = {"inputs": item.inputs, "registration": registration, "mesh": mesh_info,
                   "chunks": len(chunks), "chunk_frames": chunk_frames, **res.summary()}
        write_json(item.out / "summary.json", summary)
        write_result_info(item.out, "scan", [str(v) for v in item.inputs.values()],
                          {**item.options, "chunk_frames": chunk_frames},
                          extra={"files": [GRID_FILE, "summary.json"]})
        return Path(grid_path)

    return ItemJob(scan_chunk, chunks, finish, merge=merge_scan_results, encode=pack_scan_result,
                   decode=unpack_scan_result, description="frames")


register_kind("scan", _prepare_scan)
register_kind("checkerboard", _prepare_checkerboard)
