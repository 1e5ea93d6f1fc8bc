"""Colour as the D4xx sends it (YUYV 4:2:2, BT.601 video range): the encoder against the standard's
own values, readers of our MCAP and of realsense-ros bags giving RGB back, the simulator's sequences
recorded so, and `capture compact` keeping the encoding.

Tolerances: video-range luma has 219 steps over 255 DN (1.164 DN a step, +-0.58 DN of rounding),
decoding rounds again (+-0.5) in fixed point, so a pixel's grey comes back within 2 DN; a colour
that is constant over each pixel pair loses nothing to the 4:2:2 chroma and comes back within 2 DN
in every channel (chroma steps are 1.13-1.40 DN per channel, rounded twice).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from depthstation.app.capture_cli import compact_cmd
from depthstation.core.capture import yuv
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.sample_recordings import sample_info
from depthstation.core.frames import FrameSet
from tests.ros_bags import write_bag, yuyv_bt601

# ITU-R BT.601 video-range (Y, Cb, Cr) of the primaries, as tabulated with the standard
PRIMARIES = {(255, 255, 255): (235, 128, 128), (0, 0, 0): (16, 128, 128), (255, 0, 0): (81, 90, 240),
             (0, 255, 0): (145, 54, 34), (0, 0, 255): (41, 240, 110)}


def _pairs_image(h: int, w: int, seed: int) -> np.ndarray:
    """Random colours, each constant over a horizontal pixel pair (4:2:2 chroma keeps them)."""
    half = np.random.default_rng(seed).integers(0, 256, (h, w // 2, 3), dtype=np.uint8)
    return np.repeat(half, 2, axis=1)


def _grey(a: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY).astype(int)


def test_encoder_gives_the_standards_values() -> None:
    for rgb, (y, cb, cr) in PRIMARIES.items():
        img = np.full((2, 4, 3), rgb, np.uint8)
        out = yuv.rgb_to_yuy2(img)
        assert (out[..., 0] == y).all(), rgb
        assert (out[:, 0::2, 1] == cb).all() and (out[:, 1::2, 1] == cr).all(), rgb
        np.testing.assert_array_equal(out, yuyv_bt601(img))  # the test's own equations


def test_round_trip_within_the_quantisation() -> None:
    rgb = _pairs_image(48, 64, 1)
    back = yuv.yuv422_to_rgb(yuv.rgb_to_yuy2(rgb), yuv.ENCODING)
    assert np.abs(back.astype(int) - rgb).max() <= 2
    # sensor-like noise round mid-grey: the pair's chroma is averaged, each pixel's luma kept (so its
    # grey), as long as the decoded colour needs no clipping (fully random colours would)
    noisy = np.clip(np.random.default_rng(2).normal(128, 20, (48, 64, 3)), 0, 255).astype(np.uint8)
    back = yuv.yuv422_to_rgb(yuv.rgb_to_yuy2(noisy), "yuyv")
    assert np.abs(_grey(back) - _grey(noisy)).max() <= 2
    uyvy = yuv.rgb_to_yuy2(rgb)[..., ::-1]  # (Y, C) -> (C, Y): UYVY
    back = yuv.yuv422_to_rgb(np.ascontiguousarray(uyvy), yuv.UYVY_ENCODING)
    assert np.abs(back.astype(int) - rgb).max() <= 2
    with pytest.raises(ValueError, match="even width"):
        yuv.rgb_to_yuy2(np.zeros((2, 3, 3), np.uint8))


def _frames(info: object, n: int) -> list[FrameSet]:
    ci = info.color_intrinsics  # type: ignore[attr-defined]
    di = info.depth_intrinsics  # type: ignore[attr-defined]
    rng = np.random.default_rng(3)
    return [FrameSet(k, 1_700_000_000_000_000_000 + k * 33_333_333,
                     rng.integers(300, 5000, (di.height, di.width), dtype=np.uint16),
                     _pairs_image(ci.height, ci.width, 10 + k), None, {}) for k in range(n)]


def test_our_mcap_in_yuyv_reads_back_as_rgb_and_is_two_thirds(tmp_path: Path) -> None:
    info = sample_info(64, 48)
    frames = _frames(info, 3)
    write_mcap(tmp_path / "rgb.mcap", info, frames)
    write_mcap(tmp_path / "yuv.mcap", info, frames, color_encoding=yuv.ENCODING)
    rec = open_recording(tmp_path / "yuv.mcap")
    assert rec.metadata["format"]["color_encoding"] == yuv.ENCODING
    for got, sent in zip(rec.frames(), frames, strict=True):
        np.testing.assert_array_equal(got.depth, sent.depth)
        assert got.color is not None and np.abs(got.color.astype(int) - sent.color).max() <= 2
    # uncompressed, each colour image is one byte a pixel smaller; the rest differs only by the
    # encoding's name in each image header and the format record
    saved = (tmp_path / "rgb.mcap").stat().st_size - (tmp_path / "yuv.mcap").stat().st_size
    assert abs(saved - 3 * 64 * 48) <= 3 * 16 + 64


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_realsense_ros_bag_with_yuyv_colour(tmp_path: Path, storage: str) -> None:
    info = sample_info(64, 48)
    frames = _frames(info, 3)
    bag = tmp_path / "bag"
    write_bag(bag, info, frames, storage=storage, color_encoding="yuv422_yuy2")
    got = list(open_recording(bag).frames())
    assert len(got) == 3
    for g, sent in zip(got, frames, strict=True):
        assert g.color is not None and g.color.shape == sent.color.shape
        assert np.abs(g.color.astype(int) - sent.color).max() <= 2


def test_simulated_sequence_in_yuyv_and_compact_keeps_it(tmp_path: Path) -> None:
    from depthstation.simulate.scan_sequence import simulate_scan

    a = simulate_scan("room", "walk", "d455-ideal", tmp_path / "yuv", frames=2, width=320, height=240)
    b = simulate_scan("room", "walk", "d455-ideal", tmp_path / "rgb", frames=2, width=320, height=240,
                      color_encoding="rgb8")
    ra, rb = open_recording(a / "sequence.mcap"), open_recording(b / "sequence.mcap")
    assert ra.metadata["format"]["color_encoding"] == yuv.ENCODING
    for fa, fb in zip(ra.frames(), rb.frames(), strict=True):
        np.testing.assert_array_equal(fa.depth, fb.depth)  # same seed, same sensor
        assert np.abs(_grey(fa.color) - _grey(fb.color)).max() <= 2
    out = tmp_path / "compact.mcap"
    compact_cmd(a / "sequence.mcap", out, compression="zstd")
    rc = open_recording(out)
    assert rc.metadata["format"]["color_encoding"] == yuv.ENCODING
    for fa, fc in zip(ra.frames(), rc.frames(), strict=True):
        np.testing.assert_array_equal(fa.color, fc.color)  # no second loss
