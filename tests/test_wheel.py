"""The wheel a user installs: built from this checkout's folders, installed into a fresh virtual
environment and run from a folder outside the checkout, so every module and data file it uses
comes from the wheel (the stage folders are mapped into `depthstation.<stage>` by pyproject's
`package-dir`; a package missing from its list would be missing here).

To stay offline and quick (~30 s on 2 quiet cores), the wheel is built with this environment's setuptools
(`--no-build-isolation`) and the new environment borrows this one's third-party packages through
a `.pth` line (its own site-packages, with the wheel in it, comes first); pip installs the wheel
itself with `--no-deps`.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import site
import subprocess
import sys
import zipfile
from importlib.metadata import version
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what the wheel is built from: the package's folders, as they are in this checkout
SOURCES = ("pyproject.toml", "README.md", "depthstation", "acquire", "evaluate", "simulate", "protocols")
# installed name of each folder
INSTALLED_AS = {"depthstation": "depthstation", "acquire": "depthstation/acquire",
                "evaluate": "depthstation/evaluate", "simulate": "depthstation/simulate",
                "protocols": "depthstation/protocols"}


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float = 120) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{cmd}: rc {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def _expected_files() -> set[str]:
    """The modules and data files of the checkout, under the names the wheel must give them."""
    out = set()
    for folder, name in INSTALLED_AS.items():
        for p in (ROOT / folder).rglob("*"):
            if p.is_file() and "__pycache__" not in p.parts and p.suffix in {".py", ".toml", ".typed"}:
                out.add(f"{name}/{p.relative_to(ROOT / folder).as_posix()}")
    return out


@pytest.mark.slow
def test_wheel_installs_and_runs_a_study(tmp_path: Path) -> None:
    if int(version("setuptools").split(".")[0]) < 77:
        pytest.skip("setuptools >= 77 (the dev extra) is needed to build the wheel offline")
    src = tmp_path / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    env = {k: v for k, v in os.environ.items() if k not in {"PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV"}}
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
          "--no-index", "-w", str(dist), str(src)], tmp_path, env, timeout=180)
    (wheel,) = dist.glob("depthstation-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = _expected_files() - names
    assert not missing, f"not in the wheel (a package missing from pyproject's list?): {sorted(missing)}"

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path, env)
    python = venv / "bin" / "python"
    purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                        tmp_path, env).strip())
    # this environment's third-party packages, after the new one's own (.pth lines are appended)
    (purelib / "borrowed.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
          "--no-index", str(wheel)], tmp_path, env, timeout=180)

    work = tmp_path / "work"
    work.mkdir()
    where = json.loads(_run([str(python), "-c", (
        "import json, depthstation, depthstation.acquire, depthstation.evaluate.scan, "
        "depthstation.simulate, depthstation.app.cli\n"
        "from depthstation.core.protocol import PROTOCOL_DIR\n"
        "from depthstation.simulate.model import MODEL_DIR\n"
        "print(json.dumps([m.__file__ for m in (depthstation, depthstation.acquire, "
        "depthstation.evaluate.scan, depthstation.simulate, depthstation.app.cli)]"
        " + [str(PROTOCOL_DIR), str(MODEL_DIR)]))")], work, env))
    for path in where:
        assert Path(path).resolve().is_relative_to(purelib.resolve()), (path, purelib)
        assert not Path(path).resolve().is_relative_to(ROOT), path

    exe = str(venv / "bin" / "depthstation")
    assert "Usage: depthstation" in _run([exe, "--help"], work, env)
    # the input comes from this checkout's simulator, whose compiled kernels are cached: the wheel's
    # are compiled afresh on first use (numba caches by source path), minutes for the simulator's
    _run([str(Path(sys.executable).parent / "depthstation"), "simulate", "checkerboard", "--protocol",
          "demo-d455", "--frames", "2", "--standpoint", "standpoint_01", "--standpoint", "standpoint_04",
          "--out", "sim"], work, env)
    board = purelib / "depthstation" / "protocols" / "demo-d455.toml"  # the package data, as shipped
    _run([exe, "evaluate", "checkerboard", "sim", "--board", str(board), "--out", "res"], work, env)
    truth = {s["name"]: s for s in json.loads((work / "sim" / "truth.json").read_text())["standpoints"]}
    rows = list(csv.DictReader((work / "res" / "standpoints.csv").open()))
    assert [r["standpoint"] for r in rows] == ["standpoint_01", "standpoint_04"]
    for r in rows:
        t = truth[r["standpoint"]]
        # the board pose from 24 corners at 1-2.6 m puts its centre within millimetres
        assert abs(float(r["distance_m"]) - t["distance_m"]) < 0.01, (r, t["distance_m"])
        assert abs(float(r["inclination_deg"]) - t["inclination_deg"]) < 1.0, (r, t["inclination_deg"])
