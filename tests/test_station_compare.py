"""compare: side-by-side standpoint tables and grid differences on result folders in the real formats."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from depthstation.app.cli import run_cli
from depthstation.app.compare import compare_grids, compare_standpoints, match_standpoints
from depthstation.app.compare_report import COMPARE_CSV, run_compare
from depthstation.core.errors import InputError
from depthstation.core.grid import Grid
from depthstation.core.rerun_bridge import RerunTarget, read_rrd
from depthstation.core.results import read_standpoints, write_result_info

COLUMNS = ["standpoint", "frames", "distance_m", "inclination_deg", "reference_distance_std_m", "fill_rate",
           "noise_m", "noise_std_m", "accuracy_m", "accuracy_std_m", "accuracy_rms_m", "noise_black_m",
           "noise_white_m", "accuracy_black_m", "accuracy_white_m"]
FX_PX = 640.0
SUBPIXEL_PX = 0.08


def intel_rms(z: float, baseline_m: float) -> float:
    """Intel's RMS depth noise: z^2 * subpixel / (f * B)."""
    return z * z * SUBPIXEL_PX / (FX_PX * baseline_m)


def write_checkerboard(folder: Path, baseline_m: float, *, names: str = "standpoint_{:02d}",
                       jitter_m: float = 0.0, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    rows = []
    k = 1
    for incl in (0.0, 30.0):
        for z in (1.0, 1.5, 2.0, 2.5, 3.0):
            n = intel_rms(z, baseline_m)
            rows.append({"standpoint": names.format(k), "frames": 30, "distance_m": z + jitter_m,
                         "inclination_deg": incl, "reference_distance_std_m": 1e-4 * z, "fill_rate": 0.99,
                         "noise_m": n, "noise_std_m": 0.1 * n, "accuracy_m": 1e-3 * z * z,
                         "accuracy_std_m": 0.2 * n, "accuracy_rms_m": n, "noise_black_m": n,
                         "noise_white_m": n, "accuracy_black_m": 1e-3 * z, "accuracy_white_m": 1e-3 * z
                         + rng.normal(0, 1e-5)})
            k += 1
    with (folder / "standpoints.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    write_result_info(folder, "checkerboard", ["synthetic"], {"frames": 30},
                      device={"name": "synthetic", "baseline_m": baseline_m})
    return folder


def write_scan(folder: Path, sigma_m: float, *, bias_m: float = 0.0, seed: int = 0, n: int = 60000) -> Path:
    from depthstation.core.grid import Grid

    rng = np.random.default_rng(seed)
    g = Grid.empty(distance_bin_m=0.25, inclination_bin_deg=15.0, distance_max_m=2.0,
                   inclination_max_deg=60.0)
    dist = rng.uniform(0.5, 1.5, n)
    incl = rng.uniform(0.0, 60.0, n)
    g.add(dist, incl, bias_m + rng.normal(0.0, sigma_m, n))
    folder.mkdir(parents=True)
    g.save(folder / "grid.npz")
    write_result_info(folder, "scan", ["synthetic"], {"sigma_m": sigma_m})
    return folder


def test_same_data_gives_zero_differences(tmp_path: Path) -> None:
    a = write_checkerboard(tmp_path / "a", 0.095)
    b = tmp_path / "b"
    b.mkdir()
    (b / "standpoints.csv").write_bytes((a / "standpoints.csv").read_bytes())
    summary = run_compare([a, b], tmp_path / "cmp", quiet=True)
    per = summary["standpoints"]["others"]["b"]
    assert per["matched"] == per["of"] == 10
    for col in summary["standpoints"]["columns"]:
        assert per[col]["max_abs_diff"] == 0.0, col
    rows = list(csv.DictReader((tmp_path / "cmp" / COMPARE_CSV).open()))
    assert len(rows) == 10 and float(rows[0]["noise_m[b - a]"]) == 0.0
    assert (tmp_path / "cmp" / "compare_b.png").stat().st_size > 1000
    assert json.loads((tmp_path / "cmp" / "result.json").read_text())["kind"] == "compare"


def test_shorter_baseline_shows_larger_noise(tmp_path: Path) -> None:
    a = write_checkerboard(tmp_path / "d455", 0.095)
    b = write_checkerboard(tmp_path / "d435", 0.050)
    summary = run_compare([a, b], tmp_path / "cmp", quiet=True)
    ratio = summary["standpoints"]["others"]["d435"]["noise_m"]["median_ratio"]
    assert ratio == pytest.approx(0.095 / 0.050, rel=1e-6)
    assert summary["standpoints"]["others"]["d435"]["noise_m"]["mean_diff"] > 0


def test_nearest_match_when_names_differ(tmp_path: Path) -> None:
    ref = read_standpoints(write_checkerboard(tmp_path / "a", 0.095) / "standpoints.csv")
    other = read_standpoints(write_checkerboard(tmp_path / "b", 0.095, names="pose{:02d}", jitter_m=0.02)
                             / "standpoints.csv")
    other = other[::-1]                      # order must not matter
    idx = match_standpoints(ref, other)
    assert [other[j]["distance_m"] - 0.02 for j in idx if j is not None] == pytest.approx(
        [r["distance_m"] for r in ref])
    assert match_standpoints(ref, other, mode="name") == [None] * len(ref)
    far = [dict(r, distance_m=r["distance_m"] + 0.25) for r in other]   # 2.3 units from any
    assert match_standpoints(ref, far, mode="nearest") == [None] * len(ref)
    cmp = compare_standpoints([("a", ref), ("b", other)])
    assert cmp.summary["others"]["b"]["matched"] == len(ref)


def test_grid_differences(tmp_path: Path) -> None:
    a = Grid.load(write_scan(tmp_path / "a", 0.004) / "grid.npz")
    same = compare_grids(a, a, min_count=100)
    assert same.mask.sum() > 10
    assert np.all(same.mean_diff_m[same.mask] == 0) and np.all(same.std_diff_m[same.mask] == 0)
    b = Grid.load(write_scan(tmp_path / "b", 0.008, bias_m=0.002, seed=1) / "grid.npz")
    d = compare_grids(a, b, min_count=100)
    n = np.minimum(a.count, b.count)[d.mask]
    # std of a sample std is about sigma / sqrt(2n); of a mean about sigma / sqrt(n): 5 standard errors
    assert np.all(np.abs(d.std_diff_m[d.mask] - 0.004) < 5 * 0.008 / np.sqrt(2 * n))
    assert np.all(np.abs(d.mean_diff_m[d.mask] - 0.002) < 5 * np.sqrt(0.008**2 + 0.004**2) / np.sqrt(n))
    assert d.summary()["cells_significant_3sigma"] == d.mask.sum()
    none = compare_grids(a, b, min_count=10**9)
    assert none.mask.sum() == 0 and none.summary()["cells_compared"] == 0


def test_grid_compare_writes_files_and_recording(tmp_path: Path) -> None:
    a = write_scan(tmp_path / "a", 0.004)
    b = write_scan(tmp_path / "b", 0.004)
    rrd = tmp_path / "cmp.rrd"
    summary = run_compare([a, b], tmp_path / "cmp", min_count=100, target=RerunTarget(rrd=rrd), quiet=True)
    s = summary["grids"]["b"]
    assert s["cells_compared"] > 10 and s["mean_diff_m"]["max_abs"] == 0.0
    assert (tmp_path / "cmp" / "grid_diff_b.png").is_file()
    with np.load(tmp_path / "cmp" / "grid_diff_b.npz") as z:
        assert z["mean_diff_m"].shape == z["mask"].shape
    contents = read_rrd(rrd)
    shape, names = contents.tensors["/compare/b/mean_diff"]
    assert names == ("distance [m]", "inclination [deg]") and shape == (8, 4)
    assert "Comparison" in contents.texts["/description"]


def test_mixed_kinds_and_bad_grids_are_input_errors(tmp_path: Path) -> None:
    a = write_checkerboard(tmp_path / "a", 0.095)
    s = write_scan(tmp_path / "s", 0.004)
    with pytest.raises(InputError, match="one kind"):
        run_compare([a, s], tmp_path / "cmp", quiet=True)
    other = tmp_path / "o"
    other.mkdir()
    np.savez(other / "grid.npz", distance_edges_m=np.linspace(0, 2, 5),
             inclination_edges_deg=np.linspace(0, 60, 3),
             count=np.ones((4, 2)), mean_m=np.zeros((4, 2)), var_m2=np.zeros((4, 2)))
    with pytest.raises(InputError, match="different bins"):
        run_compare([s, other], tmp_path / "cmp2", quiet=True)
    np.savez(other / "grid.npz", count=np.ones((4, 2)))
    with pytest.raises(InputError, match="lacks"):
        Grid.load(other / "grid.npz")


def test_cli_exit_codes(tmp_path: Path) -> None:
    exe = Path(sys.executable).with_name("depthstation")
    a = write_checkerboard(tmp_path / "a", 0.095)
    b = write_checkerboard(tmp_path / "b", 0.050)
    ok = subprocess.run([str(exe), "compare", str(a), str(b), "--out", str(tmp_path / "cmp")],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "noise" in ok.stderr and (tmp_path / "cmp" / COMPARE_CSV).is_file()
    bad = subprocess.run([str(exe), "compare", str(a), str(tmp_path / "missing"),
                          "--out", str(tmp_path / "x")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().count("\n") == 0 and "not a folder" in bad.stderr



def test_same_names_at_other_places_match_by_geometry(tmp_path: Path) -> None:
    """Two sessions of different plans both name their standpoints standpoint_01..N: by name, a
    1.8 m standpoint was compared with a 2.6 m one without a word."""
    from depthstation.core.run_warnings import collecting

    ref = read_standpoints(write_checkerboard(tmp_path / "a", 0.095) / "standpoints.csv")
    shifted = [dict(r, distance_m=ref[(i + 1) % len(ref)]["distance_m"],
                    inclination_deg=ref[(i + 1) % len(ref)]["inclination_deg"]) for i, r in enumerate(ref)]
    with collecting() as found:
        idx = match_standpoints(ref, shifted)
    assert all(j is not None for j in idx)  # each place exists in the other, under another name
    for i, j in enumerate(idx):
        assert j is not None and j != i
        assert shifted[j]["distance_m"] == pytest.approx(ref[i]["distance_m"])
        assert shifted[j]["inclination_deg"] == pytest.approx(ref[i]["inclination_deg"])
    assert [w.code for w in found] == ["compare-match"] and "matched by distance" in found[0].message
    with collecting() as found:
        assert match_standpoints(ref, shifted, mode="name") == list(range(len(ref)))
    assert [w.code for w in found] == ["compare-match"]
    with collecting() as found:  # the same places: names as before, nothing said
        assert match_standpoints(ref, ref) == list(range(len(ref)))
    assert found == []


def test_bad_output_options_are_refused_before_any_table(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """An existing --rrd (or a folder given as one) and a negative --min-count are bad input, refused
    before the comparison prints or writes anything (they were refused after its tables)."""
    a = write_scan(tmp_path / "a", 0.004)
    b = write_scan(tmp_path / "b", 0.004)
    rrd = tmp_path / "old.rrd"
    rrd.write_bytes(b"RRF2 an earlier recording")
    cases = [(["--rrd", str(rrd)], "old.rrd"), (["--rrd", str(tmp_path)], "is a folder"),
             (["--min-count", "-5"], "--min-count"), (["--max-offset", "-1"], "--max-offset"),
             (["--max-offset", "nan"], "--max-offset")]
    for extra, named in cases:
        capsys.readouterr()
        code = run_cli(["compare", str(a), str(b), "--out", str(tmp_path / "cmp"), *extra])
        captured = capsys.readouterr()
        assert code == 2 and named in captured.err, (extra, captured.err)
        assert "mean diff" not in captured.out + captured.err and not (tmp_path / "cmp").exists()
    assert rrd.read_bytes() == b"RRF2 an earlier recording"


def test_a_figure_that_is_no_number_names_the_file_and_the_standpoint(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A damaged cell ('abc' for a distance) was read as NaN: the standpoint went unmatched under a
    warning about names, exit 0. Now bad input naming the table, the standpoint and the column."""
    a = write_checkerboard(tmp_path / "a", 0.095)
    b = write_checkerboard(tmp_path / "b", 0.095)
    table = (b / "standpoints.csv").read_text().splitlines()
    head = table[0].split(",")
    cells = table[1].split(",")
    cells[head.index("distance_m")] = "abc"
    (b / "standpoints.csv").write_text("\n".join([table[0], ",".join(cells), *table[2:]]) + "\n")
    capsys.readouterr()
    code = run_cli(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")])
    err = capsys.readouterr().err
    assert code == 2 and f"{b / 'standpoints.csv'}: {cells[0]}: distance_m 'abc' is not a number" in err, err
    assert not (tmp_path / "cmp").exists()
