"""No import cycles inside ``guidedmatch``: every module's imports, read with ``ast``, form a graph without cycles.

Every ``import`` / ``from ... import`` statement of a module counts, wherever it is (module level, inside a
function, under ``if TYPE_CHECKING:``): a lazy import inside a function still makes the two modules depend on each
other, and a cycle hidden that way is one an edit away from breaking at import time.

Edges (``A -> B``: module ``A`` imports ``B``), for a statement in module ``A``:

* ``import p.q.r`` / ``from p.q import r``: ``A -> p.q`` (``p.q.r`` too when ``r`` is a module), and, when ``p.q``
  lies in a package that does not contain ``A``, ``A -> `` each such enclosing package (its ``__init__`` runs first).
  The packages that contain ``A`` are not added implicitly: their ``__init__`` has already started when ``A`` is
  imported, so importing a sibling does not run them again -- that is how a package's ``__init__`` re-exports its
  own submodules (``pkg -> pkg.sub``) without a cycle.
* ``from . import x`` in ``p.a``: ``A -> p.x`` when ``x`` is a module; ``A -> p`` (the package's ``__init__``)
  when ``x`` is a name defined there -- so a submodule importing a name from its own package's ``__init__``, which
  imports that submodule, is reported as the cycle it is.

Not seen: imports made by ``importlib.import_module`` (the top-level package's lazy export table: a name is
imported on first attribute access, never while ``guidedmatch`` itself is being imported).
"""
from __future__ import annotations

import ast
import os
import textwrap
from pathlib import Path

#: cycles known to be removed by separate work, each the exact set of its modules; delete the entry when it is gone
#: (a listed cycle that no longer exists fails the test too, so the entry cannot outlive its cycle)
EXPECTED_TO_BE_FIXED: dict[str, frozenset] = {
}


# ============================================================================================ the checker
def package_modules(root: Path, package: str) -> dict[str, Path]:
    """``{dotted module name: file}`` for every ``.py`` file of the package at ``root`` (a package's ``__init__.py``
    is the package's own name)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).with_suffix("")
        parts = [package, *rel.parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(not (root.joinpath(*parts[1:k]) / "__init__.py").is_file() for k in range(1, len(parts))):
            continue  # not inside a package (no __init__.py on the way): not importable as package.x
        out[".".join(parts)] = path
    return out


def _enclosing_packages(module: str, is_package: bool) -> list[str]:
    """``module`` itself when it is a package, and every package above it."""
    parts = module.split(".")
    own = len(parts) if is_package else len(parts) - 1
    return [".".join(parts[:k]) for k in range(1, own + 1)]


def import_edges(modules: dict[str, Path], package: str) -> dict[str, set[str]]:
    """``{module: {modules of the package it imports}}`` by the rules of the module doc."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        own_packages = set(_enclosing_packages(mod, is_pkg))
        base_pkg = mod if is_pkg else mod.rpartition(".")[0]

        def add(target: str) -> None:
            """``mod -> target`` and the packages containing ``target`` that do not contain ``mod``."""
            if target not in modules:
                return
            for parent in _enclosing_packages(target, False):
                if parent not in own_packages and parent in modules:
                    graph[mod].add(parent)
            graph[mod].add(target)

        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == package or alias.name.startswith(package + "."):
                        add(alias.name)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = base_pkg.split(".")
                    if node.level - 1 >= len(parts):
                        raise ValueError(f"{path}: relative import beyond the top-level package")
                    base = ".".join(parts[:len(parts) - (node.level - 1)])
                    if node.module:
                        base = f"{base}.{node.module}"
                elif node.module == package or (node.module or "").startswith(package + "."):
                    base = node.module
                else:
                    continue
                names = [alias.name for alias in node.names]
                submodules = [f"{base}.{n}" for n in names if f"{base}.{n}" in modules]
                for sub in submodules:
                    add(sub)
                if len(submodules) < len(names) or base not in own_packages:
                    # a name defined in base's own code (or base is not already being imported): base runs
                    add(base)
    return graph


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph`` (iterative), each sorted, in sorted order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    comps: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    comps.append(sorted(comp))
    return sorted(comps)


def import_cycles(root: Path, package: str) -> list[list[str]]:
    """The import cycles of the package at ``root``: every strongly connected component of more than one module,
    and every module importing itself."""
    graph = import_edges(package_modules(root, package), package)
    return [c for c in strongly_connected(graph) if len(c) > 1 or c[0] in graph[c[0]]]


def describe(cycle: list[str], graph: dict[str, set[str]]) -> str:
    """A cycle as its modules and the edges between them."""
    inside = set(cycle)
    edges = [f"{a} -> {b}" for a in cycle for b in sorted(graph[a]) if b in inside]
    return "{" + ", ".join(cycle) + "}: " + "; ".join(edges)


# ============================================================================================ the tests
def _write_package(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text), encoding="utf-8")
    return tmp_path / "pkg"


def test_checker_finds_a_cycle_hidden_in_functions_and_type_checking(tmp_path):
    root = _write_package(tmp_path, {
        "pkg/__init__.py": "from .a import A\n",                     # a package re-exporting its submodule: fine
        "pkg/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .b import B\nA = 1\n",
        "pkg/b.py": "def f():\n    from pkg.sub import c\n    return c\nB = 2\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/c.py": "def g():\n    from .. import a\n",         # b -> sub.c -> a -> b
        "pkg/d.py": "import os\nfrom . import a\n",                   # not on a cycle
        "pkg/notes/x.py": "from pkg import d\n",                      # no __init__.py: not a module of pkg
    })
    modules = package_modules(root, "pkg")
    assert set(modules) == {"pkg", "pkg.a", "pkg.b", "pkg.sub", "pkg.sub.c", "pkg.d"}
    graph = import_edges(modules, "pkg")
    assert graph["pkg"] == {"pkg.a"}
    assert graph["pkg.b"] == {"pkg.sub", "pkg.sub.c"}   # importing pkg.sub.c runs pkg.sub's __init__ first
    assert graph["pkg.sub.c"] == {"pkg.a"}              # its own packages' __init__ already run
    assert import_cycles(root, "pkg") == [["pkg.a", "pkg.b", "pkg.sub.c"]]
    assert "pkg.a -> pkg.b" in describe(["pkg.a", "pkg.b", "pkg.sub.c"], graph)


def test_checker_counts_a_name_from_the_own_package_init_and_a_self_import(tmp_path):
    root = _write_package(tmp_path, {
        "pkg/__init__.py": "from .a import helper\nVERSION = '1'\n",
        "pkg/a.py": "def helper():\n    from pkg import VERSION\n    return VERSION\n",  # upward: a cycle
        "pkg/b.py": "import pkg.b\n",                                                     # itself
        "pkg/c.py": "from . import a\n",                                                  # a module: no cycle
    })
    assert import_cycles(root, "pkg") == [["pkg", "pkg.a"], ["pkg.b"]]


def test_checker_on_an_acyclic_package(tmp_path):
    root = _write_package(tmp_path, {
        "pkg/__init__.py": "from . import low\nfrom .mid import M\n",
        "pkg/low.py": "X = 1\n",
        "pkg/mid.py": "from .low import X\nM = X\n",
        "pkg/top/__init__.py": "from .run import R\n",
        "pkg/top/run.py": "from ..mid import M\nfrom . import helpers\nR = M\n",
        "pkg/top/helpers.py": "import pkg.low\n",
    })
    assert import_cycles(root, "pkg") == []


def test_guidedmatch_has_no_import_cycles():
    import guidedmatch

    root = Path(guidedmatch.__file__).parent
    graph = import_edges(package_modules(root, "guidedmatch"), "guidedmatch")
    cycles = import_cycles(root, "guidedmatch")
    expected = {frozenset(c) for c in EXPECTED_TO_BE_FIXED.values()}
    unexpected = [describe(c, graph) for c in cycles if frozenset(c) not in expected]
    assert not unexpected, "import cycles inside guidedmatch:\n" + "\n".join(unexpected)
    gone = [k for k, v in EXPECTED_TO_BE_FIXED.items() if list(sorted(v)) not in cycles]
    assert not gone, f"these cycles are gone: delete their EXPECTED_TO_BE_FIXED entries: {gone}"


def test_every_module_is_seen():
    """The walk covers the installed package (no module silently skipped by the package rule)."""
    import guidedmatch

    root = Path(guidedmatch.__file__).parent
    files = {p for p in root.rglob("*.py") if "__pycache__" not in p.parts}
    seen = set(package_modules(root, "guidedmatch").values())
    assert files == seen, sorted(os.fspath(p) for p in files - seen)


if __name__ == "__main__":  # print the cycles: python tests/test_imports.py
    import guidedmatch

    _root = Path(guidedmatch.__file__).parent
    _graph = import_edges(package_modules(_root, "guidedmatch"), "guidedmatch")
    for _c in import_cycles(_root, "guidedmatch"):
        print(describe(_c, _graph))
