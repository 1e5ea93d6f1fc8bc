"""A batch of real items: two simulated room sequences (scan) and a real ChArUco standpoint
(checkerboard), on 2 local workers; the combined grid equals the two one-pass grids merged and
the combined table holds the checkerboard rows."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")


def make_scan_item(root: Path, name: str, seed: int) -> dict[str, Path]:
    import open3d as o3d

    from depthstation.evaluate.scan.synthetic import Room, make_sequence, write_tum_folder
    from depthstation.evaluate.scan.trajectory import write_tum

    room = Room()
    seq = make_sequence(frames=6, width=64, height=48, room=room, seed=seed)
    folder = write_tum_folder(seq, root / name)
    poses = write_tum(root / f"{name}.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    mesh = root / "room.ply"
    if not mesh.exists():
        o3d.io.write_triangle_mesh(str(mesh), room.mesh(segments=64))  # type: ignore[arg-type]
    sim = root / "identity.txt"
    np.savetxt(sim, np.eye(4))
    return {"sequence": folder, "poses": poses, "reference": mesh, "similarity": sim}


def test_batch_of_scans_and_checkerboard(tmp_path: Path, charuco_dir: Path) -> None:
    from depthstation.core.grid import GRID_FILE, Grid
    from depthstation.core.parallel import ChunkRunner
    from depthstation.evaluate.batch import batch
    from depthstation.evaluate.scan.chunks import run_scan_chunks
    from depthstation.evaluate.scan.study import StudyConfig
    from depthstation.evaluate.scan.trajectory import read_tum

    items = {n: make_scan_item(tmp_path, n, s) for n, s in (("room_a", 1), ("room_b", 2))}
    opts = 'options = { icp = false, chunk_frames = 2, distance_bin_m = 0.05, inclination_bin_deg = 1.0 }'
    text = ['out = "res"']
    for n, inp in items.items():
        fields = ", ".join(f'{k} = "{v}"' for k, v in inp.items())
        text.append(f'[[items]]\nkind = "scan"\nname = "{n}"\ninputs = {{ {fields} }}\n{opts}\n')
    cb = f'inputs = ["{charuco_dir / "pose03"}"], board = "{charuco_dir / "board.json"}"'
    text.append(f'[[items]]\nkind = "checkerboard"\nname = "d435"\ninputs = {{ {cb} }}\n'
                'options = { frames = 3 }\n')
    manifest = tmp_path / "m.toml"
    manifest.write_text("\n".join(text))
    report = batch(manifest, workers=2)
    assert report.done == ["room_a", "room_b", "d435"]
    out = tmp_path / "res"
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=1.0)
    expected = None
    for n, inp in items.items():
        with ChunkRunner(1) as serial:
            one = run_scan_chunks(inp["sequence"], inp["reference"], read_tum(inp["poses"]), config,
                                  serial).grid
        got = Grid.load(out / n / GRID_FILE)
        np.testing.assert_array_equal(got.count, one.count)
        np.testing.assert_allclose(got.mean, one.mean, rtol=1e-9, atol=1e-15)
        expected = one if expected is None else expected.merge(one)
    assert expected is not None and expected.total > 1000
    combined = Grid.load(out / "combined" / GRID_FILE)
    np.testing.assert_array_equal(combined.count, expected.count)
    np.testing.assert_allclose(combined.mean, expected.mean, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(combined.m2, expected.m2, rtol=1e-8, atol=1e-18)
    with (out / "combined" / "standpoints.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(r["item"], r["standpoint"]) for r in rows] == [("d435", "pose03")]
    assert (out / "d435" / "standpoints.csv").is_file() and (out / "d435" / "result.json").is_file()
    assert batch(manifest, workers=2).skipped == ["room_a", "room_b", "d435"]


def test_item_without_usable_frame_fails_alone(tmp_path: Path, charuco_dir: Path, d435_bag: Path) -> None:
    """A recording with no board in it fails its item (exit 1 at the end, as docs/scale-out.md
    says), and the item after it still runs."""
    from depthstation.app.cli import run_cli

    board = charuco_dir / "board.json"
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        f'out = "res"\n[defaults.checkerboard]\nframes = 2\n'
        f'[[items]]\nkind = "checkerboard"\nname = "bag"\n'
        f'inputs = {{ inputs = "{d435_bag}", board = "{board}" }}\n'
        f'[[items]]\nkind = "checkerboard"\nname = "ok"\n'
        f'inputs = {{ inputs = "{charuco_dir / "pose03"}", board = "{board}" }}\n')
    assert run_cli(["evaluate", "batch", str(manifest), "--quiet"]) == 1
    info = json.loads((tmp_path / "res" / "batch.json").read_text())
    assert [(i["name"], i["done"]) for i in info["items"]] == [("bag", False), ("ok", True)]
    assert "frame" in info["items"][0]["error"]
    with (tmp_path / "res" / "combined" / "standpoints.csv").open() as f:
        assert [(r["item"], r["standpoint"]) for r in csv.DictReader(f)] == [("ok", "pose03")]
