"""Shared fixtures: paths to the real data beside the repository, skipped with a reason when absent."""

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
