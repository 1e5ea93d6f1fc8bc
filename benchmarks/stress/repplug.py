"""A pytest plugin that repeats each collected test `--rep` times in a row (module fixtures shared).

Used by `benchmarks/stress/stress.sh` to run the kill/interrupt tests 50 times beside two busy
processes: a race shows as one failure among the repeats.
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--rep", type=int, default=1, help="run every test this many times in a row")


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    n = metafunc.config.getoption("rep")
    if n > 1:
        metafunc.fixturenames.append("_rep")
        metafunc.parametrize("_rep", range(n))
