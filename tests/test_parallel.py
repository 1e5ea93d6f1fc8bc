"""The executor: serial, local processes and a Dask LocalCluster give the same merged statistics.

The chunk function here is a small, independent stand-in for a grid evaluation: it reads its
frame range from a file (chunks carry a path and a range, never pixels), bins values into cells
and keeps count/mean/M2 by Welford; partial results merge by Chan's formula written here. The
truth is a plain two-pass numpy mean/variance over all frames at once.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from depthstation.core.parallel import ChunkRunner, WorkerLost, reduce_chunks, run_chunks

CELLS = 16


@dataclass(frozen=True)
class SynthChunk:
    path: str
    start: int
    stop: int
    index: int
    kill_flag: str = ""  # when set: the first worker to see it dies (os._exit) on chunk 1


def synth_cells(frames: np.ndarray) -> np.ndarray:
    return (np.arange(frames.shape[-1]) % CELLS)[None, :].repeat(frames.shape[0], 0)


def welford_chunk(chunk: SynthChunk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """count, mean, M2 per cell over frames [start, stop) of the file (read here, by the worker)."""
    if chunk.kill_flag and chunk.index == 1 and not Path(chunk.kill_flag).exists():
        Path(chunk.kill_flag).write_text(str(os.getpid()))
        os._exit(17)  # the worker dies mid-run, as if killed
    data = np.load(chunk.path, mmap_mode="r")[chunk.start:chunk.stop]
    count = np.zeros(CELLS, np.int64)
    mean = np.zeros(CELLS)
    m2 = np.zeros(CELLS)
    for frame in data:
        cells = np.arange(frame.size) % CELLS
        for c, x in zip(cells, frame, strict=True):
            count[c] += 1
            d = x - mean[c]
            mean[c] += d / count[c]
            m2[c] += d * (x - mean[c])
    return count, mean, m2


def chan(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    na, ma, sa = a
    nb, mb, sb = b
    n = na + nb
    safe = np.maximum(n, 1)
    d = mb - ma
    return n, ma + d * nb / safe, sa + sb + d * d * na * nb / safe


def raise_on_two(chunk: SynthChunk) -> int:
    if chunk.index == 2:
        raise ValueError("bad chunk 2")
    return chunk.index


@pytest.fixture(scope="module")
def frames_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(7)
    frames = 3.0 + rng.normal(0, 0.01, (24, 48)) + (np.arange(48) % CELLS) * 0.1
    path = tmp_path_factory.mktemp("synth") / "frames.npy"
    np.save(path, frames)
    return path


def chunks_of(path: Path, size: int = 4, kill_flag: str = "") -> list[SynthChunk]:
    n = np.load(path, mmap_mode="r").shape[0]
    return [SynthChunk(str(path), s, min(s + size, n), i, kill_flag)
            for i, s in enumerate(range(0, n, size))]


def truth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    data = np.load(path)
    cells = synth_cells(data).ravel()
    x = data.ravel()
    count = np.bincount(cells, minlength=CELLS)
    mean = np.bincount(cells, x, minlength=CELLS) / count
    var = np.bincount(cells, (x - mean[cells]) ** 2, minlength=CELLS) / (count - 1)
    return count, mean, var


def assert_matches_truth(result: tuple[np.ndarray, ...], path: Path) -> None:
    count, mean, var = truth(path)
    np.testing.assert_array_equal(result[0], count)
    np.testing.assert_allclose(result[1], mean, rtol=1e-13)
    np.testing.assert_allclose(result[2] / (result[0] - 1), var, rtol=1e-9)


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as lc:
        yield lc.scheduler_address


def test_serial_merge_matches_two_pass_truth(frames_file: Path) -> None:
    seen: list[tuple[int, int]] = []
    result = reduce_chunks(welford_chunk, chunks_of(frames_file), chan,
                           progress=lambda d, t: seen.append((d, t)))
    assert_matches_truth(result, frames_file)
    assert seen[0] == (0, 6) and seen[-1] == (6, 6)
    assert [d for d, _ in seen] == list(range(7))


def test_local_processes_equal_serial(frames_file: Path) -> None:
    chunks = chunks_of(frames_file, size=3)
    serial = reduce_chunks(welford_chunk, chunks, chan)
    local = reduce_chunks(welford_chunk, chunks, chan, workers=2)
    for a, b in zip(serial, local, strict=True):
        np.testing.assert_array_equal(a, b)  # same merge order: same floats
    listed = run_chunks(welford_chunk, chunks, workers=2)
    assert len(listed) == len(chunks)
    np.testing.assert_array_equal(listed[3][1], welford_chunk(chunks[3])[1])


def test_local_worker_killed_reruns_its_chunk(frames_file: Path, tmp_path: Path) -> None:
    flag = tmp_path / "killed"
    chunks = chunks_of(frames_file, size=4, kill_flag=str(flag))
    with ChunkRunner(workers=2) as runner:
        result = runner.reduce(welford_chunk, chunks, chan)
    assert flag.exists(), "the chunk function did not kill its worker"
    serial = reduce_chunks(welford_chunk, chunks_of(frames_file, size=4), chan)
    for a, b in zip(serial, result, strict=True):
        np.testing.assert_array_equal(a, b)


def always_die(chunk: SynthChunk) -> int:
    os._exit(3)


def test_local_chunk_that_always_kills_gives_up(frames_file: Path) -> None:
    with pytest.raises(WorkerLost, match="lost its worker"):
        run_chunks(always_die, chunks_of(frames_file)[:1], workers=2)


def test_chunk_error_propagates(frames_file: Path) -> None:
    for workers in (1, 2):
        with pytest.raises(ValueError, match="bad chunk 2"):
            run_chunks(raise_on_two, chunks_of(frames_file), workers=workers)


def test_single_machine_path_does_not_import_dask(frames_file: Path) -> None:
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_parallel import welford_chunk, chunks_of, chan
        from pathlib import Path
        from depthstation.core.parallel import reduce_chunks
        if __name__ == "__main__":
            reduce_chunks(welford_chunk, chunks_of(Path({str(frames_file)!r})), chan, workers=2)
            bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed'))
            print('DASK' if bad else 'CLEAN', bad[:3])
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("CLEAN"), out.stdout


def test_dask_cluster_equals_serial_and_survives_a_killed_worker(
        frames_file: Path, cluster: str, tmp_path: Path) -> None:
    chunks = chunks_of(frames_file, size=3)
    serial = reduce_chunks(welford_chunk, chunks, chan)
    done: list[int] = []
    with ChunkRunner(cluster=cluster) as runner:
        on_dask = runner.reduce(welford_chunk, chunks, chan, progress=lambda d, t: done.append(d))
        for a, b in zip(serial, on_dask, strict=True):
            np.testing.assert_array_equal(a, b)
        assert done[-1] == len(chunks)
        flag = tmp_path / "killed"
        killed = runner.reduce(welford_chunk, chunks_of(frames_file, size=3, kill_flag=str(flag)), chan)
    assert flag.exists(), "the chunk function did not kill its worker"
    for a, b in zip(serial, killed, strict=True):
        np.testing.assert_array_equal(a, b)
    assert_matches_truth(killed, frames_file)


def test_unreachable_cluster_is_a_clear_input_error(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("distributed")
    from depthstation.core.errors import InputError

    monkeypatch.setenv("DEPTHSTATION_CLUSTER_TIMEOUT", "1")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        run_chunks(raise_on_two, [], cluster="tcp://127.0.0.1:1")
