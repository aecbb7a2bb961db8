"""The repository's structure: one home per concept, no import cycle, the import directions.

Read from the source with :mod:`ast` (nothing is imported), so a violation names the file and
line. Every import counts: at module level, under ``if TYPE_CHECKING:`` (a type-level cycle is
still a cycle) and inside functions (a lazy import hides a cycle, it does not remove it). The one
exception is the root package ``pipeline/__init__.py``: it imports nothing at run time (its public
names are resolved on first use by ``__getattr__``) and its ``TYPE_CHECKING`` block only tells
type checkers what those names are, so its own imports are not edges; a submodule importing
``pipeline`` (for ``__version__``) is.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

REPO = Path(__file__).resolve().parent.parent


def _modules(folder: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``folder`` (a package or not)."""
    out = {}
    for p in sorted(folder.rglob("*.py")):
        parts = list(p.relative_to(folder.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(path: Path, module: str) -> list[tuple[str, int]]:
    """(imported name, line) of every import statement in a file, relative ones resolved;
    ``from a import b`` gives ``a.b`` (a submodule or a name in ``a``)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            out += [(f"{base}.{a.name}", node.lineno) for a in node.names]
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest known module a dotted name starts with (None: outside ``modules``)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(folder: Path) -> dict[str, dict[str, int]]:
    """module -> {module it imports: first line}, within the package ``folder``."""
    modules = _modules(folder)
    graph: dict[str, dict[str, int]] = {m: {} for m in modules}
    for m, p in modules.items():
        if m == folder.name:  # the root facade (see the module docstring)
            continue
        for name, line in _imports(p, m):
            target = _resolve(name, modules)
            if target is not None and target != m:
                graph[m].setdefault(target, line)
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (each an import cycle)."""
    names = sorted(graph)
    index = {n: i for i, n in enumerate(names)}
    rows = [index[a] for a, bs in graph.items() for _ in bs]
    cols = [index[b] for bs in graph.values() for b in bs]
    adjacency = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    n, label = connected_components(adjacency, directed=True, connection="strong")
    groups = [[names[i] for i in np.flatnonzero(label == k)] for k in range(n)]
    return [g for g in groups if len(g) > 1]


def test_the_cycle_finder_finds_a_cycle_through_a_lazy_import(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "io").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from pkg import a\n")  # the root facade: not an edge
    (pkg / "io" / "__init__.py").write_text("")
    (pkg / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.io.b import X\n"
    )
    (pkg / "io" / "b.py").write_text("from .c import f\n")
    (pkg / "io" / "c.py").write_text("def f():\n    from pkg import a\n")
    (pkg / "d.py").write_text("import pkg.a\n")
    assert cycles(import_graph(pkg)) == [["pkg.a", "pkg.io.b", "pkg.io.c"]]


def test_no_import_cycle_among_pipeline_modules():
    graph = import_graph(REPO / "pipeline")
    found = cycles(graph)
    detail = [f"{a}:{n} -> {b}" for g in found for a in g for b, n in graph[a].items() if b in g]
    assert not found, "import cycles:\n" + "\n".join(detail)


def test_series_types_live_in_a_leaf_module():
    """TopicSeries, Gap and Loss: defined once, in a module importing nothing of pipeline's
    at run time, so the scanner, the reader, the mapping importer and Flight all can name them."""
    from pipeline.io import series

    defined = {}
    for p in (REPO / "pipeline").rglob("*.py"):
        for node in ast.parse(p.read_text()).body:
            if isinstance(node, ast.ClassDef) and node.name in ("TopicSeries", "Gap", "Loss"):
                defined.setdefault(node.name, []).append(p.relative_to(REPO).as_posix())
    assert defined == {k: ["pipeline/io/series.py"] for k in ("TopicSeries", "Gap", "Loss")}
    runtime = [
        n
        for n in ast.parse(Path(series.__file__).read_text()).body
        if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("pipeline")
    ]
    assert runtime == []
