"""The package's structure: no import cycles, and every import points down the layers.

Imports are read from the source (every ``import`` and ``from ... import``, at module
level or inside functions, TYPE_CHECKING included), so an arrow hidden behind a lazy
import is found too. Importing ``geoidspline.b.c`` also runs ``geoidspline/b/__init__``:
that counts as an edge (the root package's own imports are checked on their own).

The layers, bottom to top (docs/ARCHITECTURE.md draws them):

0. ``_kernels``: the numeric bottom, imports nothing of the package outside itself;
1. base: ``errors``, ``options`` (the numeric rules), ``_version``, ``_files``, ``_memory``, ``geodesy``,
   ``grids`` (data);
2. ``sphere`` (geometry); 3. ``bspline`` (basis, levels, brick index); 4. ``hierarchy``;
5. side by side, importing none of each other: ``sources``, ``fitting``, ``store``, ``query``;
6. the front door: ``api`` (and the root package), composing the four;
7. ``cli``: parsing and printing, importing only the front door and the error types.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "geoidspline"
# cli/ and grids/ install inside the package (pyproject's package-dir)
FOLDERS = {"geoidspline": PACKAGE, "geoidspline.cli": REPO / "cli", "geoidspline.grids": REPO / "grids"}

BASE = ("geoidspline.errors", "geoidspline.options", "geoidspline._version", "geoidspline._files",
        "geoidspline._memory", "geoidspline.geodesy", "geoidspline.grids")
SIDE_BY_SIDE = ("geoidspline.sources", "geoidspline.fitting", "geoidspline.store", "geoidspline.query")
LAYERS = [  # (rank, prefixes)
    (0, ("geoidspline._kernels",)),
    (1, BASE),
    (2, ("geoidspline.sphere",)),
    (3, ("geoidspline.bspline",)),
    (4, ("geoidspline.hierarchy",)),
    (5, SIDE_BY_SIDE),
    (6, ("geoidspline.api",)),
    (7, ("geoidspline.cli", "geoidspline.__main__")),
]
# what the command line may import besides itself
CLI_MAY_IMPORT = ("geoidspline.api", "geoidspline.errors")


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def layer_of(module: str) -> tuple[int, str]:
    """(rank, group): imports go to a lower rank or stay in the same group."""
    if module == "geoidspline":
        return 6, "6"  # the root package re-exports the front door
    for rank, prefixes in LAYERS:
        for prefix in prefixes:
            if _within(module, prefix):
                # side-by-side packages are groups of their own; other layers are one group
                return rank, prefix if rank == 5 else str(rank)
    raise AssertionError(f"{module} belongs to no layer: add it to LAYERS")


def allowed(source: str, target: str) -> bool:
    (rank, group), (target_rank, target_group) = layer_of(source), layer_of(target)
    if rank == 7:
        return target_rank == 7 or any(_within(target, p) for p in CLI_MAY_IMPORT)
    if rank == 0:
        return target_rank == 0
    return target_rank < rank or group == target_group


def _module_name(path: Path) -> str:
    for package, folder in FOLDERS.items():
        if package != "geoidspline" and path.is_relative_to(folder):
            rel = path.relative_to(folder).with_suffix("")
            parts = package.split(".") + list(rel.parts)
            break
    else:
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for folder in FOLDERS.values() for p in folder.rglob("*.py")}


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


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that runs against the layers, as "importer -> imported"."""
    return sorted(f"{m} -> {t}" for m, targets in graph.items() for t in targets if not allowed(m, t))


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


def test_every_module_has_a_layer():
    for module in import_graph():
        layer_of(module)


def test_no_import_runs_against_the_layers():
    found = violations(import_graph())
    assert found == [], f"{len(found)} imports against the layers:\n" + "\n".join(found)


@pytest.mark.parametrize("source, target, ok", [
    ("geoidspline.store.reader", "geoidspline.query.derived", False),  # side by side
    ("geoidspline.hierarchy.ambient", "geoidspline.bspline.index", True),  # down
    ("geoidspline.bspline.index", "geoidspline.hierarchy.ambient", False),  # up
    ("geoidspline._kernels.query", "geoidspline.errors", False),  # kernels are the bottom
    ("geoidspline.sphere.coordinates", "geoidspline._kernels.query", True),
    ("geoidspline.cli.fit", "geoidspline.api", True),
    ("geoidspline.cli.fit", "geoidspline.fitting.parameters", False),  # the front door only
    ("geoidspline.api", "geoidspline.fitting.driver", True),
    ("geoidspline.fitting.driver", "geoidspline.api", False),
])
def test_the_layer_rule(source, target, ok):
    assert allowed(source, target) is ok


def test_reading_a_store_imports_neither_the_compiled_kernels_nor_scipy():
    """What a one-point query needs (opening a store, the numpy evaluator, the front door
    and geoid-query's module) stays light: scipy alone costs a few hundred ms in a cold
    process, and the kernels' library (ctypes) is only for large batches and fits."""
    code = ("import sys, geoidspline, geoidspline.store.reader, geoidspline.query.derived, geoidspline.api, "
            "geoidspline.query.batch, geoidspline.cli.query; "
            "print(sorted(m for m in ('geoidspline._kernels._clib', 'scipy', 'pyproj', 'xarray', 'dask') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
