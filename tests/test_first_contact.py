"""What a new user meets first: full-width tables and progress lines in a log, compare's word when
nothing matches, compact's word when nothing was saved."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from console import run_console

from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.sample_recordings import sample_frames, sample_info


def test_compact_says_when_the_file_did_not_get_smaller(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A zstd recording rewritten without compression grows; compact printed only the two sizes."""
    info = sample_info(48, 32)
    packed, plain = tmp_path / "packed.mcap", tmp_path / "plain.mcap"
    write_mcap(packed, info, sample_frames(info, 4), compression="zstd")
    write_mcap(plain, info, sample_frames(info, 4), compression="none")
    code, out, err = run_console(["capture", "compact", str(packed), str(tmp_path / "grown.mcap"),
                                  "--compression", "none"], capsys)
    assert code == 0, err
    said = [line for line in out.splitlines() if "not smaller" in line]
    assert len(said) == 1 and str(packed) in said[0], out
    assert (tmp_path / "grown.mcap").stat().st_size >= packed.stat().st_size
    code, out, err = run_console(["capture", "compact", str(plain), str(tmp_path / "small.mcap")], capsys)
    assert code == 0, err
    assert (tmp_path / "small.mcap").stat().st_size < plain.stat().st_size
    assert "not smaller" not in out, out


def test_tables_are_not_cut_when_the_console_is_no_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    """In a log rich took 80 columns and cut every cell to `stand…`; ours is as wide as the table."""
    from rich.console import Console
    from rich.table import Table

    from depthstation.core.progress import stderr_console, stdout_console

    names = [f"standpoint_{k:02d}_at_{1.2 + 0.2 * k:.1f}m" for k in range(8)]
    table = Table(title="checkerboard results side by side")
    for name in names:
        table.add_column(name)
    table.add_row(*[f"{0.1 * k:.3f}" for k in range(8)])
    for console in (stderr_console, stdout_console):
        assert not console.is_terminal  # pytest captures both streams
        console.print(table)
    out, err = capsys.readouterr()
    for text in (out, err):
        assert "…" not in text
        assert all(name in text for name in names), text
    Console(stderr=True).print(table)  # rich's own fallback (80 columns), for contrast
    assert "…" in capsys.readouterr().err


def test_progress_in_a_log_is_lines_with_rate_and_eta(capsys: pytest.CaptureFixture[str]) -> None:
    """stderr to a log: a line per milestone with rate and ETA, at most one a second, the end always;
    rich drew its bar once, when the work was over."""
    from depthstation.core.progress import LogProgress, progress

    now = [0.0]
    with progress(get_time=lambda: now[0]) as bar:
        assert isinstance(bar, LogProgress)
        fast = bar.add_task("checkerboard", total=200, status="")
        for _ in range(200):  # 0.1 s a frame: 5 % (10 frames) a second
            now[0] += 0.1
            bar.advance(fast)
        slow = bar.add_task("standpoints", total=3, status="")
        for k in range(3):  # a minute a step: every step said
            now[0] += 60.0
            bar.update(slow, completed=k + 1, status=f"standpoint_{k + 1:02d}")
    lines = capsys.readouterr().err.splitlines()
    fast_lines = [x for x in lines if x.startswith("checkerboard: ")]
    slow_lines = [x for x in lines if x.startswith("standpoints: ")]
    assert fast_lines[0].startswith("checkerboard: 0/200 (0%)")
    assert fast_lines[-1].startswith("checkerboard: 200/200 (100%)")
    assert 15 <= len(fast_lines) <= 22, fast_lines  # start, one per 5 % (one a second), the end
    middle = fast_lines[len(fast_lines) // 2]
    done = int(middle.split(": ")[1].split("/")[0])
    rate = float(middle.split(", ")[1].removesuffix("/s"))
    assert abs(rate - 10.0) < 0.5, middle  # frames per second of the fake clock
    eta = middle.split("ETA ")[1].split(",")[0]
    h, m, s = (int(v) for v in eta.split(":"))
    assert abs(3600 * h + 60 * m + s - (200 - done) / 10.0) <= 1.0, middle
    assert [x.split(",")[0] for x in slow_lines] == ["standpoints: 0/3 (0%)", "standpoints: 1/3 (33%)",
                                                       "standpoints: 2/3 (67%)", "standpoints: 3/3 (100%)"]
    assert slow_lines[-1].endswith("standpoint_03")


def test_progress_in_a_terminal_stays_a_bar() -> None:
    from rich.console import Console

    from depthstation.core.progress import LogProgress, progress

    assert not isinstance(progress(console=Console(force_terminal=True)), LogProgress)


def test_capture_import_in_a_log_says_its_progress(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Through the console script, stderr captured: the recording's lines, not a bar at the end."""
    info = sample_info(48, 32)
    write_mcap(tmp_path / "rec.mcap", info, sample_frames(info, 5))
    code, _, err = run_console(["capture", "import", str(tmp_path / "rec.mcap"), "--out",
                                str(tmp_path / "session")], capsys)
    assert code == 0, err
    assert "rec: 5/5 (100%)" in err, err


def test_compare_with_no_standpoint_in_common_warns_and_strict_exits_3(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two sessions with no standpoint within --max-offset: a table of '-' and exit 0, not a word."""
    from test_station_compare import write_checkerboard

    a = write_checkerboard(tmp_path / "a", 0.095)
    far = write_checkerboard(tmp_path / "far", 0.095, names="pose{:02d}", jitter_m=0.25)  # 2.5 units from any
    near = write_checkerboard(tmp_path / "near", 0.050, names="pose{:02d}", jitter_m=0.02)
    code, _, err = run_console(["compare", str(a), str(far), "--out", str(tmp_path / "c1")], capsys)
    assert code == 0, err
    said = [x for x in err.splitlines() if "warning" in x and "no standpoint in common" in x]
    assert len(said) == 1 and "--max-offset 1" in said[0], err
    code, _, err = run_console(["--strict", "compare", str(a), str(far), "--out", str(tmp_path / "c2")],
                               capsys)
    assert code == 3, err
    code, _, err = run_console(["--strict", "compare", str(a), str(near), "--out", str(tmp_path / "c3")],
                               capsys)
    assert code == 0 and "no standpoint in common" not in err, err


def test_compare_with_no_cell_in_common_warns_and_strict_exits_3(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from depthstation.core.grid import Grid
    from depthstation.core.results import write_result_info

    rng = np.random.default_rng(3)
    folders = []
    for name, (lo, hi) in (("near", (0.5, 1.0)), ("far", (1.5, 2.0))):  # disjoint distances
        g = Grid.empty(distance_bin_m=0.25, inclination_bin_deg=15.0, distance_max_m=2.0,
                       inclination_max_deg=60.0)
        g.add(rng.uniform(lo, hi, 20000), rng.uniform(0.0, 60.0, 20000), rng.normal(0.0, 0.002, 20000))
        (tmp_path / name).mkdir()
        g.save(tmp_path / name / "grid.npz")
        write_result_info(tmp_path / name, "scan", ["synthetic"], {})
        folders.append(str(tmp_path / name))
    code, _, err = run_console(["compare", *folders, "--out", str(tmp_path / "c1"), "--min-count", "10"],
                               capsys)
    assert code == 0, err
    assert any("warning" in x and "no cell holds 10 samples in both" in x for x in err.splitlines()), err
    code, _, err = run_console(["--strict", "compare", *folders, "--out", str(tmp_path / "c2"),
                                "--min-count", "10"], capsys)
    assert code == 3, err
