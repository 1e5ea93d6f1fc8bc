"""What a new user meets first: full-width tables and progress lines in a log, compare's word when
nothing matches, compact's word when nothing was saved."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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


def _region(family: str, kind: str, label: str, diff: float, p: float) -> dict[str, object]:
    return {"family": family, "kind": kind, "label": label, "axes": [family], "diff": diff, "se": diff / 10,
            "p_adj": p}


def _explain_data(regions: list[dict[str, object]], time_stamps: bool = True) -> dict[str, object]:
    from depthstation.evaluate.explain.report import in_domain

    fit = {"role": "calibration", "selected": False, "delta_bic": -90.0, "heldout_rmse_before_m": 0.011,
           "heldout_rmse_after_m": 0.0085}
    return {
        "mismatch": {"significant": True, "standpoints": [], "regions": regions, "alpha": 0.05},
        "candidates": [in_domain({"rank": 1, "effect": "window_noise", "kind": "variance", **fit,
                                  "params": {"sigma_px": {"value": -0.10, "unit": "px", "stderr": 0.02}}}),
                       in_domain({"rank": 2, "effect": "depth_scale", "kind": "bias", **fit,
                                  "role": "missing_physics",
                                  "params": {"scale_error": {"value": -0.0026, "unit": "1",
                                                             "stderr": 1e-4}}}),
                       in_domain({"rank": 3, "effect": "disparity_offset", "kind": "bias", **fit,
                                  "params": {"offset_px": {"value": -0.05, "unit": "px", "stderr": 0.01}}})],
        "missing_physics": [], "calibrated": [], "near_ties": [], "discovered": [], "discovery": None,
        "time_stamps": time_stamps,
    }


def test_explain_report_lists_what_it_counts_in_units_and_domains() -> None:
    """report.md said '26 regions' and listed 20; a sigma of '-0.10 px'; 'scale_error = -0.0026 1';
    correlation coefficients as '2.74e+05 mm^2'."""
    import re

    from depthstation.evaluate.explain.report import MAX_REGIONS, report_md

    regions = [_region("distance", "noise", f"{1 + k / 10:.1f} m", 1.2e-4, 1e-4 * (k + 1)) for k in range(24)]
    regions += [_region("albedo", "bias", "white", 3.3e-3, 0.01),
                _region("correlation_u", "noise", "u lag 2.78 px", 0.274, 0.02)]
    md = report_md(None, _explain_data(regions), [])
    assert "(26 regions: 25 of bias or noise, 1 of noise correlation;" in md
    assert f"Top {MAX_REGIONS} of 25 regions of bias or noise" in md
    rows = [x for x in md.splitlines() if x.startswith("| distance") or x.startswith("| albedo")]
    assert len(rows) == MAX_REGIONS
    corr = [x for x in md.splitlines() if x.startswith("| correlation_u")]
    assert corr == ["| correlation_u | u lag 2.78 px | +0.274 | 0.027 | 0.02 |"]
    assert "e+05" not in md and "0.274 mm" not in md
    # noise rows: value and SE in mm^2, bias rows in mm
    assert all(x.count("mm^2") == 2 for x in rows if x.startswith("| distance"))
    # widths in their domain, the fit said; ratios without the unit "1"
    assert not re.search(r"= -[0-9.]+ px", md.split("## Candidates")[1].split("disparity_offset")[0])
    assert "sigma_px = 0 px (clamped at 0: the fitted variance is negative, -0.01 px^2)" in md
    assert "scale_error = -0.0026 |" in md and not re.search(r"[0-9] 1 \|", md)
    assert "offset_px = -0.05 px" in md  # a disparity offset has a sign: left alone
    few = report_md(None, _explain_data(regions[:3]), [])
    assert "(3 regions: 3 of bias or noise;" in few and "3 region(s) of bias or noise" in few


def test_explain_json_keeps_the_signed_fit_beside_the_clamped_width() -> None:
    from depthstation.evaluate.explain.report import in_domain

    c = in_domain({"kind": "variance", "params": {"sigma_px": {"value": -0.1, "unit": "px", "stderr": 0.02},
                                                   "window_px": {"value": 9.0, "unit": "px", "stderr": 1.0}}})
    assert c["params"]["sigma_px"]["value"] == 0.0 and c["params"]["sigma_px"]["fitted_signed"] == -0.1
    assert "clamped at 0" in c["params"]["sigma_px"]["domain"]
    assert c["params"]["window_px"] == {"value": 9.0, "unit": "px", "stderr": 1.0}
    bias = {"kind": "bias", "params": {"offset_px": {"value": -0.1, "unit": "px", "stderr": 0.02}}}
    assert in_domain(bias) == bias


def test_explain_makes_up_no_time_axis_for_frames_without_time_stamps() -> None:
    """A PNG folder's frames are stamped k / fps from 0 in every standpoint: report.md drew
    'time since session start' from them."""
    from depthstation.evaluate.explain.report import report_md, session_clock
    from depthstation.evaluate.explain.run import FrameClock

    def clock(t0_ns: int, n: int = 5, fps: float = 30.0) -> FrameClock:
        return FrameClock(list(range(n)), [t0_ns + round(k * 1e9 / fps) for k in range(n)], [np.nan] * n)

    png = {"pose03": clock(0), "pose04": clock(0)}
    assert not session_clock(png)
    assert not session_clock({"pose03": clock(0)})
    session = {"standpoint_01": clock(1_700_000_000_000_000_000),
               "standpoint_02": clock(1_700_000_060_000_000_000)}
    assert session_clock(session)
    t0 = 1_700_000_000_000_000_000
    overlapping = {"a": clock(t0), "b": clock(t0 + 10**8)}
    assert not session_clock(overlapping)
    regions = [_region("time", "bias", "0.1-0.2 s", 2e-3, 0.01),
               _region("albedo", "bias", "white", 3e-3, 0.02)]
    md = report_md(None, _explain_data(regions, time_stamps=False), [])
    assert "no time stamps" in md and "| time |" not in md
    assert "1 along frame time without time stamps" in md
    assert "| time |" in report_md(None, _explain_data(regions, time_stamps=True), [])


def _saved_figures(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, list[Any]]]:
    """What every matplotlib figure shows as it is saved (the figure functions close theirs): the
    problems of the texts it drew, its axes' titles and texts."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.text import Text

    saved: list[dict[str, list[Any]]] = []
    original_save, original_draw = Figure.savefig, Text.draw
    drawn: list[tuple[int, str, Any, bool, tuple[float, float]]] = []

    def draw(self: Text, renderer: Any) -> None:
        original_draw(self, renderer)
        if self.get_visible() and self.get_text().strip() and self.figure is not None:
            in_3d = self.axes is not None and self.axes.name == "3d"
            page = (self.figure.bbox.width, self.figure.bbox.height)  # at the saving dpi
            box = Text.get_window_extent(self, renderer)  # the text alone (an annotation's line apart)
            drawn.append((id(renderer), self.get_text(), box, in_3d, page))

    def keep(self: Figure, *args: Any, **kwargs: Any) -> None:
        drawn.clear()
        original_save(self, *args, **kwargs)
        last_pass = [d[1:] for d in drawn if d[0] == drawn[-1][0]] if drawn else []
        last = list({(t, tuple(np.round(b.extents, 1))): (t, b, f, p) for t, b, f, p in last_pass}.values())
        saved.append({"problems": _text_problems(last),
                      "titles": [ax.get_title() for ax in self.axes if ax.get_label() != "<colorbar>"],
                      "labels": [[t.get_text() for t in ax.texts] for ax in self.axes]})

    monkeypatch.setattr(Figure, "savefig", keep)
    monkeypatch.setattr(Text, "draw", draw)
    return saved


def _text_problems(drawn: list[tuple[str, Any, bool, tuple[float, float]]]) -> list[str]:
    """Texts cut by the figure's edge, and pairs of texts that overlap (pixels of the saved figure;
    a 3-D axes' own tick labels are left to matplotlib)."""
    problems = []
    boxes = [(text, b) for text, b, in_3d, _ in drawn if not in_3d]
    for text, b, _, (width, height) in drawn:
        if b.x0 < -0.5 or b.y0 < -0.5 or b.x1 > width + 0.5 or b.y1 > height + 0.5:
            problems.append(f"cut: {text!r}")
    for i, (a, ba) in enumerate(boxes):
        for b, bb in boxes[i + 1:]:
            w = min(ba.x1, bb.x1) - max(ba.x0, bb.x0)
            h = min(ba.y1, bb.y1) - max(ba.y0, bb.y0)
            if w > 0.5 and h > 0.5:
                problems.append(f"overlap: {a!r} / {b!r}")
    return problems


def _standpoints_like_the_d435_set() -> list[object]:
    """Nine standpoints where the real D435 set has them: two of them 0.5 cm and 1 deg apart."""
    from types import SimpleNamespace

    places = [(1.08, 36.5), (1.21, 24.0), (1.225, 41.2), (1.295, 40.3), (1.35, 29.2), (1.40, 38.8),
              (1.405, 39.7), (1.44, 19.6), (1.60, 6.0)]
    out = []
    for k, (d, inc) in enumerate(places):
        v = 0.006 + 0.001 * k
        out.append(SimpleNamespace(name=f"pose{k + 3:02d}", usable=True, camera_in_board=None, figures={
            "distance_m": d, "inclination_deg": inc, "noise_m": v, "noise_std_m": v / 8, "noise_m_u95": v / 5,
            "accuracy_m": v - 0.01, "accuracy_std_m": v / 6, "accuracy_m_u95": v,
            "noise_black_m": v, "noise_white_m": v, "accuracy_black_m": v, "accuracy_white_m": v}))
    return out


def test_fig6_labels_of_close_standpoints_do_not_overlap(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Fig. 6/7 of the real D435 set printed '8.43 ± 1.68' over '7.69 ± 1.61' (0.5 cm, 1 deg apart)."""
    from depthstation.evaluate.checkerboard.figures import fig_colours, fig_over_grid

    saved = _saved_figures(monkeypatch)
    rs = _standpoints_like_the_d435_set()
    fig_over_grid(tmp_path / "fig6.png", rs, "noise", "noise", 6, "depth 1280x720, 3 frames")  # type: ignore[arg-type]
    fig_over_grid(tmp_path / "fig7.png", rs, "accuracy", "accuracy", 7, "")  # type: ignore[arg-type]
    fig_colours(tmp_path / "bw.png", rs)  # type: ignore[arg-type]
    for fig in saved:
        assert fig["problems"] == []
        assert all(fig["titles"])
    labels = saved[0]["labels"][0]
    assert len(labels) == 9 and "6.00 ± 1.20" in labels


def test_fig5_axis_labels_are_inside_the_figure(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An image of equal aspect under tight_layout cut the x label off Fig. 5's bottom edge."""
    from types import SimpleNamespace

    from depthstation.evaluate.checkerboard.figures import fig5_pixels

    saved = _saved_figures(monkeypatch)
    rng = np.random.default_rng(1)
    example = SimpleNamespace(noise_map_m=rng.normal(0, 0.005, (455, 440)),
                              accuracy_map_m=rng.normal(0, 0.005, (455, 440)), u0=965, v0=435, index=9)
    r = SimpleNamespace(name="pose06", example=example, figures={"distance_m": 1.40, "inclination_deg": 39.5})
    fig5_pixels(tmp_path / "fig5.png", r, "depth 1920x1080, 3 frames per standpoint")  # type: ignore[arg-type]
    assert saved[0]["problems"] == []


def test_fig1_puts_the_cameras_on_the_boards_plus_z_for_either_convention() -> None:
    from depthstation.evaluate.checkerboard.figures import board_turn

    below = np.array([[0.1, 0.2, -1.2], [0.3, -0.1, -0.9]])  # a chessboard's OpenCV frame: z into the board
    turn = board_turn(below)
    assert np.allclose(turn @ turn.T, np.eye(3)) and np.isclose(np.linalg.det(turn), 1.0)  # a rotation
    assert ((below @ turn.T)[:, 2] > 0).all()
    above = -below
    assert np.array_equal(board_turn(above), np.eye(3))


def test_a_discovered_terms_long_title_is_not_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from depthstation.evaluate.explain.figures import term_field_figure, term_residual_figure

    saved = _saved_figures(monkeypatch)
    title = ("poly_field_uv3 (bias along u, v): 0.0123*x + -0.0456*y + 0.0789*x*x + 0.0012*x*y + -0.0345*y*y "
             "+ 0.0067*x*x*x + -0.0089*x*x*y + 0.0011*x*y*y + 0.0022*y*y*y")
    x = np.linspace(0, 1, 10)
    term_residual_figure(tmp_path / "a.png", title, "x", "disparity error real - sim (px)",
                         [("before (real - sim)", x, x * 0.1, x * 0 + 0.01)], (x, x * 0.1, x * 0 + 0.02))
    xe, ye = np.linspace(-0.6, 0.6, 13), np.linspace(-0.35, 0.35, 8)
    m = np.random.default_rng(0).normal(0, 0.02, (12, 7))
    term_field_figure(tmp_path / "b.png", title, "px", xe, ye,
                      [("residual before (px)", m), ("fitted term (px)", m), ("2 SE (px)", m)])
    assert [fig["problems"] for fig in saved] == [[], []]


def test_every_console_is_built_in_one_place() -> None:
    """A rich Console made elsewhere falls back to 80 columns in a log and cuts tables again."""
    repo = Path(__file__).resolve().parents[1]
    own = repo / "depthstation" / "core" / "progress.py"
    stages = ("depthstation", "acquire", "evaluate", "simulate")
    files = [p for stage in stages for p in (repo / stage).rglob("*.py")]
    assert any(p.parent.name == "errormodel" for p in files)  # the stage folders are searched
    found = [f"{p.relative_to(repo)}:{k + 1}" for p in sorted(files) if p.resolve() != own
             for k, line in enumerate(p.read_text().splitlines()) if "Console(" in line.split("#")[0]]
    assert found == []


def test_a_log_console_is_wide_even_with_columns_in_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """rich takes $COLUMNS as a fixed width at construction: a process that exported COLUMNS=80 cut
    the log's tables again (seen in the full suite); a width given by the caller is kept."""
    import io

    from depthstation.core.progress import LOG_WIDTH, StationConsole

    monkeypatch.setenv("COLUMNS", "80")
    assert StationConsole(file=io.StringIO()).width == LOG_WIDTH
    assert StationConsole(file=io.StringIO(), width=60).width == 60
    c = StationConsole(file=io.StringIO())
    c.width = 70
    assert c.width == 70
