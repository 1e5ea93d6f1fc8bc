"""Shared fixtures: paths to the real data beside the repository (skipped with a reason when absent)
and a small simulated session."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _has_device() -> bool:
    try:
        import pyrealsense2 as rs

        return len(rs.context().query_devices()) > 0
    except Exception:
        return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip `hardware` tests unless a RealSense device is attached."""
    if any("hardware" in item.keywords for item in items) and not _has_device():
        skip = pytest.mark.skip(reason="needs a RealSense device attached")
        for item in items:
            if "hardware" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def charuco_dir() -> Path:
    path = SHARED_DATA / "alr-d435-charuco"
    if not (path / "camera.json").is_file():
        pytest.skip(f"real D435 ChArUco set not found at {path}")
    return path


@pytest.fixture(scope="session")
def d435_bag() -> Path:
    path = SHARED_DATA / "librealsense-d435-bag" / "single_depth_color_640x480.bag"
    if not path.is_file():
        pytest.skip(f"real RealSense .bag not found at {path}")
    return path


@pytest.fixture(scope="module")
def small_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated session (2 standpoints x 12 frames of 640x360) and its protocol beside it
    (`p.toml`, the board file the evaluation takes)."""
    from depthstation.app.cli import run_cli

    root = tmp_path_factory.mktemp("sim")
    proto = root / "p.toml"
    proto.write_text((Path(__file__).parents[1] / "protocols" / "demo-d455.toml").read_text()
                     .replace("width = 1280", "width = 640").replace("height = 720", "height = 360"))
    code = run_cli(["simulate", "checkerboard", "--protocol", str(proto), "--model", "d455-ideal",
                    "--out", str(root / "s"),
                    "--frames", "12", "--standpoint", "standpoint_01", "--standpoint", "standpoint_02"])
    assert code == 0
    return root / "s"
