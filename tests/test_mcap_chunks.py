"""Our chunked MCAP writer against the mcap package's own readers (the format's reference code):
every message, its channel, times and bytes, the summary's statistics and indexes, CRCs checked."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import ChunkIndex, MessageIndex
from mcap.stream_reader import StreamReader

from depthstation.core.capture.mcap_chunks import ChunkedMcapWriter


def _write(compression: str, chunk_size: int) -> tuple[bytes, list[tuple[int, int, bytes]]]:
    rng = np.random.default_rng(1)
    out = io.BytesIO()
    w = ChunkedMcapWriter(out, profile="ros2", library="test", compression=compression,
                          chunk_size=chunk_size)
    sid = w.register_schema("pkg/msg/Thing", "ros2msg", b"uint8[] data")
    chans = [w.register_channel(f"/t{k}", "cdr", sid, {"k": str(k)}) for k in range(3)]
    w.add_metadata("format", {"json": "{}"})
    sent = []
    for i in range(40):
        cid = chans[i % 3]
        head = bytes([i]) * int(rng.integers(0, 9))
        body = rng.integers(0, 255, int(rng.integers(0, 3000)), dtype=np.uint8)
        t = 1_000_000 + i * 10 - (5 if i % 7 == 3 else 0)  # not monotonic everywhere
        w.add_message(cid, t, (head, body.data), t + 1, sequence=i)
        sent.append((cid, t, head + body.tobytes()))
    w.add_metadata("late", {"a": "b"})
    w.finish()
    return out.getvalue(), sent


@pytest.mark.parametrize("compression", ["", "lz4", "zstd"])
def test_mcap_readers_see_every_message(compression: str) -> None:
    data, sent = _write(compression, chunk_size=10_000)
    seek = SeekingReader(io.BytesIO(data), validate_crcs=True)
    summary = seek.get_summary()
    assert summary is not None and summary.statistics is not None
    st = summary.statistics
    assert st.message_count == 40 and st.channel_count == 3 and st.schema_count == 1
    assert st.metadata_count == 2 and st.chunk_count == len(summary.chunk_indexes) > 3
    assert st.message_start_time == min(t for _, t, _ in sent)
    assert st.message_end_time == max(t for _, t, _ in sent)
    assert {c.topic for c in summary.channels.values()} == {"/t0", "/t1", "/t2"}
    got = [(c.id, m.log_time, m.data) for _, c, m in seek.iter_messages(log_time_order=False)]
    assert got == sent
    ordered = [m.log_time for _, _, m in seek.iter_messages(log_time_order=True)]
    assert ordered == sorted(t for _, t, _ in sent)
    assert {m.name: m.metadata for m in seek.iter_metadata()}["late"] == {"a": "b"}
    stream = [(c.id, m.log_time, m.data) for _, c, m in NonSeekingReader(io.BytesIO(data)).iter_messages()]
    assert stream == sent


def test_message_indexes_point_at_their_messages() -> None:
    data, sent = _write("", chunk_size=10_000)
    recs = list(StreamReader(io.BytesIO(data), emit_chunks=True).records)
    index_recs = [r for r in recs if isinstance(r, MessageIndex)]
    assert sum(len(r.records) for r in index_recs) == len(sent)
    summary = SeekingReader(io.BytesIO(data)).get_summary()
    assert summary is not None
    for ci in summary.chunk_indexes:
        assert isinstance(ci, ChunkIndex)
        chunk_bytes = data[ci.chunk_start_offset: ci.chunk_start_offset + ci.chunk_length]
        assert chunk_bytes[0] == 0x06
        for cid, off in ci.message_index_offsets.items():
            assert data[off] == 0x07 and int.from_bytes(data[off + 9: off + 11], "little") == cid
        assert ci.message_index_length > 0


def test_written_file_is_standard_on_disk(tmp_path: Path) -> None:
    """Through a real buffered file: the writer counts offsets itself and never asks tell()."""
    p = tmp_path / "x.mcap"
    with p.open("xb") as f:
        w = ChunkedMcapWriter(f, profile="ros2", library="test", compression="lz4", chunk_size=4096)
        sid = w.register_schema("pkg/msg/Thing", "ros2msg", b"uint8[] data")
        cid = w.register_channel("/t", "cdr", sid)
        for i in range(10):
            w.add_message(cid, i, (b"x" * 1000,), i)
        w.finish()
    with p.open("rb") as f:
        msgs = list(SeekingReader(f, validate_crcs=True).iter_messages())
    assert len(msgs) == 10 and all(m.data == b"x" * 1000 for _, _, m in msgs)
