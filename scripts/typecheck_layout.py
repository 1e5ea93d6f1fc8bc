"""Lay out `build/typecheck/depthstation/<stage>` as links to the stage folders, for type checkers.

The stage folders install as `depthstation.<stage>` through setuptools' package-dir mapping; an
editable install serves that mapping with an import hook, which Python follows and static tools
(mypy, editors) do not. mypy's `mypy_path` names this folder: it finds `depthstation` itself in
the checkout and each stage here. Links are made at install time (`scripts/install.sh`), never
committed: a symbolic link where the system allows one, else a directory junction (Windows).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "build" / "typecheck" / "depthstation"
STAGES = ("acquire", "evaluate", "simulate")
MARKER = '"""The stage folders for type checkers: scripts/typecheck_layout.py."""\n'


def _link(link: Path, target: Path) -> None:
    if link.is_symlink() or link.exists():
        if link.resolve() == target.resolve():
            return
        link.unlink()
    try:
        link.symlink_to(os.path.relpath(target, link.parent), target_is_directory=True)
    except OSError:
        if sys.platform != "win32":
            raise
        subprocess.run(["cmd", "/c", "mklink", "/J", str(link), str(target)], check=True,
                       capture_output=True)


def main() -> None:
    LAYOUT.mkdir(parents=True, exist_ok=True)
    # a package marker for mypy only: `depthstation` itself is found in the checkout first
    (LAYOUT / "__init__.py").write_text(MARKER)
    for stage in STAGES:
        _link(LAYOUT / stage, ROOT / stage)
    print(f"typecheck layout: {LAYOUT}", file=sys.stderr)


if __name__ == "__main__":
    main()
