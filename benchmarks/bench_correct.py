"""`depthstation correct` speed at 1280x720 against reading and writing the same recording without
correction (same reader, same writer, same compression, measured in the same run), and the proof
figures on the tests' own room (tests/test_error_model_room.py): a model fitted on walk A, walk B
corrected, its scan study's cell means and a TSDF map against the room.

    .venv/bin/python benchmarks/bench_correct.py [--frames 60] [--no-proof] [--repeat 3]

Prints frames/s of the baseline copy, of `correct` (with and without --sigma), of the kernel
alone, and the ratios; then the proof figures; with --png a figure of walk B's cell means before
and after.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import test_error_model_room as room

from depthstation.app.cli import run_cli
from depthstation.core.camera_model import ray_planes
from depthstation.core.capture import mcap_writer as mw
from depthstation.core.capture.registry import open_recording
from depthstation.core.grid import Grid
from depthstation.evaluate.errormodel.correct import correct_recording
from depthstation.evaluate.errormodel.kernels import Corrector
from depthstation.evaluate.errormodel.schema import load_model


def copy_recording(src: Path, dst: Path) -> int:
    """The baseline: every frame set read and written again unchanged (what `correct` does minus
    the correction)."""
    rec = open_recording(src)
    with mw.McapFileWriter(dst, rec.info, {k: v for k, v in rec.metadata.items() if k != "format"},
                           compression=mw.CAPTURE_COMPRESSION) as w:
        for fs in rec.frames():
            w.write(fs)
        return w.frames_written


def speed(root: Path, model: Path, frames: int, repeat: int) -> None:
    w = room.walk(1.0, 1.3, 10.0, frames, seed=5, width=1280, height_px=720)
    seq, _ = room.write_walk(w, root / "hd")
    mb = seq.stat().st_size / 2**20
    print(f"recording: {frames} frame sets of 1280x720 depth + rgb8 colour, lz4, {mb:.0f} MiB")
    # the model fitted at 160x120 is a model of that camera: for speed only its numbers matter
    m = load_model(model)
    m.camera["resolution"] = None
    fast = root / "model_hd.json"
    from depthstation.evaluate.errormodel.cli import write_model

    write_model(m, fast)
    rows: dict[str, list[float]] = {"copy (read + write)": [], "correct": [], "correct --sigma": [],
                                    "kernel alone": []}
    rec = open_recording(seq)
    depth = [np.array(fs.depth) for fs in rec.frames()]
    x, y = ray_planes(rec.info.depth_intrinsics)
    corr = Corrector(m, np.asarray(x), np.asarray(y), room.UNITS, room.UNITS, threads=2)
    corr(depth[0], True)   # compiled (numba caches it on disk) before any timing
    for k in range(repeat):
        for name in rows:
            t0 = time.perf_counter()
            if name == "copy (read + write)":
                copy_recording(seq, root / f"copy{k}.mcap")
            elif name == "kernel alone":
                for d in depth:
                    corr(d, False)
            else:
                correct_recording(seq, fast, root / f"{name.replace(' ', '')}{k}", sigma="sigma" in name)
            rows[name].append(frames / (time.perf_counter() - t0))
    corr.close()
    base = np.median(rows["copy (read + write)"])
    print(f"{'':22s} frames/s (median of {repeat})   ratio to the copy")
    for name, v in rows.items():
        print(f"{name:22s} {np.median(v):8.1f}  ({min(v):.1f}-{max(v):.1f})   {np.median(v) / base:6.2f}")
    print(f"on {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")


def proof(root: Path, png: Path | None) -> Path:
    a = room.walk(0.8, 1.4, 0.0, 20, seed=1)
    b = room.walk(1.2, 1.1, 40.0, 20, seed=2)
    sa, ta = room.write_walk(a, root / "a")
    sb, tb = room.write_walk(b, root / "b")
    mesh = room.write_room_mesh(root / "room.ply")
    args = ["--distance-bin-m", "0.05", "--inclination-bin-deg", "1", "--min-count-sequence", "50"]
    for name, seq, traj in (("scan_a", sa, ta), ("scan_b", sb, tb)):
        assert run_cli(["evaluate", "scan", "--sequence", str(seq), "--poses", str(traj), "--reference",
                        str(mesh), "--out", str(root / name), *args]) == 0
    model = root / "model.json"
    assert run_cli(["model", "fit", str(root / "scan_a"), "--out", str(model), "--min-count", "100"]) == 0
    assert run_cli(["correct", str(sb), "--model", str(model), "--out", str(root / "fixed")]) == 0
    fixed = root / "fixed" / "sequence.mcap"
    assert run_cli(["evaluate", "scan", "--sequence", str(fixed), "--poses", str(tb), "--reference",
                    str(mesh), "--out", str(root / "scan_c"), *args]) == 0
    m = load_model(model)
    raw, cor = Grid.load(root / "scan_b" / "grid.npz"), Grid.load(root / "scan_c" / "grid.npz")
    zc = np.broadcast_to(raw.distance_centers_m[:, None], raw.shape)
    tc = np.broadcast_to(raw.inclination_centers_deg[None, :], raw.shape)
    ok = (raw.count >= 50) & (cor.count >= 50) & m.domain.contains(zc, tc)
    w = raw.count[ok]
    before = np.average(np.abs(raw.mean_m[ok]), weights=w)
    after = np.average(np.abs(cor.mean_m[ok]), weights=w)
    s_raw, s_cor = np.average(raw.std[ok], weights=w), np.average(cor.std[ok], weights=w)
    print(f"walk B, {ok.sum()} cells in the model's domain: mean |cell mean| {before * 1e3:.2f} mm raw, "
          f"{after * 1e3:.2f} mm corrected ({after / before:.3f}x); std {s_raw * 1e3:.2f} -> "
          f"{s_cor * 1e3:.2f} mm")
    from test_error_model import _tsdf_error

    fixed_depth = [np.asarray(fs.depth) for fs in open_recording(fixed).frames()]
    e_raw, e_fix = _tsdf_error(b, b.depth), _tsdf_error(b, fixed_depth)
    print(f"TSDF (UniformTSDFVolume 6.4 m / 192, true poses): mean |map - room| {e_raw * 1e3:.2f} mm raw, "
          f"{e_fix * 1e3:.2f} mm corrected ({e_fix / e_raw:.3f}x)")
    if png is not None:
        _figure(raw, cor, ok, png)
    return model


def _figure(raw: Grid, cor: Grid, ok: Any, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from depthstation.core.heatmaps import SIGNED, colormap

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    ext = [raw.distance_edges_m[0], raw.distance_edges_m[-1], raw.inclination_edges_deg[0],
           raw.inclination_edges_deg[-1]]
    for a, g, title in ((ax[0], raw, "walk B raw"), (ax[1], cor, "walk B corrected (model of walk A)")):
        img = np.where(ok, g.mean_m * 1e3, np.nan).T
        im = a.imshow(img, origin="lower", aspect="auto", extent=ext, cmap=colormap(SIGNED), vmin=-40,
                      vmax=40)
        a.set_xlim(1.0, 4.0)
        a.set_ylim(0, 75)
        a.set_xlabel("distance z (m)")
        a.set_ylabel("inclination (deg)")
        a.set_title(f"{title}: cell mean error (mm)")
        fig.colorbar(im, ax=a, label="mm")
    fig.savefig(png, dpi=100)
    print(f"-> {png}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-proof", action="store_true")
    ap.add_argument("--png", type=Path, default=None)
    opt = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_correct_"))
    try:
        model = proof(root / "proof", opt.png) if not opt.no_proof else None
        if model is None:
            w = room.walk(0.8, 1.4, 0.0, 12, seed=1)
            sa, ta = room.write_walk(w, root / "a")
            assert run_cli(["evaluate", "scan", "--sequence", str(sa), "--poses", str(ta), "--reference",
                            str(room.write_room_mesh(root / "room.ply")), "--out", str(root / "scan_a"),
                            "--distance-bin-m", "0.05", "--inclination-bin-deg", "1"]) == 0
            model = root / "model.json"
            assert run_cli(["model", "fit", str(root / "scan_a"), "--out", str(model),
                            "--min-count", "50"]) == 0
        speed(root, model, opt.frames, opt.repeat)
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
