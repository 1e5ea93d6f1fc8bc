"""The rerun bridge: recordings read back with rerun's chunk reader hold heatmaps, series, text, blueprint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.app.view import folder_to_rrd, view_path
from depthstation.core import rerun_bridge as viz
from depthstation.core.errors import InputError
from depthstation.core.heatmaps import colorize


def test_recording_round_trip(tmp_path: Path) -> None:
    rrd = tmp_path / "r.rrd"
    d_edges = np.linspace(0.5, 2.5, 5)
    i_edges = np.linspace(0.0, 60.0, 4)
    grid = np.arange(12, dtype=float).reshape(4, 3) * 1e-3
    grid[0, 0] = np.nan
    bp = viz.blueprint(viz.heatmap_view("grid/mean", "mean [m]"), viz.series_view("progress", "progress"))
    with viz.recording("depthstation-test", viz.RerunTarget(rrd=rrd), bp, "# What\nA test.") as rec:
        viz.send_heatmap(rec, "grid/mean", grid, d_edges, i_edges, quantity="mean error", unit="m")
        viz.send_series(rec, "progress/frames_done", np.arange(5), np.arange(5) * 2.0, name="frames",
                        unit="1")
        for k in range(3):
            viz.send_scalar(rec, "progress/live", 0.5 * k, step=k)
        viz.send_colormapped(rec, "images/noise", np.random.default_rng(0).random((8, 10)))
        viz.send_table(rec, "table", [{"standpoint": "s1", "noise_m": 0.001}])
    c = viz.read_rrd(rrd)
    assert c.tensors["/grid/mean"] == ((4, 3), (viz.DISTANCE_DIM, viz.INCLINATION_DIM))
    assert {"unit", "quantity", "distance_edges_m", "inclination_edges_deg"} <= c.entities["/grid/mean"]
    assert c.series["/progress/frames_done"].tolist() == [0.0, 2.0, 4.0, 6.0, 8.0]
    assert c.series["/progress/live"].tolist() == [0.0, 0.5, 1.0]
    assert c.texts["/description"].startswith("# What")
    assert "noise_m" in c.texts["/table"]
    assert c.has_blueprint


def test_disabled_target_costs_nothing(tmp_path: Path) -> None:
    with viz.recording("x", viz.RerunTarget()) as rec:
        assert rec is None
        viz.send_heatmap(rec, "g", np.zeros((2, 2)), np.arange(3.0), np.arange(3.0), quantity="q", unit="m")
        viz.send_series(rec, "s", [0], [1.0], name="s", unit="m")
    assert not list(tmp_path.iterdir())


def test_heatmap_shape_must_match_edges(tmp_path: Path) -> None:
    with viz.recording("x", viz.RerunTarget(rrd=tmp_path / "x.rrd")) as rec, \
            pytest.raises(ValueError, match="does not match"):
        viz.send_heatmap(rec, "g", np.zeros((3, 3)), np.arange(3.0), np.arange(4.0), quantity="q", unit="m")


def test_colorize_greys_out_nan() -> None:
    img = colorize(np.array([[0.0, 1.0], [np.nan, 0.5]]))
    assert img.shape == (2, 2, 3) and img.dtype == np.uint8
    assert img[1, 0].tolist() == [128, 128, 128]
    assert not np.array_equal(img[0, 0], img[0, 1])


def test_view_converts_a_result_folder(tmp_path: Path) -> None:
    from tests.test_station_compare import write_checkerboard, write_scan

    cb = write_checkerboard(tmp_path / "cb", 0.095)
    rrd = view_path(cb, spawn=False)
    c = viz.read_rrd(rrd)
    assert c.series["/standpoints/noise_m"].size == 10
    assert "checkerboard" in c.texts["/description"]
    scan = write_scan(tmp_path / "scan", 0.004)
    c2 = viz.read_rrd(folder_to_rrd(scan, tmp_path / "scan.rrd"))
    assert c2.tensors["/grid/std"][1] == (viz.DISTANCE_DIM, viz.INCLINATION_DIM)
    assert c2.has_blueprint


def _listen_addresses(port: int) -> set[str]:
    """Local addresses listening on `port`, from /proc/net/tcp{,6} (Linux)."""
    found = set()
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        path = Path(name)
        if not path.is_file():
            continue
        for line in path.read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, port_hex = local.rsplit(":", 1)
            if int(port_hex, 16) == port and state == "0A":       # 0A = LISTEN
                found.add(addr)
    return found


def test_web_viewer_binds_to_localhost_only() -> None:
    import os
    import signal
    import sys
    from urllib.parse import urlparse

    if not sys.platform.startswith("linux"):
        pytest.skip("reads /proc/net/tcp")
    proxy, proc, browser = viz.start_web_server()
    try:
        port = urlparse(proxy.replace("rerun+http", "http")).port
        web_port = urlparse(browser).port
        assert port is not None and web_port is not None
        for p in (port, web_port):
            addrs = _listen_addresses(p)
            assert addrs, f"nothing listens on {p}"
            assert addrs <= {"0100007F", "00000000000000000000000001000000"}, addrs   # 127.0.0.1 / ::1
        assert browser.startswith("http://127.0.0.1:")
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=10)


def test_view_refuses_what_is_not_a_result_or_a_recording(tmp_path: Path) -> None:
    """Files named .rrd that are no recording, a broken result.json or grid, a folder of captured
    PNGs: one-line bad input, nothing written into the user's folder (view.rrd landed in captures)."""
    from tests.test_station_compare import write_scan

    for name, data in (("empty.rrd", b""), ("notes.rrd", b"my notes"), ("cut.rrd", b"RR")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match="not a rerun recording"):
            view_path(tmp_path / name, spawn=False)
    pngs = tmp_path / "pose03"
    pngs.mkdir()
    (pngs / "frame0_color.png").write_bytes(b"\\x89PNG")
    with pytest.raises(InputError, match="not a result folder"):
        view_path(pngs, spawn=False)
    assert sorted(p.name for p in pngs.iterdir()) == ["frame0_color.png"]
    scan = write_scan(tmp_path / "scan", 0.004)
    grid = scan / "grid.npz"
    good = grid.read_bytes()
    grid.write_bytes(good[: len(good) // 2])
    with pytest.raises(InputError, match=r"grid\.npz"):
        view_path(scan, spawn=False)
    grid.write_bytes(good)
    (scan / "result.json").write_text("{broken")
    with pytest.raises(InputError, match=r"result\.json"):
        view_path(scan, spawn=False)
    from tests.test_station_compare import write_checkerboard

    table = write_checkerboard(tmp_path / "cb", 0.095) / "standpoints.csv"
    table.write_text(table.read_text().splitlines()[0] + "\n")  # the header alone: a cut table
    with pytest.raises(InputError, match=r"standpoints\.csv: holds no standpoint"):
        view_path(table.parent, spawn=False)


def test_view_rebuilds_a_recording_older_than_its_folder(tmp_path: Path) -> None:
    """A batch rerun rewrites combined/grid.npz; the view.rrd made before showed the old grid."""
    import os

    from tests.test_station_compare import write_scan

    scan = write_scan(tmp_path / "scan", 0.004)
    first = view_path(scan, spawn=False)
    os.utime(first, (1, 1))  # made long ago: every file of the folder is newer
    again = view_path(scan, spawn=False)
    assert again == first and again.stat().st_mtime > 1  # rebuilt
    made = again.stat().st_mtime
    os.utime(scan / "grid.npz", (1, 1))  # nothing newer than the recording: opened as it is
    assert view_path(scan, spawn=False).stat().st_mtime == made


def test_view_writes_its_recording_under_one_temporary_name(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """`view` hands the final name to the recording, which alone writes it under a temporary name
    and renames it (it was `..view.rrd.partial-N.partial-N`, renamed twice)."""
    from tests.test_station_compare import write_scan

    made: list[Path] = []
    real_new_file = viz.new_file

    def recording_new_file(path: Path, *, force: bool = False) -> Path:
        made.append(real_new_file(path, force=force))
        return made[-1]

    monkeypatch.setattr(viz, "new_file", recording_new_file)
    scan = write_scan(tmp_path / "scan", 0.004)
    rrd = view_path(scan, spawn=False)
    assert rrd == scan / "view.rrd" and rrd.is_file()
    assert [p.name.count(".partial-") for p in made] == [1] and made[0].parent == scan
    assert not [p for p in scan.iterdir() if ".partial-" in p.name]
