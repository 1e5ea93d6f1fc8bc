"""explain --scan: a simulated room sequence with a concealed disparity offset written by the test."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXE = ROOT / ".venv" / "bin" / "depthstation"


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from depthstation.simulate.scan_sequence import simulate_scan

    out = tmp_path_factory.mktemp("room") / "sim"
    return simulate_scan("room", "walk", "d455", out, frames=24, width=256, height=144, color=False, seed=5)


def _conceal(sim: Path, out: Path, c_per_m: float) -> Path:
    """The sequence with every depth measured c * z^2 too far (what a wrong disparity offset does),
    written here as a z-domain error, not through simulate.effects."""
    from depthstation.core.capture.mcap_writer import write_mcap
    from depthstation.core.capture.registry import open_recording
    from depthstation.core.frames import FrameSet

    rec = open_recording(sim / "sequence.mcap")
    units = rec.info.depth_units_m
    frames = []
    for fs in rec.frames():
        assert fs.depth is not None
        z = fs.depth.astype(np.float64) * units
        z = z + c_per_m * z * z
        depth = np.where(fs.depth > 0, np.clip(np.rint(z / units), 1, 65535), 0).astype(np.uint16)
        frames.append(FrameSet(fs.index, fs.timestamp_ns, depth, fs.color, fs.infrared, dict(fs.metadata)))
    out.mkdir(parents=True)
    write_mcap(out / "sequence.mcap", rec.info, frames, dict(rec.metadata))
    return out / "sequence.mcap"


def test_scan_concealed_disparity_offset(room: Path, tmp_path: Path) -> None:
    c = 4e-3       # 4 mm/m^2: 0.05 px at 256x144 (fB ~ 12 px m), half the per-pixel disparity noise
    real = _conceal(room, tmp_path / "real", c)
    out = tmp_path / "out"
    r = subprocess.run([str(EXE), "explain", "--scan", str(real), "--poses", str(room / "trajectory.txt"),
                        "--reference", str(room / "scene.ply"), "--model", "d455", "--no-icp",
                        "--block-frames", "4", "--out", str(out), "--seed", "2"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((out / "explain.json").read_text())
    info = json.loads((room / "truth.json").read_text())["stream_info"]
    fb = info["baseline_m"] * info["depth_intrinsics"]["fx"]
    assert data["mismatch"]["significant"]
    top = data["candidates"][0]
    assert top["effect"] == "disparity_offset" and top["selected"] and top["role"] == "missing_physics"
    assert top["params"]["offset_px"]["value"] == pytest.approx(-c * fb, rel=0.25)
    assert top["heldout_rmse_after_m"] < top["heldout_rmse_before_m"]
    assert data["selected"] == ["disparity_offset"]
    assert not data["mismatch_after"]["significant"]
    for f in ("model.toml", "report.md", "result.json", "residual_grid.png"):
        assert (out / f).is_file()
    assert "disparity_offset" in (out / "model.toml").read_text()


def test_scan_needs_poses_and_reference(room: Path, tmp_path: Path) -> None:
    r = subprocess.run([str(EXE), "explain", "--scan", str(room / "sequence.mcap"),
                        "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--poses" in r.stderr


def test_scan_null_selects_nothing(room: Path, tmp_path: Path) -> None:
    """The same sequence with no hidden effect: no missing physics, no significant mismatch."""
    real = _conceal(room, tmp_path / "real", 0.0)
    out = tmp_path / "out"
    r = subprocess.run([str(EXE), "explain", "--scan", str(real), "--poses", str(room / "trajectory.txt"),
                        "--reference", str(room / "scene.ply"), "--model", "d455", "--no-icp",
                        "--block-frames", "4", "--out", str(out), "--seed", "2", "--no-resimulate"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((out / "explain.json").read_text())
    assert data["selected"] == []
    assert not data["mismatch"]["significant"]
