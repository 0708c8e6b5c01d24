"""The house's layers, read from the source: what each part may import, and no circles.

Every ``import`` statement of the package is read with :mod:`ast` (those inside functions too: a
lazy import is still an arrow). The rules are the ones of docs/design.md:

* ``engine/`` imports only the numerical floor (numpy, scipy, numba, scikit-image's thresholds and
  the standard library) and its own modules: never ``io``, ``tiled``, ``commands``, ``widgets``,
  ``report``, napari or Qt;
* ``io/`` may import the engine (the data model) but nothing above it;
* ``tiled/`` sits above ``engine`` and ``io``; ``commands/`` and ``widgets/`` sit on top;
* no two modules import each other, directly or around a longer circle.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = "napari_dvc_correct"
ROOT = Path(__file__).resolve().parents[1] / "src" / PACKAGE

#: Third-party top-level packages the engine may use (plus the standard library). llvmlite is
#: numba's code generator: the four-wide kernels (``engine/correlation/simd*.py``) write LLVM IR through it.
ENGINE_FLOOR = {"numpy", "scipy", "numba", "llvmlite", "skimage"}

#: For each part of the package, the parts it must not import.
FORBIDDEN = {
    "engine": {
        "io",
        "jobs",
        "tiled",
        "commands",
        "widgets",
        "report",
        "layers",
        "viewer_layers",
        "cli",
        "demo",
        "_reader",
        "_writer",
        "_sample_data",
    },
    "io": {
        "tiled",
        "jobs",
        "commands",
        "widgets",
        "report",
        "layers",
        "viewer_layers",
        "cli",
        "demo",
    },
    "tiled": {"jobs", "commands", "widgets", "report", "layers", "viewer_layers", "cli", "demo"},
    "report": {"tiled", "jobs", "commands", "widgets", "cli", "demo"},
    # a job may write a report (export does); the report never runs a job
    "jobs": {"commands", "widgets", "layers", "viewer_layers", "cli", "demo", "_reader", "_writer"},
    "commands": {
        "widgets",
        "layers",
        "viewer_layers",
        "demo",
        "_reader",
        "_writer",
        "_sample_data",
    },
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Absolute names of everything ``path`` imports (relative imports resolved)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module
            names.add(prefix)
            # ``from . import warp`` imports a module; ``from .field import Status`` a name
            names.update(f"{prefix}.{alias.name}" for alias in node.names)
    return names


def _graph() -> dict[str, set[str]]:
    modules = {_module_name(p): p for p in ROOT.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for imported in _imports(path):
            # the longest known module that the imported name starts with
            parts = imported.split(".")
            for k in range(len(parts), 0, -1):
                candidate = ".".join(parts[:k])
                if candidate in modules:
                    if candidate != name and not name.startswith(candidate + "."):
                        targets.add(candidate)
                    break
        graph[name] = targets
    return graph


def _part(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def test_the_scan_finds_the_package_and_its_arrows():
    graph = _graph()
    assert f"{PACKAGE}.engine.correlation.correlate" in graph
    assert (
        f"{PACKAGE}.engine.correlation.pyramid" in graph[f"{PACKAGE}.engine.correlation.correlate"]
    )
    assert f"{PACKAGE}.engine.correlation.icgn" in graph[f"{PACKAGE}.engine.correlation.pyramid"]
    assert f"{PACKAGE}.engine.fields.field" in graph[f"{PACKAGE}.io.npz"]


@pytest.mark.parametrize("part", sorted(FORBIDDEN))
def test_no_arrow_points_up(part):
    graph = _graph()
    wrong = sorted(
        f"{source} -> {target}"
        for source, targets in graph.items()
        if _part(source) == part
        for target in targets
        if _part(target) in FORBIDDEN[part]
    )
    assert not wrong, f"{part}/ imports upwards: {wrong}"


def test_the_engine_uses_only_the_numerical_floor():
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    wrong = []
    for path in (ROOT / "engine").rglob("*.py"):
        for imported in _imports(path):
            top = imported.split(".")[0]
            if top not in stdlib | ENGINE_FLOOR | {PACKAGE}:
                wrong.append(f"{_module_name(path)} imports {imported}")
    assert not wrong, wrong


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = [0]

    def visit(node):
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                item = stack.pop()
                on_stack.discard(item)
                component.append(item)
                if item == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_cycle_finder_finds_a_known_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_two_modules_import_each_other():
    graph = _graph()
    # a package's __init__ re-exporting its own modules is not a circle of design
    for name in list(graph):
        graph[name] = {t for t in graph[name] if not name.startswith(t + ".")}
        if (ROOT.parent / Path(*name.split(".")) / "__init__.py").exists():
            graph[name] = {t for t in graph[name] if not t.startswith(name + ".")}
    assert _cycles(graph) == []


#: The longest a source file may grow: past it, a module holds two things (split it by what
#: each part is, as engine/correlation/pyramid.py was split from correlate.py).
MAX_LINES = 600


def test_no_source_file_is_longer_than_a_reader_can_hold():
    long = {
        str(path.relative_to(ROOT)): n
        for path in ROOT.rglob("*.py")
        if (n := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"split these (lines): {long}"
