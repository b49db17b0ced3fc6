"""The import graph of ``src/selfcal``: no circle inside a package, the toa layers import downward.

Every ``import`` / ``from ... import`` statement of every module is read with :mod:`ast`, at
module level and inside functions (a function-level import is still a dependency: it only
defers the circle to the first call). Imports under ``if TYPE_CHECKING:`` never run and are
not counted. ``from pkg import name`` counts as an import of the module ``pkg.name`` when
that module exists, else of ``pkg``. The rules are those of docs/design.md (Layout).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "selfcal"

#: the children of selfcal.toa, bottom to top (docs/design.md, "The toa layers"); a child
#: imports only children of lower layers
TOA_LAYERS: tuple[tuple[str, ...], ...] = (
    ("options",), ("engine",), ("moves",), ("init",), ("verdict",), ("result",), ("search",), ("block_start",),
    ("fit_result",), ("fit",), ("solve",), ("plan",), ("frame",), ("recipes",), ("sparse",), ("graph",),
)


def _module_name(path: Path, src: Path = SRC) -> str:
    parts = list(path.relative_to(src.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of ``tree`` outside ``if TYPE_CHECKING:`` blocks."""
    out: list[ast.Import | ast.ImportFrom] = []
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return out


@functools.cache
def import_graph(src: Path = SRC) -> tuple[set[str], set[str], set[tuple[str, str]]]:
    """(modules, packages, edges importer -> imported) of the selfcal modules under ``src``."""
    files = {_module_name(p, src): p for p in src.rglob("*.py")}
    packages = {m for m, p in files.items() if p.name == "__init__.py"}
    edges: set[tuple[str, str]] = set()
    for mod, path in files.items():
        here = mod if mod in packages else mod.rsplit(".", 1)[0]
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                if node.level:
                    base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                    pkg = ".".join(base + ([node.module] if node.module else []))
                else:
                    pkg = node.module or ""
                targets = [f"{pkg}.{a.name}" if f"{pkg}.{a.name}" in files else pkg for a in node.names]
            for t in targets:
                while t and t not in files:  # a name inside a module: the module
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    edges.add((mod, t))
    return set(files), packages, edges


def _child(pkg: str, mod: str) -> str | None:
    """The direct child of ``pkg`` that ``mod`` lies in (a module or a subpackage), or None."""
    if not mod.startswith(pkg + "."):
        return None
    return mod[len(pkg) + 1:].split(".")[0]


def _cycles(nodes: set[str], edges: set[tuple[str, str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan, iterative)."""
    succ: dict[str, list[str]] = {n: [] for n in nodes}
    for a, b in edges:
        succ[a].append(b)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for root in sorted(nodes):
        if root in index:
            continue
        work = [(root, iter(sorted(succ[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(succ[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def package_graph(pkg: str, edges: set[tuple[str, str]]) -> dict[tuple[str, str], list[tuple[str, str]]]:
    """Edges between the direct children of ``pkg``, each with the module imports behind it."""
    out: dict[tuple[str, str], list[tuple[str, str]]] = {}
    for a, b in edges:
        ca, cb = _child(pkg, a), _child(pkg, b)
        if ca and cb and ca != cb:
            out.setdefault((ca, cb), []).append((a, b))
    return out


def test_the_scan_sees_the_imports() -> None:
    """The scan itself works: known imports of each kind are found (module level, function
    level, relative, through ``from pkg import module``)."""
    mods, packages, edges = import_graph()
    assert len(mods) > 150 and "selfcal.toa" in packages and "selfcal.toa.engine" in packages
    assert ("selfcal.toa.solve", "selfcal.toa.fit") in edges                      # module level
    assert ("selfcal.toa.engine.constrained", "selfcal.toa.engine.covariance") in edges  # inside a function
    assert ("selfcal.tdoa.deletion", "selfcal.tdoa.solve") in edges               # inside a function
    # a circle is found when there is one
    assert _cycles({"a", "b", "c", "d"}, {("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")}) == [["a", "b", "c"]]
    assert _cycles({"a", "b"}, {("a", "b")}) == []


def test_no_import_circle_between_modules() -> None:
    mods, _, edges = import_graph()
    assert _cycles(mods, edges) == []


@pytest.mark.parametrize("pkg", sorted(import_graph()[1]))
def test_no_import_circle_inside_a_package(pkg: str) -> None:
    """In each package, the children (modules, and subpackages counted as one node) import
    one another without a circle."""
    g = package_graph(pkg, import_graph()[2])
    nodes = {n for e in g for n in e}
    circles = _cycles(nodes, set(g))
    detail = {c: sorted(v for (a, b), lst in g.items() if a in c and b in c for v in lst) for c in map(tuple, circles)}
    assert not circles, f"import circles inside {pkg}: {detail}"


def test_toa_layers_import_downward() -> None:
    """Each child of selfcal.toa imports only children of lower layers (docs/design.md)."""
    mods, _, edges = import_graph()
    rank = {name: k for k, layer in enumerate(TOA_LAYERS) for name in layer}
    children = {_child("selfcal.toa", m) for m in mods} - {None}
    assert children <= set(rank), f"place these in TOA_LAYERS and docs/design.md: {sorted(children - set(rank))}"
    upward = sorted(v for (a, b), lst in package_graph("selfcal.toa", edges).items() if rank[b] >= rank[a]
                    for v in lst)
    assert not upward, f"upward imports between the toa layers: {upward}"
