"""The demo's step runner: unavailable stages are said, failures reported, the rest still runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from depthstation.app.demo import DemoContext, Step, fresh_dir, missing_requirement, run_demo
from depthstation.core.errors import DepthstationError, InputError


def test_missing_requirement() -> None:
    assert missing_requirement(("json:dumps", "depthstation.core.rerun_bridge:send_heatmap")) is None
    assert missing_requirement(("json:dumps", "no_such_module_xyz:run")) == "no_such_module_xyz:run"
    assert missing_requirement(("json:no_such_function",)) == "json:no_such_function"


def test_fresh_dir_never_reuses_a_folder(tmp_path: Path) -> None:
    assert fresh_dir(tmp_path / "d") == tmp_path / "d"
    (tmp_path / "d").mkdir()
    assert fresh_dir(tmp_path / "d") == tmp_path / "d"          # empty: fine
    (tmp_path / "d" / "x").write_text("captured")
    assert fresh_dir(tmp_path / "d") == tmp_path / "d-2"


def _ok(ctx: DemoContext) -> tuple[Path, str]:
    folder = ctx.out / "ok"
    folder.mkdir()
    return folder, "fine"


def _boom(ctx: DemoContext) -> tuple[Path, str]:
    raise ValueError("broken on purpose")


def _after(ctx: DemoContext) -> tuple[Path, str]:
    assert "ok" in ctx.results
    return ctx.results["ok"], "saw the first step"


def test_steps_report_and_go_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    steps = [Step("ok", "works", ("json:dumps",), _ok),
             Step("absent", "stage missing", ("no_such_module_xyz:run",), _ok),
             Step("boom", "fails", (), _boom),
             Step("after", "runs after a failure", (), _after),
             Step("skipme", "skipped", (), _boom)]
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "old").write_text("a previous run")
    with pytest.raises(DepthstationError, match="boom"):
        run_demo(tmp_path / "demo", steps=steps, skip={"skipme"})
    out = tmp_path / "demo-2"
    report = json.loads((out / "demo.json").read_text())["steps"]
    assert {k: v["status"] for k, v in report.items()} == {
        "ok": "done", "absent": "not available", "boom": "failed", "after": "done", "skipme": "skipped"}
    assert "step absent: not available in this build" in report["absent"]["summary"]
    assert "broken on purpose" in (out / "demo.log").read_text()
    assert (tmp_path / "demo" / "old").read_text() == "a previous run"
    assert json.loads((out / "result.json").read_text())["kind"] == "demo"
    err = " ".join(capsys.readouterr().err.split())      # the console wraps long lines
    assert "not available in this build" in err and "open it with" in err


def test_demo_records_every_study_by_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each study's recording lands in its folder without --rrd; the report prints the command."""
    def study(ctx: DemoContext) -> tuple[Path, str]:
        folder = ctx.out / "study"
        folder.mkdir()
        target = ctx.target(folder, "study")
        assert target.rrd is not None
        target.rrd.write_bytes(b"")  # what the study's recording would be
        return folder, "recorded"

    out = tmp_path / ("a-long-folder-name-" * 4) / "d"   # a command longer than the console is wide
    run_demo(out, steps=[Step("study", "a study", (), study)])
    err = capsys.readouterr().err
    assert f"  depthstation view {out / 'study' / 'study.rrd'}\n" in err   # whole: it can be pasted


def test_unknown_skip_is_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown step"):
        run_demo(tmp_path / "d", steps=[Step("ok", "works", (), _ok)], skip={"nope"})


def test_a_file_as_out_is_input_error(tmp_path: Path) -> None:
    """Every command refuses a file as --out; the demo ran into afile-2/ instead, exit 0."""
    (tmp_path / "afile").write_text("x")
    with pytest.raises(InputError, match="is a file, not a folder"):
        run_demo(tmp_path / "afile", steps=[Step("ok", "works", (), _ok)])
    assert not (tmp_path / "afile-2").exists()


def test_step_dependencies() -> None:
    assert missing_requirement(("step:checkerboard",), set()) == "the checkerboard step"
    assert missing_requirement(("step:checkerboard", "json:dumps"), {"checkerboard"}) is None


def test_demo_checkerboard_and_compare_steps_for_real(tmp_path: Path) -> None:
    """The demo's checkerboard and compare steps on the real simulator and study (no session step:
    the checkerboard step then simulates the session directly). Judged here too: the same data
    evaluated twice compares to zero; the D435's shorter baseline (50 vs 95 mm) shows as larger
    noise (Intel: noise ~ z^2 / B, about 1.9x; we ask for more than 1.4x)."""
    pytest.importorskip("depthstation.simulate.checkerboard_session")
    from depthstation.app.compare_report import run_compare
    from depthstation.app.demo_steps import CHECKERBOARD, COMPARE
    from depthstation.app.view import view_path
    from depthstation.core.protocol import PROTOCOL_DIR
    from depthstation.core.rerun_bridge import read_rrd
    from depthstation.evaluate.checkerboard.run import run_checkerboard

    out = tmp_path / "demo"
    outcomes = run_demo(out, rrd=True, steps=[CHECKERBOARD, COMPARE])
    assert {k: o.status for k, o in outcomes.items()} == {"checkerboard": "done", "compare": "done"}
    facts = json.loads((out / "demo.json").read_text())["facts"]
    assert facts["noise_ratio_d435_over_d455"] > 1.4
    contents = read_rrd(out / "compare-d455-d435" / "compare.rrd")
    assert contents.series["/standpoints/noise_m/checkerboard-d435"].size == 6
    assert "Comparison" in contents.texts["/description"]
    stage = read_rrd(out / "checkerboard" / "checkerboard.rrd")          # the stage's own recording
    assert any(k.startswith("/progress") for k in stage.series) and "/description" in stage.texts
    viewed = read_rrd(view_path(out / "checkerboard", spawn=False))
    assert viewed.series["/standpoints/noise_m"].size == 6 and viewed.has_blueprint
    again = tmp_path / "again"
    run_checkerboard([out / "session-simulated"], PROTOCOL_DIR / "demo-d455.toml", again)
    same = run_compare([out / "checkerboard", again], tmp_path / "same", quiet=True)
    per = same["standpoints"]["others"]["again"]
    assert per["matched"] == per["of"] == 6
    for col in ("noise_m", "accuracy_m", "fill_rate", "noise_black_m"):
        assert per[col]["max_abs_diff"] == 0.0, col
