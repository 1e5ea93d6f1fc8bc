"""The house's layers, checked on the installed package's import graph (function-local imports too).

core <- simulate <- acquire / evaluate <- app: a module imports only from its own layer or below
(acquire and evaluate may both use simulate: the simulated camera, explain's re-simulation; they
never use each other). No module takes part in an import cycle. Imports inside functions are
allowed only for optional or heavy third-party packages, never for the project's own modules,
so the graph read from the top of each file is the real one.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
import pkgutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import depthstation

ROOT = Path(__file__).resolve().parents[1]

# what each layer may import from the project (besides itself)
LAYERS = {"core": 0, "simulate": 1, "acquire": 2, "evaluate": 2, "app": 3}
MAY_IMPORT = {
    "core": {"core"},
    "simulate": {"core", "simulate"},
    "acquire": {"core", "simulate", "acquire"},
    "evaluate": {"core", "simulate", "evaluate"},
    "app": {"core", "simulate", "acquire", "evaluate", "app"},
}
# third-party packages a function may import on first use: optional extras, or heavy imports that
# only some commands need (seconds of start-up each, or a native viewer/camera library)
LAZY_OK = {"open3d", "rerun", "matplotlib", "pyrealsense2", "dask", "distributed", "pye57", "laspy",
           "lazrs", "laszip", "tomli", "scipy"}


def layer_of(module: str) -> str:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    return "core"  # the package root and anything not in a stage belongs to the core


@dataclass
class ModuleImports:
    name: str
    path: Path
    top: set[str] = field(default_factory=set)          # project modules imported at module level
    local: list[tuple[int, str]] = field(default_factory=list)  # (line, module) inside functions
    type_only: set[str] = field(default_factory=set)    # under `if TYPE_CHECKING:`


STAGES = ("acquire", "evaluate", "simulate")


def _modules() -> dict[str, Path]:
    """Every module of the package. The stages are walked from their own `__path__`: an editable
    install maps them onto the top-level folders, which `depthstation.__path__` does not hold."""
    out = {"depthstation": Path(depthstation.__file__)}
    packages = [depthstation, *(importlib.import_module(f"depthstation.{s}") for s in STAGES)]
    for package in packages:
        out[package.__name__] = Path(str(package.__file__))
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            spec = importlib.util.find_spec(info.name)
            assert spec is not None and spec.origin is not None, info.name
            out[info.name] = Path(spec.origin)
    return out


def test_the_graph_holds_every_layer() -> None:
    """The checks below see every layer's modules (a walk of `depthstation.__path__` alone would
    miss the stages of an editable install and pass on half the package)."""
    mods = _modules()
    assert {layer_of(n) for n in mods} == set(LAYERS)
    on_disk = {p.resolve() for stage in STAGES for p in (ROOT / stage).rglob("*.py")
               if "__pycache__" not in p.parts}
    if all(str(p).startswith(str(ROOT)) for p in mods.values()):  # the checkout is what is installed
        assert on_disk <= {p.resolve() for p in mods.values()}


def _resolve(mod: str, names: list[str], known: set[str]) -> list[str]:
    """`from mod import a, b`: the submodules a, b when they are modules, else mod itself."""
    out = []
    for n in names:
        cand = f"{mod}.{n}"
        out.append(cand if cand in known else mod)
    return out


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def scan(name: str, path: Path, known: set[str]) -> ModuleImports:
    tree = ast.parse(path.read_text(), str(path))
    res = ModuleImports(name, path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]

    def visit(node: ast.AST, in_function: bool, type_only: bool) -> None:
        for child in ast.iter_child_nodes(node):
            func = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            tc = type_only or (isinstance(child, ast.If) and _is_type_checking(child))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")[: len(package.split(".")) - child.level + 1]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                targets = _resolve(mod, [a.name for a in child.names], known)
            for t in targets:
                project = t.split(".")[0] == "depthstation"
                if in_function:
                    res.local.append((child.lineno, t))
                elif project and tc:
                    res.type_only.add(t)
                elif project:
                    res.top.add(t)
            visit(child, func, tc)

    visit(tree, False, False)
    return res


def _graph() -> dict[str, ModuleImports]:
    mods = _modules()
    known = set(mods)
    return {n: scan(n, p, known) for n, p in mods.items()}


def _resolve_known(target: str, known: set[str]) -> str | None:
    while target and target not in known:
        target = target.rpartition(".")[0]
    return target or None


def test_no_function_local_project_imports() -> None:
    bad = []
    for m in _graph().values():
        for line, target in m.local:
            top = target.split(".")[0]
            if top == "depthstation" or top not in LAZY_OK:
                bad.append(f"{m.path}:{line}: imports {target} inside a function")
    assert not bad, "imports belong at the top of the module:\n" + "\n".join(bad)


def test_imports_follow_the_layers() -> None:
    graph = _graph()
    known = set(graph)
    bad = []
    for m in graph.values():
        src = layer_of(m.name)
        for target in sorted(m.top | m.type_only | {t for _, t in m.local}):
            t = _resolve_known(target, known)
            if t is None or not t.startswith("depthstation"):
                continue
            dst = layer_of(t)
            if dst not in MAY_IMPORT[src]:
                bad.append(f"{m.name} ({src}) imports {t} ({dst})")
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_no_import_cycles() -> None:
    graph = _graph()
    known = set(graph)
    edges = {n: {t for x in (m.top | {t for _, t in m.local}) if (t := _resolve_known(x, known)) and t != n}
             for n, m in graph.items()}
    # Tarjan's strongly connected components
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10000)

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in edges:
        if v not in index:
            strong(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_checker_sees_a_cycle_and_a_layer_breach(tmp_path: Path) -> None:
    """The checks above can fail: a package written here with a cycle and an upward import."""
    pkg = tmp_path / "depthstation_probe"
    (pkg / "core").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "__init__.py").write_text("")
    (pkg / "core" / "a.py").write_text("from depthstation.core import b\n")
    (pkg / "core" / "b.py").write_text(
        "import depthstation.core.a\n\ndef f():\n    import depthstation.app.x\n")
    known = {"depthstation.core.a", "depthstation.core.b", "depthstation.app.x"}
    a = scan("depthstation.core.a", pkg / "core" / "a.py", known)
    b = scan("depthstation.core.b", pkg / "core" / "b.py", known)
    assert a.top == {"depthstation.core.b"}
    assert b.top == {"depthstation.core.a"}
    assert b.local == [(4, "depthstation.app.x")]
    assert layer_of("depthstation.app.x") not in MAY_IMPORT[layer_of("depthstation.core.b")]


def test_stage_folders_are_not_top_level_packages(tmp_path: Path) -> None:
    """`import evaluate` never finds this project, from the repository root or elsewhere."""
    for cwd in (ROOT, tmp_path):
        for stage in ("acquire", "evaluate", "simulate"):
            proc = subprocess.run([sys.executable, "-c", f"import {stage}"], cwd=cwd,
                                  capture_output=True, text=True, timeout=60)
            if proc.returncode == 0:  # some other installed package of that name: not ours
                check = subprocess.run(
                    [sys.executable, "-c", f"import {stage}, sys; print({stage}.__file__)"],
                    cwd=cwd, capture_output=True, text=True, timeout=60)
                assert str(ROOT) not in check.stdout, (cwd, stage, check.stdout)
            else:
                assert "ModuleNotFoundError" in proc.stderr, proc.stderr


def test_a_stage_hands_its_bare_name_on(tmp_path: Path) -> None:
    """Why `depthstation/core/stage_folder.py` stays: from the repository root Python looks in the
    current directory first, so without it `import evaluate` would run our `evaluate/` folder (a
    second copy of our modules, under a name that is not ours) instead of the package of that name
    the user installed (HuggingFace's `evaluate` is one)."""
    other = tmp_path / "site"
    (other / "evaluate").mkdir(parents=True)
    (other / "evaluate" / "__init__.py").write_text("WHO = 'the other evaluate'\n")
    env = {**os.environ, "PYTHONPATH": str(other)}
    proc = subprocess.run([sys.executable, "-c", "import evaluate, sys; print(evaluate.WHO); "
                           "print(any(m == 'evaluate.scan' for m in sys.modules))"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["the", "other", "evaluate", "False"], proc.stdout
