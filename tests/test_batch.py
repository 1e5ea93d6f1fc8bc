"""Batch runs: a result folder per item, a combined grid equal to one pass over everything,
and an interrupted batch redoes only what was unfinished.

The item kind here is a small synthetic grid evaluation registered by the test (its chunk
function reads (distance, inclination, error) samples of a frame range from a .npy file); the
truth is a two-pass numpy mean/variance per cell over all samples of all items.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.app.cli import run_cli
from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE, Grid, pack_grid, unpack_grid
from depthstation.core.parallel import FrameChunk, frame_chunks
from depthstation.core.results import write_result_info
from depthstation.core.run_warnings import collecting, warn
from depthstation.evaluate import batch as batch_mod
from depthstation.evaluate.batch import (
    DONE_MARKER,
    BatchItem,
    ItemJob,
    batch,
    load_manifest,
    merge_grids,
)

EDGES_D = np.linspace(0.0, 6.0, 13)    # 0.5 m bins
EDGES_I = np.linspace(0.0, 90.0, 10)   # 10 degree bins


def synth_chunk(chunk: FrameChunk) -> Grid:
    """Partial grid of frames [start, stop); logs the call; obeys fault flags next to the file."""
    base = Path(chunk.path)
    with (base.parent / "calls.log").open("a") as f:
        f.write(f"{base.stem}:{chunk.index}\n")
    flag = base.with_suffix(".interrupt")
    if chunk.index == 1 and flag.exists():
        mode = flag.read_text()
        flag.unlink()
        if mode == "kill":
            os._exit(9)  # the whole batch process dies mid-item
        raise KeyboardInterrupt
    data = np.load(chunk.path, mmap_mode="r")[chunk.start:chunk.stop]
    grid = Grid.with_edges(EDGES_D, EDGES_I)
    grid.add(data[..., 0], data[..., 1], data[..., 2])
    return grid


def prepare_synth(item: BatchItem) -> ItemJob:
    path = Path(item.inputs["samples"])
    n = np.load(path, mmap_mode="r").shape[0]

    def finish(grid: Grid) -> Path:
        out = grid.save(item.out / GRID_FILE)
        write_result_info(item.out, "synthetic-grid", [str(path)], item.options)
        return out

    return ItemJob(synth_chunk, frame_chunks(path, n, int(item.options.get("chunk_frames", 3))),
                   finish, merge=merge_grids, encode=pack_grid, decode=unpack_grid)


@pytest.fixture(autouse=True)
def synth_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(batch_mod.KINDS, "synthgrid", prepare_synth)


def make_samples(path: Path, seed: int, frames: int = 10) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.3, 5.9, (frames, 200))
    a = rng.uniform(0.0, 89.0, (frames, 200))
    err = 0.002 * d**2 + rng.normal(0, 0.001 * d)
    data = np.stack([d, a, err], axis=-1)
    np.save(path, data)
    return data


def write_manifest(root: Path, names: list[str], extra: str = "") -> Path:
    lines = [f'out = "results"\n{extra}\n[defaults.synthgrid]\nchunk_frames = 3\n']
    for n in names:
        lines.append(f'[[items]]\nkind = "synthgrid"\nname = "{n}"\ninputs = {{ samples = "{n}.npy" }}\n')
    path = root / "campaign.toml"
    path.write_text("\n".join(lines))
    return path


def truth(datas: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.concatenate([d.reshape(-1, 3) for d in datas])
    k = np.digitize(x[:, 0], EDGES_D) - 1
    j = np.digitize(x[:, 1], EDGES_I) - 1
    cell = k * (EDGES_I.size - 1) + j
    size = (EDGES_D.size - 1) * (EDGES_I.size - 1)
    count = np.bincount(cell, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(cell, x[:, 2], minlength=size) / count
        var = np.bincount(cell, (x[:, 2] - mean[cell]) ** 2, minlength=size) / (count - 1)
    shape = (EDGES_D.size - 1, EDGES_I.size - 1)
    return count.reshape(shape), mean.reshape(shape), var.reshape(shape)


def calls(root: Path) -> list[str]:
    log = root / "calls.log"
    return log.read_text().split() if log.exists() else []


def assert_grid_is_truth(path: Path, datas: list[np.ndarray]) -> None:
    g = Grid.load(path)
    count, mean, var = truth(datas)
    np.testing.assert_array_equal(g.count, count)
    ok = count > 1
    np.testing.assert_allclose(g.mean_m[ok], mean[ok], rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(g.var[ok], var[ok], rtol=1e-8, atol=1e-18)


def test_pack_grid_is_exact_and_small() -> None:
    g = Grid.empty()  # the DESIGN grid, 1200 x 900
    rng = np.random.default_rng(0)
    g.add(rng.uniform(1, 1.5, 50_000), rng.uniform(10, 20, 50_000), rng.normal(0, 0.01, 50_000))
    p = pack_grid(g)
    back = unpack_grid(p)
    for a, b in ((g.count, back.count), (g.mean, back.mean), (g.m2, back.m2)):
        np.testing.assert_array_equal(a, b)
    dense = g.count.nbytes + g.mean.nbytes + g.m2.nbytes
    assert p.nbytes < dense / 20, (p.nbytes, dense)


def test_batch_results_combined_grid_and_resume(tmp_path: Path) -> None:
    names = ["seq_a", "seq_b", "seq_c"]
    datas = [make_samples(tmp_path / f"{n}.npy", seed=i) for i, n in enumerate(names)]
    manifest = write_manifest(tmp_path, names)
    report = batch(manifest, workers=1)
    assert report.done == names and not report.skipped
    out = tmp_path / "results"
    for n, d in zip(names, datas, strict=True):
        assert (out / n / "result.json").is_file() and (out / n / DONE_MARKER).is_file()
        assert_grid_is_truth(out / n / GRID_FILE, [d])
    assert_grid_is_truth(out / "combined" / GRID_FILE, datas)
    assert json.loads((out / "combined" / "result.json").read_text())["kind"] == "combined-grid"
    first = calls(tmp_path)
    assert len(first) == 3 * 4  # 10 frames in chunks of 3: 4 chunks per item, each read once
    again = batch(manifest, workers=1)
    assert again.skipped == names and not again.done
    assert calls(tmp_path) == first  # nothing re-read


def test_interrupted_batch_redoes_only_unfinished(tmp_path: Path) -> None:
    names = ["seq_a", "seq_b", "seq_c"]
    datas = [make_samples(tmp_path / f"{n}.npy", seed=10 + i) for i, n in enumerate(names)]
    manifest = write_manifest(tmp_path, names)
    (tmp_path / "seq_b.interrupt").write_text("interrupt")
    with pytest.raises(KeyboardInterrupt):
        batch(manifest, workers=2)
    out = tmp_path / "results"
    assert (out / "seq_a" / DONE_MARKER).is_file()
    assert not (out / "seq_b" / DONE_MARKER).exists() and not (out / "seq_c").exists()
    before = calls(tmp_path)
    report = batch(manifest, workers=2)
    assert report.skipped == ["seq_a"] and report.done == ["seq_b", "seq_c"]
    redone = calls(tmp_path)[len(before):]
    assert not [c for c in redone if c.startswith("seq_a")]
    # as sets: the interrupted run's other worker may still finish its chunk after the interrupt
    # (the pool is not waited for on Ctrl-C) and log it late, inside the second run's share
    assert sorted(set(redone)) == sorted({f"{n}:{i}" for n in ("seq_b", "seq_c") for i in range(4)})
    assert_grid_is_truth(out / "combined" / GRID_FILE, datas)


def test_killed_batch_process_resumes(tmp_path: Path) -> None:
    names = ["seq_a", "seq_b"]
    datas = [make_samples(tmp_path / f"{n}.npy", seed=20 + i) for i, n in enumerate(names)]
    manifest = write_manifest(tmp_path, names)
    (tmp_path / "seq_b.interrupt").write_text("kill")
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        import test_batch
        from depthstation.evaluate import batch as b
        b.KINDS["synthgrid"] = test_batch.prepare_synth
        b.batch(b.Path({str(manifest)!r}), workers=1)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 9, proc.stderr
    out = tmp_path / "results"
    assert (out / "seq_a" / DONE_MARKER).is_file() and not (out / "seq_b" / DONE_MARKER).exists()
    report = batch(manifest)
    assert report.skipped == ["seq_a"] and report.done == ["seq_b"]
    assert_grid_is_truth(out / "combined" / GRID_FILE, datas)


def test_changed_item_is_redone(tmp_path: Path) -> None:
    make_samples(tmp_path / "seq_a.npy", seed=1)
    manifest = write_manifest(tmp_path, ["seq_a"])
    batch(manifest)
    manifest.write_text(manifest.read_text().replace("chunk_frames = 3", "chunk_frames = 5"))
    assert batch(manifest).done == ["seq_a"]


def test_item_whose_input_changed_is_redone_and_said(tmp_path: Path) -> None:
    names = ["seq_a", "seq_b"]
    datas = [make_samples(tmp_path / f"{n}.npy", seed=30 + i) for i, n in enumerate(names)]
    manifest = write_manifest(tmp_path, names)
    batch(manifest)
    datas[0] = make_samples(tmp_path / "seq_a.npy", seed=99)  # the recording replaced, same size
    lines: list[str] = []
    with collecting() as found:
        report = batch(manifest, log=lines.append)
    assert report.done == ["seq_a"] and report.skipped == ["seq_b"]
    assert [(w.code, w.where) for w in found] == [("batch-input-changed", str(tmp_path / "seq_a.npy"))]
    assert any("seq_a.npy changed" in line for line in lines)
    # the combined grid holds the new recording, not the old one
    assert_grid_is_truth(tmp_path / "results" / "combined" / GRID_FILE, datas)
    assert batch(manifest).skipped == names  # fingerprints taken again: nothing changed since


def table_chunk(path: str) -> list[str]:
    return Path(path).read_text().split()


def prepare_table(item: BatchItem) -> ItemJob:
    """A checkerboard-like item: a standpoints table, no grid, and a warning of its run."""
    path = Path(item.inputs["samples"])

    def finish(results: list[list[str]]) -> None:
        warn("board not found in 1 of 3 frames", results[0][0], "board-not-found")
        (item.out / "standpoints.csv").write_text("standpoint,distance_m\n" + f"{results[0][0]},1.5\n")
        write_result_info(item.out, "checkerboard", [str(path)], {})

    return ItemJob(table_chunk, [str(path)], finish)


def test_warnings_of_finished_items_come_back_on_rerun(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(batch_mod.KINDS, "synthtable", prepare_table)
    (tmp_path / "pose03.txt").write_text("pose03")
    manifest = tmp_path / "m.toml"
    manifest.write_text('out = "res"\n[[items]]\nkind = "synthtable"\ninputs = { samples = "pose03.txt" }\n')
    combined = tmp_path / "res" / "combined" / "result.json"
    for run in ("first", "rerun"):
        assert run_cli(["evaluate", "batch", str(manifest), "--quiet", "--strict"]) == 3, run
        info = json.loads(combined.read_text())  # a table-only batch gets its result.json too
        assert info["kind"] == "combined-standpoints", run
        assert [(w["where"], w["code"]) for w in info["warnings"]] == [("pose03", "board-not-found")], run
    assert json.loads((tmp_path / "res" / "batch.json").read_text())["skipped"] == ["pose03"]


def test_batch_refuses_an_out_it_did_not_write(tmp_path: Path) -> None:
    make_samples(tmp_path / "seq_a.npy", seed=1)
    manifest = write_manifest(tmp_path, ["seq_a"])
    mine = {tmp_path / "results" / "batch.json": "my notes\n",
            tmp_path / "results" / "combined" / "standpoints.csv": "standpoint,distance_m\nmine,1.0\n"}
    for path, text in mine.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    with pytest.raises(InputError, match="did not write"):
        batch(manifest)
    assert {p: p.read_text() for p in mine} == mine
    assert not (tmp_path / "results" / "seq_a").exists() and calls(tmp_path) == []


def test_two_manifests_sharing_one_out_are_refused(tmp_path: Path) -> None:
    datas = [make_samples(tmp_path / f"{n}.npy", seed=i) for i, n in enumerate(["seq_a", "seq_b"])]
    first = write_manifest(tmp_path, ["seq_a"])
    batch(first)
    second = tmp_path / "other.toml"
    second.write_text(first.read_text().replace("seq_a", "seq_b"))
    with pytest.raises(InputError, match="another manifest"):
        batch(second)
    assert not (tmp_path / "results" / "seq_b").exists()
    assert_grid_is_truth(tmp_path / "results" / "combined" / GRID_FILE, datas[:1])
    copy = tmp_path / "copy"  # the campaign folder copied with its results: still its own out
    shutil.copytree(tmp_path, copy, ignore=shutil.ignore_patterns("copy"))
    again = batch(copy / first.name)  # (its inputs' paths changed: the item is evaluated again)
    assert again.done + again.skipped == ["seq_a"]


def test_failed_item_is_reported_and_others_finish(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from depthstation.core.errors import EvaluationError

    def prepare_maybe_fail(item: BatchItem) -> Any:
        if item.name == "seq_a":
            raise EvaluationError("no usable frame")
        return prepare_synth(item)

    monkeypatch.setitem(batch_mod.KINDS, "synthgrid", prepare_maybe_fail)
    datas = [make_samples(tmp_path / f"{n}.npy", seed=i) for i, n in enumerate(["seq_a", "seq_b"])]
    manifest = write_manifest(tmp_path, ["seq_a", "seq_b"])
    with pytest.raises(EvaluationError, match="1 item\\(s\\) failed: seq_a"):
        batch(manifest)
    info = json.loads((tmp_path / "results" / "batch.json").read_text())
    assert [i["done"] for i in info["items"]] == [False, True]
    assert_grid_is_truth(tmp_path / "results" / "combined" / GRID_FILE, datas[1:])


@pytest.mark.parametrize(("text", "match"), [
    ("", "no \\[\\[items\\]\\]"),
    ('[[items]]\nkind = "nope"\ninputs = { a = "x" }\n', "kind 'nope' is not one of"),
    ('[[items]]\nkind = "synthgrid"\n', "inputs must be a non-empty table"),
    ("out = [", "broken TOML"),
])
def test_bad_manifest_is_input_error(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "m.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=match):
        load_manifest(path)


BOARD = Path(__file__).parents[1] / "protocols" / "demo-d455.toml"


def scan_item(name: str, options: str = "", poses: bool = True) -> str:
    p = f'poses = "{name}.txt", ' if poses else ""
    return (f'[[items]]\nkind = "scan"\nname = "{name}"\n'
            f'inputs = {{ sequence = "{name}.mcap", {p}reference = "room.ply" }}\n'
            f'options = {{ {options} }}\n')


def cb_item(name: str, options: str = "", inputs: str = '["sess"]', board: str = str(BOARD)) -> str:
    return (f'[[items]]\nkind = "checkerboard"\nname = "{name}"\n'
            f'inputs = {{ inputs = {inputs}, board = "{board}" }}\noptions = {{ {options} }}\n')


def real_kinds_manifest(root: Path, text: str) -> Path:
    """A manifest of scan and checkerboard items on placeholder files: loading checks them
    without opening any recording (poses and references are read: small valid ones)."""
    for name in ("s1.mcap", "s2.mcap", "sess/standpoint_01.mcap"):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).touch()
    for name in ("s1.txt", "s2.txt"):  # poses and the reference are read at the check: well-formed ones
        (root / name).write_text("0.0 0 0 0 0 0 0 1\n")
    (root / "room.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                   "property float y\nproperty float z\nelement face 1\n"
                                   "property list uchar int vertex_indices\nend_header\n"
                                   "0 0 1\n1 0 1\n0 1 1\n3 0 1 2\n")
    path = root / "m.toml"
    path.write_text('out = "res"\n' + text)
    return path


@pytest.mark.parametrize(("text", "match"), [
    # the same recording in two items (or twice in one) would count twice in the combined result
    (scan_item("s1") + scan_item("s1").replace('name = "s1"', 'name = "again"'),
     r"items\[0\] \(s1\) and items\[1\] \(again\) both read .*s1.mcap"),
    (cb_item("a") + cb_item("b", inputs='["sess/standpoint_01.mcap"]'),
     r"items\[0\] \(a\) and items\[1\] \(b\) both read .*sess"),
    (cb_item("a", inputs='["sess", "sess"]'), r"items\[0\] \(a\): inputs.inputs names .*sess.* twice"),
    # a typo in a defaults table
    ("[defaults.checkerbaord]\nframes = 3\n" + cb_item("a"), r"did you mean \[defaults.checkerboard\]"),
    # option values of the wrong type, said instead of misread
    (cb_item("a", "frames = true"), r"items\[0\] \(a\): option frames must be a whole number, not true"),
    (cb_item("a", "frames = 2.7"), r"option frames must be a whole number, not 2.7"),
    (cb_item("a", 'frames = "abc"'), r'option frames must be a whole number, not "abc"'),
    (scan_item("s1", "distance_max_m = true"), r"option distance_max_m must be a number, not true"),
    (scan_item("s1", 'icp = "false"'), r'option icp must be true or false, not "false"'),
    (scan_item("s1", "chunk_frames = 2.5"), r"option chunk_frames must be a whole number"),
    # the rest found before any item runs, naming the item
    (cb_item("a", "frames = -1"), r"items\[0\] \(a\): option frames must be at least 1"),
    (cb_item("a", 'reference = "avg"'), r"option reference must be one of auto, average, frame"),
    (cb_item("a", "frame = 3"), r"unknown checkerboard option 'frame' \(did you mean 'frames'\?\)"),
    (cb_item("a", board="nope.json"), r"items\[0\] \(a\): .*nope.json.*not found"),
    (cb_item("a", inputs="5"), r"items\[0\]: inputs.inputs must be a path or a list of paths, not 5"),
    (scan_item("s1", poses=False), r"items\[0\] \(s1\): a scan item needs inputs .* poses missing"),
    (scan_item("s1") + scan_item("s2", "distance_bin_m = 0.01"),
     r"items\[1\] \(s2\): grid bins .* differ from those of items\[0\] \(s1\)"),
    # two items of one name: batch.json gave one's done with the other's error
    (scan_item("s1") + scan_item("s2").replace('name = "s2"', 'name = "s1"'),
     r"items\[1\] \(s1\): the name 's1' is also items\[0\] \(s1\)'s"),
])
def test_real_kinds_manifest_errors_name_manifest_and_item(tmp_path: Path, text: str, match: str) -> None:
    path = real_kinds_manifest(tmp_path, text)
    with pytest.raises(InputError, match=match) as exc:
        load_manifest(path)
    assert str(exc.value).startswith(f"{path}: ")


def test_a_batch_out_inside_an_input_is_refused(tmp_path: Path) -> None:
    """Its result folder inside a session it evaluates: every rerun found the session changed (by
    the batch itself), redid the item and warned."""
    path = real_kinds_manifest(tmp_path, cb_item("a"))
    path.write_text(path.read_text().replace('out = "res"', 'out = "sess/batch"'))
    with pytest.raises(InputError, match=r"items\[0\] \(a\): the batch's out .*sess/batch is .* its input "
                                         r".*sess: every rerun"):
        load_manifest(path)


def test_right_option_types_load(tmp_path: Path) -> None:
    text = (scan_item("s1", "distance_max_m = 6, icp = false, chunk_frames = 2, icp_band_m = [0.5, 2]")
            + cb_item("a", 'frames = 3, reference = "average"'))
    items = load_manifest(real_kinds_manifest(tmp_path, text)).items
    assert items[0].options == {"distance_max_m": 6, "icp": False, "chunk_frames": 2, "icp_band_m": [0.5, 2]}
    assert items[1].options == {"frames": 3, "reference": "average"}


def test_manifest_checked_whole_before_any_item_runs(tmp_path: Path) -> None:
    make_samples(tmp_path / "seq_a.npy", seed=1)
    manifest = write_manifest(tmp_path, ["seq_a"])
    manifest.write_text(manifest.read_text()
                        + '[[items]]\nkind = "synthgrid"\ninputs = { samples = "gone.npy" }\n')
    with pytest.raises(InputError, match=r"campaign.toml: items\[1\] \(gone\): input .*gone.npy not found"):
        batch(manifest)
    assert calls(tmp_path) == [] and not (tmp_path / "results").exists()


def test_an_items_result_lists_its_own_warnings_not_those_of_the_items_before(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each item's result.json speaks for its numbers: a warning of the first item (a board not
    found at pose03) must not appear in the second item's file; the batch lists both."""
    monkeypatch.setitem(batch_mod.KINDS, "synthtable", prepare_table)
    (tmp_path / "pose03.txt").write_text("pose03")
    (tmp_path / "pose04.txt").write_text("pose04")
    manifest = tmp_path / "m.toml"
    manifest.write_text('out = "res"\n'
                        '[[items]]\nkind = "synthtable"\ninputs = { samples = "pose03.txt" }\n'
                        '[[items]]\nkind = "synthtable"\ninputs = { samples = "pose04.txt" }\n')
    assert run_cli(["evaluate", "batch", str(manifest), "--quiet"]) == 0
    for name in ("pose03", "pose04"):
        info = json.loads((tmp_path / "res" / name / "result.json").read_text())
        assert [w["where"] for w in info["warnings"]] == [name], name
    combined = json.loads((tmp_path / "res" / "combined" / "result.json").read_text())
    assert sorted(w["where"] for w in combined["warnings"]) == ["pose03", "pose04"]


def test_a_batch_called_outside_a_command_still_says_its_items_warnings(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setitem(batch_mod.KINDS, "synthtable", prepare_table)
    (tmp_path / "pose03.txt").write_text("pose03")
    manifest = tmp_path / "m.toml"
    manifest.write_text('out = "res"\n[[items]]\nkind = "synthtable"\ninputs = { samples = "pose03.txt" }\n')
    with caplog.at_level("WARNING", logger="depthstation.warnings"):
        batch(manifest)
    assert any("pose03: board not found" in r.getMessage() for r in caplog.records)
