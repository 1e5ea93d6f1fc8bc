"""TOML parsing on every supported Python: the standard `tomllib` (3.11+), else `tomli` (3.10),
which has the same API. Every TOML reader (boards, protocols, models, batch manifests) imports
`tomllib` from here."""

from __future__ import annotations

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10 (tests/test_install.py hides tomllib to run this)
    import tomli as tomllib  # type: ignore[no-redef]

__all__ = ["tomllib"]
