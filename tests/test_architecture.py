"""The package's structure: no import cycles, and each stage in the package named for it.

Imports are read from the source (every ``import`` and ``from ... import``, at module
level or inside functions, TYPE_CHECKING included), so a cycle hidden behind a lazy
import is found too. Importing ``geoidspline.b.c`` also runs ``geoidspline/b/__init__``:
that counts as an edge (the root package's own imports are checked on their own).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "geoidspline"


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _resolve(current: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = current.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        is_package = path.name == "__init__.py"
        targets = []
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets += [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(name, is_package, node)
                targets.append(base)
                # "from pkg import mod" imports the submodule
                targets += [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules]
        for target in targets:
            if not target.startswith("geoidspline"):
                continue
            parts = target.split(".")
            # the target and every package above it but the root, whose module-level
            # imports are light (its functions import the API lazily)
            for i in range(2, len(parts) + 1):
                candidate = ".".join(parts[:i])
                # a module's own packages are always initialised before it
                own_package = name.startswith(candidate + ".") and i < len(parts)
                if candidate in modules and candidate != name and not own_package:
                    graph[name].add(candidate)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_root_package_imports_only_light_modules():
    tree = ast.parse((PACKAGE / "__init__.py").read_text())
    top = {node.module for node in tree.body if isinstance(node, ast.ImportFrom)}
    assert top <= {"__future__", "_version", "errors", "sphere.region"}


def test_the_package_has_no_import_cycle():
    assert cycles(import_graph()) == []


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


@pytest.mark.parametrize("low, high", [
    ("geoidspline.sphere", "geoidspline.fitting"),
    ("geoidspline.bspline", "geoidspline.store"),
    ("geoidspline.bspline", "geoidspline.hierarchy"),
    ("geoidspline.sources", "geoidspline.store"),
    ("geoidspline.sources", "geoidspline.fitting"),
    ("geoidspline.store.reader", "geoidspline.fitting"),
    ("geoidspline.store.writer", "geoidspline.fitting.driver"),
    ("geoidspline.store.format", "geoidspline.hierarchy"),
    ("geoidspline._kernels", "geoidspline.bspline.level"),
    ("geoidspline.query", "geoidspline.store"),
    ("geoidspline.query", "geoidspline.fitting.driver"),
])
def test_lower_layers_do_not_import_higher_ones(low, high):
    graph = import_graph()
    offenders = sorted(f"{m} -> {t}" for m, targets in graph.items() if m.startswith(low)
                       for t in targets if t == high or t.startswith(high + "."))
    assert offenders == []


def test_reading_a_store_imports_neither_numba_nor_scipy():
    """What a one-point query needs (opening a store, the numpy evaluator) stays light:
    numba alone costs about a second in a cold process."""
    code = ("import sys, geoidspline, geoidspline.store.reader, geoidspline.query.derived; "
            "print(sorted(m for m in ('numba', 'scipy', 'pyproj', 'xarray', 'dask') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
