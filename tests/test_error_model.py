"""The depth error model end to end on the tests' own box room (tests/test_error_model_room.py, not
the simulator): fit on one walk's scan study, correct a second walk of the same camera (another
radius, height and start), and check what the study, a TSDF map and the exports see."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import test_error_model_room as room

from depthstation.app.cli import run_cli
from depthstation.core.capture import rosmsgs
from depthstation.core.capture.mcap_reader import mcap_messages
from depthstation.core.capture.registry import open_recording
from depthstation.core.errors import InputError
from depthstation.core.grid import Grid
from depthstation.evaluate.errormodel.correct import SIGMA_TOPIC, correct_recording
from depthstation.evaluate.errormodel.kernels import Corrector
from depthstation.evaluate.errormodel.schema import SCHEMA_VERSION, load_model

SCAN_ARGS = ["--distance-bin-m", "0.05", "--inclination-bin-deg", "1", "--min-count-sequence", "50"]
FRAMES = 20


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Walk A (fit) and walk B (corrected), both studied; the model of A; B corrected and studied."""
    root = tmp_path_factory.mktemp("errormodel")
    a = room.walk(0.8, 1.4, 0.0, FRAMES, seed=1)
    b = room.walk(1.2, 1.1, 40.0, FRAMES, seed=2)
    sa, ta = room.write_walk(a, root / "a")
    sb, tb = room.write_walk(b, root / "b")
    mesh = room.write_room_mesh(root / "room.ply")
    for name, seq, traj in (("scan_a", sa, ta), ("scan_b", sb, tb)):
        assert run_cli(["evaluate", "scan", "--sequence", str(seq), "--poses", str(traj), "--reference",
                        str(mesh), "--out", str(root / name), *SCAN_ARGS]) == 0
    assert run_cli(["model", "fit", str(root / "scan_a"), "--out", str(root / "model.json"),
                    "--min-count", "100"]) == 0
    assert run_cli(["correct", str(sb), "--model", str(root / "model.json"), "--out", str(root / "corrected"),
                    "--sigma"]) == 0
    corrected = root / "corrected" / "sequence.mcap"
    assert run_cli(["evaluate", "scan", "--sequence", str(corrected), "--poses", str(tb), "--reference",
                    str(mesh), "--out", str(root / "scan_c"), *SCAN_ARGS]) == 0
    return {"root": root, "a": a, "b": b, "seq_b": sb, "traj_b": tb, "mesh": mesh,
            "model": root / "model.json", "corrected": corrected}


def test_fit_recovers_the_known_field(world: dict[str, Any]) -> None:
    m = load_model(world["model"])
    z, t = np.meshgrid(np.linspace(1.4, 3.6, 23), np.linspace(2, 65, 22))
    b, s, inside = m.evaluate(z, t)
    assert inside.mean() > 0.5
    truth_b = room.bias_m(z, t)
    # the field reaches 40 mm: the model holds it to a millimetre wherever it was measured
    assert np.nanmax(np.abs(b - truth_b)) < 1e-3
    # sigma: within 0.4 mm (the cells' std also holds the bias's variation inside a 0.1 m x 5 deg cell)
    assert np.nanmax(np.abs(s - room.sigma_m(z))) < 4e-4
    assert np.all(np.isnan(b[~inside]))       # no silent extrapolation
    doc = json.loads(world["model"].read_text())
    assert doc["schema_version"] == SCHEMA_VERSION
    assert doc["camera"]["serial_number"] == "TEST0001" and doc["camera"]["resolution"] == [160, 120]
    assert doc["camera"]["model"] == "D455"
    v = doc["bias"]["validation"]
    assert v["done"] and "held-out cells" in v["unit"]
    assert v["rms_residual_m"] < 0.1 * v["rms_raw_m"]
    # the physical terms put in are found, each far beyond its standard error
    coef = dict(zip(doc["bias"]["terms"], doc["bias"]["coefficients"], strict=True))
    se = dict(zip(doc["bias"]["terms"], doc["bias"]["std_errors"], strict=True))
    for term, want in (("offset", room.B_OFFSET), ("disparity", room.B_DISP), ("inclination", room.B_INCL)):
        assert term in coef
        assert abs(coef[term] - want) < max(5 * se[term], 0.1 * want), (term, coef[term], se[term])
    rows = doc["measured"]["rows"]
    assert rows and {"distance_m", "inclination_deg", "count", "mean_m", "std_m", "u95_m"} <= set(rows[0])


def _domain_cells(world: dict[str, Any], raw: Grid, fixed: Grid, min_count: int = 50) -> np.ndarray:
    m = load_model(world["model"])
    zc = np.broadcast_to(raw.distance_centers_m[:, None], raw.shape)
    tc = np.broadcast_to(raw.inclination_centers_deg[None, :], raw.shape)
    return (raw.count >= min_count) & (fixed.count >= min_count) & m.domain.contains(zc, tc)


def test_corrected_walk_cell_means_shrink(world: dict[str, Any]) -> None:
    """Walk B's study: cell means within the model's domain drop to at most 20 % of the raw ones."""
    raw = Grid.load(world["root"] / "scan_b" / "grid.npz")
    fixed = Grid.load(world["root"] / "scan_c" / "grid.npz")
    ok = _domain_cells(world, raw, fixed)
    assert ok.sum() > 500
    w = raw.count[ok]
    before = np.average(np.abs(raw.mean_m[ok]), weights=w)
    after = np.average(np.abs(fixed.mean_m[ok]), weights=w)
    assert before > 0.01
    assert after <= 0.2 * before, (before, after)
    # the spread: the inclination taken from noisy depth adds a little of its own, b's slope in theta
    # times the normal's error, which grows as 1 / cos^2: under 5 % below 50 deg (docs/error-model.md)
    low = ok & (np.broadcast_to(raw.inclination_centers_deg[None, :], raw.shape) < 50)
    wl = raw.count[low]
    assert np.average(fixed.std[low], weights=wl) <= 1.05 * np.average(raw.std[low], weights=wl)


def test_corrected_recording_keeps_frames_stamps_colour_and_metadata(world: dict[str, Any]) -> None:
    raw = open_recording(world["seq_b"])
    fixed = open_recording(world["corrected"])
    assert fixed.frame_count == raw.frame_count == FRAMES
    assert fixed.info.depth_units_m == raw.info.depth_units_m
    assert fixed.metadata["device"]["serial_number"] == "TEST0001"
    assert fixed.metadata["correction"]["sigma_topic"] == SIGMA_TOPIC
    m = load_model(world["model"])
    summary = json.loads((world["root"] / "corrected" / "correction.json").read_text())
    assert summary["stats"]["frames"] == FRAMES
    for fr, ff, truth in zip(raw.frames(), fixed.frames(), world["b"].truth, strict=True):
        assert (fr.index, fr.timestamp_ns) == (ff.index, ff.timestamp_ns)
        assert fr.color is not None and ff.color is not None and np.array_equal(fr.color, ff.color)
        assert fr.depth is not None and ff.depth is not None
        assert np.array_equal(fr.depth > 0, ff.depth > 0)
        changed = fr.depth != ff.depth
        # what was corrected moved towards the truth by the model's bias
        err_raw = np.abs(fr.depth.astype(float) - truth)[changed]
        err_fix = np.abs(ff.depth.astype(float) - truth)[changed]
        assert err_fix.mean() < 0.5 * err_raw.mean()
    # the sigma image: its own topic, the model's sigma where corrected, NaN where no depth
    topics: dict[int, str] = {}
    with world["corrected"].open("rb") as f:
        sig = [rosmsgs.image_array(rosmsgs.deserialize(d, rosmsgs.IMAGE))
               for c, _, d in mcap_messages(f, topics) if topics.get(c) == SIGMA_TOPIC]
    assert len(sig) == FRAMES
    first = next(iter(fixed.frames()))
    assert first.depth is not None
    z = first.depth.astype(float) * fixed.info.depth_units_m
    ok = np.isfinite(sig[0])
    assert ok.sum() > 0.5 * (first.depth > 0).sum() and not ok[first.depth == 0].any()
    # sigma evaluated at the corrected depth; the inclination from the depth within a few degrees
    expect = np.maximum(m.sigma.value(z[ok], np.zeros(ok.sum())), 0)
    assert np.median(np.abs(sig[0][ok] - expect)) < 3e-4


def test_inclination_from_the_depth_matches_the_room(world: dict[str, Any]) -> None:
    """The per-pixel normals `correct` takes from the depth alone against the ray cast's truth."""
    w = world["b"]
    intr = w.info.depth_intrinsics
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    x, y = (u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy
    corr = Corrector(load_model(world["model"]), x, y, room.UNITS, room.UNITS, threads=2)
    try:
        _, _, cos, _ = corr(w.depth[3], False)
        theta = corr.degrees(cos)
    finally:
        corr.close()
    _, truth = room.cast(intr, w.poses[3])
    ok = np.isfinite(theta) & (w.depth[3] > 0)
    assert ok.mean() > 0.9
    diff = np.abs(theta[ok] - truth[ok])
    assert np.median(diff) < 1.0 and np.percentile(diff, 90) < 4.0


def _tsdf_error(w: room.Walk, depth: list[np.ndarray]) -> float:
    """Mean distance of a TSDF map's vertices (Open3D's UniformTSDFVolume, true poses) to the walls.
    The reader's depth arrays carry an explicit little-endian dtype ('<u2'), which Open3D's Image
    refuses: `astype('=u2')` (docs/error-model.md)."""
    from depthstation.core.lazy_open3d import open3d

    o3d = open3d()
    intr = w.info.depth_intrinsics
    cam = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy)
    vol = o3d.pipelines.integration.UniformTSDFVolume(
        length=6.4, resolution=192, sdf_trunc=0.12,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor, origin=np.array([-0.2, -0.2, -0.2]))
    blank = o3d.geometry.Image(np.zeros((intr.height, intr.width, 3), np.uint8))
    for d, pose in zip(depth, w.poses, strict=True):
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            blank, o3d.geometry.Image(np.asarray(d).astype("=u2")), depth_scale=1.0 / room.UNITS,
            depth_trunc=6.0, convert_rgb_to_intensity=False)
        vol.integrate(rgbd, cam, np.linalg.inv(pose))
    pts = np.asarray(vol.extract_triangle_mesh().vertices)
    assert len(pts) > 1000
    return float(np.mean(room.wall_distance(pts)))


def test_tsdf_map_from_corrected_depth_is_closer_to_the_room(world: dict[str, Any]) -> None:
    fixed = [fs.depth for fs in open_recording(world["corrected"]).frames()]
    raw_err = _tsdf_error(world["b"], world["b"].depth)
    fixed_err = _tsdf_error(world["b"], [np.asarray(d) for d in fixed])
    assert raw_err > 0.005
    assert fixed_err <= 0.5 * raw_err, (raw_err, fixed_err)


@pytest.mark.parametrize("target", ["tum", "rosbag2"])
def test_corrected_recording_exports(world: dict[str, Any], tmp_path: Path, target: str) -> None:
    out = tmp_path / target
    assert run_cli(["capture", "export", str(world["corrected"]), "--to", target, "--out", str(out)]) == 0
    if target == "tum":
        folder = next(p for p in out.rglob("depth.txt")).parent
        text = (folder / "depth.txt").read_text().splitlines()
        lines = [ln for ln in text if ln and not ln.startswith("#")]
        assert len(lines) == FRAMES
    else:
        assert any(out.rglob("metadata.yaml"))


def test_model_show_writes_a_figure(world: dict[str, Any], tmp_path: Path) -> None:
    png = tmp_path / "m.png"
    assert run_cli(["model", "show", str(world["model"]), "--png", str(png)]) == 0
    assert png.stat().st_size > 20_000
    assert run_cli(["model", "show", str(world["model"]), "--png", str(png)]) == 2   # never overwritten


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    for w in words:
        assert w in err[0], err


def _edited_model(world: dict[str, Any], tmp_path: Path, edit: Any) -> Path:
    doc = json.loads(world["model"].read_text())
    edit(doc)
    p = tmp_path / "edited.json"
    p.write_text(json.dumps(doc))
    return p


@pytest.mark.parametrize(("edit", "words"), [
    (lambda d: d["camera"].update(resolution=[1280, 720]), ("edited.json", "resolution", "1280x720")),
    (lambda d: d["camera"].update(model="D435"), ("edited.json", "camera.model", "D435")),
    (lambda d: d["camera"].update(serial_number="OTHER9"), ("edited.json", "serial", "OTHER9")),
    (lambda d: d.update(schema_version=SCHEMA_VERSION + 1), ("edited.json", "schema_version")),
    (lambda d: d.pop("bias"), ("edited.json", "bias")),
])
def test_bad_model_is_refused(world: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str],
                              edit: Any, words: tuple[str, ...]) -> None:
    model = _edited_model(world, tmp_path, edit)
    capsys.readouterr()
    out = tmp_path / "out"
    assert run_cli(["correct", str(world["seq_b"]), "--model", str(model), "--out", str(out)]) == 2
    _one_error_line(capsys, *words)
    assert not out.exists() and not list(tmp_path.glob(".out.partial-*"))


def test_sequence_without_depth_is_refused(world: dict[str, Any], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """An MCAP written with the mcap library itself: the station's metadata, a colour topic, no depth."""
    from mcap.writer import Writer

    path = tmp_path / "nodepth.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        w.add_metadata("streams", {"json": json.dumps(room.info().to_dict())})
        schema = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        ch = w.register_channel("/camera/color/image_raw", "cdr", schema)
        w.add_message(ch, 1, b"\x00\x01\x00\x00\x01\x00\x00\x00\x00", 1)
        w.finish()
    capsys.readouterr()
    assert run_cli(["correct", str(path), "--model", str(world["model"]), "--out", str(tmp_path / "o")]) == 2
    _one_error_line(capsys, "nodepth.mcap", "depth")


def test_correct_never_writes_into_an_existing_folder(world: dict[str, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "taken"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert run_cli(["correct", str(world["seq_b"]), "--model", str(world["model"]), "--out", str(out)]) == 2
    _one_error_line(capsys, "taken")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert run_cli(["model", "fit", str(world["root"] / "scan_a"), "--out", str(world["model"])]) == 2


def test_a_folder_appearing_while_correct_writes_keeps_the_recording_where_the_error_says(
        world: dict[str, Any], tmp_path: Path) -> None:
    """A folder someone fills while `correct` writes is not replaced; the corrected recording is
    kept under the visible name the error gives (the shared write-then-rename of result folders)."""
    out = tmp_path / "corrected"

    def meanwhile(i: int, total: int | None) -> None:
        if i == 0:
            out.mkdir()
            (out / "theirs.txt").write_text("written by another program meanwhile")

    with pytest.raises(InputError) as caught:
        correct_recording(world["seq_b"], world["model"], out, on_frame=meanwhile)
    assert "appeared while this run was writing" in str(caught.value)
    kept = Path(str(caught.value).rsplit("left in ", 1)[1])
    assert kept.is_dir() and not kept.name.startswith(".") and kept.name.startswith("corrected.new-")
    assert (kept / "sequence.mcap").is_file() and (kept / "correction.json").is_file()
    assert open_recording(kept / "sequence.mcap").frame_count == FRAMES
    assert sorted(p.name for p in out.iterdir()) == ["theirs.txt"]
    assert not list(tmp_path.glob(".corrected.partial-*"))


def test_fit_refuses_a_folder_that_is_no_study(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "r").mkdir()
    capsys.readouterr()
    assert run_cli(["model", "fit", str(tmp_path / "r"), "--out", str(tmp_path / "m.json")]) == 2
    _one_error_line(capsys, "grid.npz", "standpoints.csv")


def test_fit_refuses_studies_of_two_cameras(world: dict[str, Any], tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A copy of walk A's study that names another serial (and whose recording is gone, so only
    result.json speaks): one model cannot describe two cameras."""
    other = tmp_path / "other"
    shutil.copytree(world["root"] / "scan_a", other)
    info = json.loads((other / "result.json").read_text())
    info["device"]["serial_number"] = "OTHER9"
    (other / "result.json").write_text(json.dumps(info))
    summary = json.loads((other / "summary.json").read_text())
    summary["inputs"]["sequence"] = str(tmp_path / "gone.mcap")
    (other / "summary.json").write_text(json.dumps(summary))
    capsys.readouterr()
    assert run_cli(["model", "fit", str(world["root"] / "scan_a"), str(other), "--out",
                    str(tmp_path / "m.json"), "--min-count", "100"]) == 2
    _one_error_line(capsys, "other", "serial_number", "OTHER9")
    assert not (tmp_path / "m.json").exists()
