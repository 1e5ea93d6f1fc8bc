"""Chunk-compressed captures (lz4 for recordings, zstd for simulations and `capture compact`) read
back unchanged by our reader, by rosbags, and by rerun's own MCAP importer (`capture compact` is
tested in test_capture_cli.py)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.capture.mcap_writer import CAPTURE_COMPRESSION, SIMULATION_COMPRESSION, write_mcap
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.capture.session import Session


def _chunk_compressions(path: Path) -> set[str]:
    """The compression field of every chunk record, read with the mcap package's own reader."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with path.open("rb") as f:
        return {r.compression for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)}


@pytest.mark.parametrize("compression", ["lz4", "zstd"])
def test_compressed_capture_reads_back_in_every_reader(tmp_path: Path, compression: str) -> None:
    from rosbags.highlevel import AnyReader

    info = sample_info()
    frames = list(sample_frames(info, 3))
    path = tmp_path / f"x-{compression}.mcap"
    write_mcap(path, info, frames, compression=compression)
    assert _chunk_compressions(path) == {compression}
    got = list(open_recording(path).frames())
    assert [f.index for f in got] == [f.index for f in frames]
    for a, b in zip(got, frames, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.color, b.color)
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == "/camera/depth/image_rect_raw"]
        msgs: list[Any] = [reader.deserialize(raw, c.msgtype)
                           for c, _, raw in reader.messages(connections=conns)]
    assert len(msgs) == 3
    np.testing.assert_array_equal(np.frombuffer(msgs[1].data, np.uint16).reshape(frames[1].depth.shape),
                                  frames[1].depth)
    exe = Path(sys.executable).parent / "rerun"
    if not exe.exists() and shutil.which("rerun") is None:
        pytest.skip("rerun CLI not installed")
    rerun = str(exe) if exe.exists() else str(shutil.which("rerun"))
    rrd = tmp_path / "x.rrd"
    subprocess.run([rerun, "mcap", "convert", str(path), "-o", str(rrd)], check=True, capture_output=True,
                   timeout=120)
    text = subprocess.run([rerun, "rrd", "print", "-vvv", str(rrd)], check=True, capture_output=True,
                          text=True, timeout=120).stdout
    rows = [ln for ln in text.splitlines() if "channel_datatype" in ln and "camera_depth_optical_frame" in ln]
    assert len(rows) == 3


def test_recordings_are_lz4_and_simulations_zstd_by_default(tmp_path: Path) -> None:
    info = sample_info()
    s = Session.create(tmp_path / "s", device=info.device)
    with s.standpoint_writer("standpoint_01", info, blocking=True) as w:
        for fs in sample_frames(info, 2):
            w.write(fs)
    assert _chunk_compressions(tmp_path / "s" / "standpoint_01.mcap") == {CAPTURE_COMPRESSION} == {"lz4"}
    assert SIMULATION_COMPRESSION == "zstd"
