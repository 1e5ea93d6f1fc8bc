"""Jobs split between this process and a forked child (`core.forked`): the same values and files as
a serial run, in order, whatever the child does (finishes, raises, dies)."""

from __future__ import annotations

import os
import time
from functools import partial
from pathlib import Path

import pytest

from depthstation.core import forked
from depthstation.core.forked import ENV_SWITCH, can_fork, run_split, split_jobs

PARENT = os.getpid()


def _write(path: Path, value: int) -> int:
    """A job: writes which process ran it, returns a value."""
    path.write_text(str(os.getpid()))
    return value * value


def _raise_in_child(path: Path) -> int:
    if os.getpid() != PARENT:
        raise ValueError("only in the child")
    path.write_text(str(os.getpid()))
    return 7


def _die_in_child(path: Path) -> int:
    if os.getpid() != PARENT:
        os._exit(9)  # as if killed: no value, no clean exit
    path.write_text(str(os.getpid()))
    return 8


def _always_raise() -> int:
    raise ValueError("bad figure input")


def test_longest_jobs_alternate_between_the_two_sides() -> None:
    here, child = split_jobs([0.2, 1.0, 0.9, 0.5, 0.4])
    assert sorted(here + child) == [0, 1, 2, 3, 4]
    loads = [sum([0.2, 1.0, 0.9, 0.5, 0.4][k] for k in side) for side in (here, child)]
    assert abs(loads[0] - loads[1]) <= 0.5  # greedy longest-first: within the smallest-but-one job
    assert 1 in here and 2 in child


def test_values_come_back_in_order_and_the_child_did_its_share(tmp_path: Path) -> None:
    jobs = [partial(_write, tmp_path / f"f{k}.txt", k) for k in range(6)]
    assert run_split(jobs) == [k * k for k in range(6)]
    writers = {int((tmp_path / f"f{k}.txt").read_text()) for k in range(6)}
    if can_fork():
        assert PARENT in writers and len(writers) == 2  # half here, half in one child
    else:
        assert writers == {PARENT}


@pytest.mark.skipif(not can_fork(), reason="this platform runs the jobs serially")
def test_a_job_that_fails_in_the_child_is_run_again_here(tmp_path: Path) -> None:
    jobs = [partial(_raise_in_child, tmp_path / f"r{k}.txt") for k in range(2)]
    assert run_split(jobs) == [7, 7]
    assert {int((tmp_path / f"r{k}.txt").read_text()) for k in range(2)} == {PARENT}


@pytest.mark.skipif(not can_fork(), reason="this platform runs the jobs serially")
def test_a_child_that_dies_leaves_its_jobs_to_this_process(tmp_path: Path) -> None:
    jobs = [partial(_die_in_child, tmp_path / f"d{k}.txt") for k in range(3)]
    assert run_split(jobs) == [8, 8, 8]
    assert all((tmp_path / f"d{k}.txt").exists() for k in range(3))


def test_an_error_in_a_job_reaches_the_caller() -> None:
    with pytest.raises(ValueError, match="bad figure input"):
        run_split([_always_raise, _always_raise, _always_raise])


def test_the_switch_runs_everything_here(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV_SWITCH, "0")
    assert not can_fork()
    jobs = [partial(_write, tmp_path / f"s{k}.txt", k) for k in range(4)]
    assert run_split(jobs) == [0, 1, 4, 9]
    assert {int((tmp_path / f"s{k}.txt").read_text()) for k in range(4)} == {PARENT}


def _hang_in_child(path: Path) -> int:
    if os.getpid() != PARENT:
        time.sleep(60)  # a child stuck (e.g. on a lock another thread held at the fork)
    path.write_text(str(os.getpid()))
    return 5


@pytest.mark.skipif(not can_fork(), reason="this platform runs the jobs serially")
def test_a_child_that_hangs_is_killed_and_its_jobs_run_here(tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(forked, "CHILD_PATIENCE", (0.5, 1.0))
    t = time.monotonic()
    assert run_split([partial(_hang_in_child, tmp_path / f"h{k}.txt") for k in range(2)]) == [5, 5]
    assert time.monotonic() - t < 10
    assert {int((tmp_path / f"h{k}.txt").read_text()) for k in range(2)} == {PARENT}
