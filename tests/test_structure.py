"""The shape of the ``temoto`` package: no import cycles.

The check reads the source (``ast``), so it sees the package as a reader does, without
importing anything.

- **Import cycles.** The import graph has an edge from a module to every ``temoto`` module it
  imports when it runs, at the top or inside a function (a deferred import is still a
  dependency: the circle ``graph -> legacy -> graph`` was one). Imports under
  ``if TYPE_CHECKING:`` are left out: they never run. ``from a.b import c`` counts as an
  import of ``a.b.c`` when that is a module, else of ``a.b``. Every strongly connected set of
  two or more modules is a cycle.

There is no cap on a module's length: modules are cut by concept, not by line count (a cap
made modules trimmed to it and concepts cut in two).

:data:`KNOWN_CYCLES` may hold offenders being fixed elsewhere (empty since issue 19); an entry
that is no longer true fails too, so the list only shrinks.
"""

from __future__ import annotations

import ast
from pathlib import Path

import temoto

ROOT = Path(temoto.__file__).parent

#: Generated code (lcm-gen, ``tools/gen_lcm_types.py``): never edited by hand, so not checked.
GENERATED = ("temoto.lcm_types",)

#: Import cycles allowed, each a set of modules with a comment saying why and where it is
#: being fixed. None: keep it so.
KNOWN_CYCLES: dict[frozenset[str], str] = {}


def module_name(path: Path, root: Path = ROOT) -> str:
    """The dotted name of a module file under the package root."""
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the package (generated ones left out), by dotted name."""
    found = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    return {n: p for n, p in found.items() if not n.startswith(GENERATED)}


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _runtime_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement that can run, at any depth, except under ``if TYPE_CHECKING``."""
    found: list[ast.Import | ast.ImportFrom] = []
    todo: list[ast.AST] = [tree]
    while todo:
        node = todo.pop()
        if isinstance(node, ast.If) and _type_checking(node.test):
            todo.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        todo.extend(ast.iter_child_nodes(node))
    return found


def import_graph(known: dict[str, Path]) -> dict[str, set[str]]:
    """For each module, the package's modules it imports when it runs."""
    graph: dict[str, set[str]] = {}
    for name, path in known.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for stmt in _runtime_imports(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(stmt, ast.Import):
                candidates = [alias.name for alias in stmt.names]
            else:
                if stmt.level:
                    base = package.split(".")[: len(package.split(".")) - stmt.level + 1]
                    source = ".".join([*base, *([stmt.module] if stmt.module else [])])
                else:
                    source = stmt.module or ""
                candidates = [
                    f"{source}.{a.name}" if f"{source}.{a.name}" in known else source
                    for a in stmt.names
                ]
            for target in candidates:
                while target and target not in known:  # `import a.b.c` of a name, or a package
                    target = target.rpartition(".")[0]
                if target and target != name:
                    targets.add(target)
        graph[name] = targets
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected sets of two or more modules (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                members = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    members.add(member)
                    if member == node:
                        break
                if len(members) > 1:
                    found.append(frozenset(members))
    return found


def _show(cycle: frozenset[str]) -> str:
    return " <-> ".join(sorted(cycle))


def test_no_import_cycles() -> None:
    found = cycles(import_graph(modules()))
    new = [_show(c) for c in found if c not in KNOWN_CYCLES]
    assert not new, "import cycles (break them: a module per concept, no back edges):\n" + (
        "\n".join(new)
    )
    gone = [_show(c) for c in KNOWN_CYCLES if c not in found]
    assert not gone, "cycles fixed or changed: update KNOWN_CYCLES\n" + "\n".join(gone)


# ---------------------------------------------------------------------- the checks themselves


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


def test_a_deferred_import_closes_a_cycle_a_type_checking_one_does_not(tmp_path: Path) -> None:
    root = _package(
        tmp_path,
        {
            "__init__.py": "",
            "a.py": "from pkg.b import x\n",
            "b.py": "def f():\n    from pkg import a\n",
            "c.py": "import typing\nif typing.TYPE_CHECKING:\n    from pkg.a import y\n",
            "d.py": "from pkg.c import z\n",
        },
    )
    graph = import_graph(modules(root))
    assert graph["pkg.b"] == {"pkg.a"}  # `from pkg import a` is the module pkg.a
    assert graph["pkg.c"] == set()
    assert cycles(graph) == [frozenset({"pkg.a", "pkg.b"})]


def test_relative_imports_resolve(tmp_path: Path) -> None:
    root = _package(
        tmp_path,
        {
            "__init__.py": "from .sub import thing\n",
            "sub/__init__.py": "from ..top import value\nfrom . import leaf\n",
            "sub/leaf.py": "from .. import top\n",
            "top.py": "import pkg.sub.leaf\n",
        },
    )
    graph = import_graph(modules(root))
    assert graph["pkg"] == {"pkg.sub"}
    assert graph["pkg.sub"] == {"pkg.top", "pkg.sub.leaf"}
    assert graph["pkg.sub.leaf"] == {"pkg.top"}
    assert cycles(graph) == [frozenset({"pkg.sub.leaf", "pkg.top"})]
