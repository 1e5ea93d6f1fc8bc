"""What a new user meets first: full-width tables and progress lines in a log, compare's word when
nothing matches, compact's word when nothing was saved."""

from __future__ import annotations

from pathlib import Path

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
