"""The stage folders (`acquire/`, `evaluate/`, `simulate/`) sit at the repository's top level but are
installed only as `depthstation.<stage>` (pyproject's `package-dir` mapping).

Why this module: from the repository root, Python finds those folders as top-level packages
(`import evaluate`), which would shadow unrelated PyPI packages of the same name (`evaluate` is
one) and import our code twice under two names. A stage's `__init__` calls `claim_stage` first:
imported under its own name it hands the import over to whatever else bears that name on
`sys.path` (or reports it as not found), so only `depthstation.<stage>` ever names this code.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path


def claim_stage(name: str, init_file: str) -> None:
    """Call from a stage's `__init__` with its `__name__` and `__file__`."""
    if name.startswith("depthstation."):
        return
    here = Path(init_file).resolve().parent.parent
    elsewhere = [p for p in sys.path if Path(p or ".").resolve() != here]
    spec = importlib.machinery.PathFinder.find_spec(name, elsewhere)
    if spec is None or spec.loader is None:
        raise ModuleNotFoundError(f"No module named {name!r} (the folder {name}/ here is "
                                  f"depthstation.{name}: import it under that name)", name=name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # the import statement returns what sys.modules holds afterwards
    spec.loader.exec_module(module)
