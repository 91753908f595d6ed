"""The shape of the ``temoto`` package: no import cycles, no reaching into another module's
privates, every logger named after its module.

The checks read the source (``ast``), so they see the package as a reader does, without
importing anything.

- **Import cycles.** The import graph has an edge from a module to every ``temoto`` module it
  imports, at the top or inside a function (a deferred import is still a dependency: the
  circle ``graph -> legacy -> graph`` was one). ``from a.b import c`` counts as an import of
  ``a.b.c`` when that is a module, else of ``a.b``. Every strongly connected set of two or
  more modules is a cycle. Checked twice: for the imports that run, and with the imports under
  ``if TYPE_CHECKING:`` too (they never run, but a type-only circle is still two modules that
  cannot be read, or moved, one without the other).
- **Boundaries.** A module uses only another module's public names (:func:`leaks`): no
  ``from m import _x``, no ``obj._x`` on anything but ``self``/``cls`` unless this module
  defines an ``_x`` of its own (a class reading its private on another instance of itself),
  and a private module (``a.b._c``) is imported only from inside its package ``a.b`` (that is
  what makes it private: its names are the package's, not the world's). Friends, each with a
  reason, are in :data:`FRIENDS`.
- **Loggers.** Every ``logging.getLogger(...)`` call names ``__name__``, the actions' logger
  (:data:`temoto.core.action.ACTION_LOGGER`, with a suffix), or a documented name of
  :data:`LOGGER_NAMES`: a log line's logger tells where it was written.

There is no cap on a module's length: modules are cut by concept, not by line count (a cap
made modules trimmed to it and concepts cut in two).

The allow-lists (:data:`KNOWN_CYCLES`, :data:`KNOWN_TYPE_CYCLES`, :data:`FRIENDS`,
:data:`KNOWN_LOGGERS`) may hold offenders being fixed elsewhere, each with a reason; an entry
that is no longer true fails too, so the lists only shrink.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import temoto

ROOT = Path(temoto.__file__).parent

#: Generated code (lcm-gen, ``tools/gen_lcm_types.py``): never edited by hand, so not checked.
GENERATED = ("temoto.lcm_types",)

#: Import cycles allowed, each a set of modules with a comment saying why and where it is
#: being fixed. None: keep it so.
KNOWN_CYCLES: dict[frozenset[str], str] = {}

#: Cycles through ``TYPE_CHECKING`` imports allowed, each with why. None: keep it so (the
#: registrar's servers see it as :class:`temoto.core.registrar.RegistrarAPI`, a Protocol in
#: their own module, which is how such a circle is broken).
KNOWN_TYPE_CYCLES: dict[frozenset[str], str] = {}

#: Uses of another module's private names allowed: (module, what :func:`leaks` says) -> why.
FRIENDS: dict[tuple[str, str], str] = {
    ("temoto.testing", "import temoto.managers._procmon"): (
        "ProcessMarker finds the test's leftover processes with the Process Manager's /proc"
        " scanner (process_state, processes_with_environ): one reading of /proc, not two"
    ),
    ("temoto.transport._envelope", "._get_packed_fingerprint"): (
        "lcm-gen's generated types (temoto.lcm_types) give their fingerprint under this name only"
    ),
    ("temoto.cli", "import temoto.core._fast"): (
        "temoto --version names the build (compiled or pure kernels), which only their loader knows"
    ),
}

#: Logger names other than a module's ``__name__``: each documented, and why it is not one.
LOGGER_NAMES: dict[str, str] = {
    "temoto": "the package's root: the recorder records its WARNINGs (docs/recording.md)",
    "temoto.engine.events": "LoggingInstrument's documented logger (temoto.core.instrument)",
    "can": "python-can's own logger, quieted while a CAN scan probes buses (not ours)",
}

#: Loggers named otherwise, allowed: (module, the name) -> why.
KNOWN_LOGGERS: dict[tuple[str, str], str] = {}


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


@functools.cache
def _tree(path: Path) -> ast.Module:
    """A module's syntax tree (each file is read once for every check)."""
    return ast.parse(path.read_text(encoding="utf-8"))


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST, typing: bool = False) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement that can run, at any depth; under ``if TYPE_CHECKING`` too if
    ``typing``."""
    found: list[ast.Import | ast.ImportFrom] = []
    todo: list[ast.AST] = [tree]
    while todo:
        node = todo.pop()
        if not typing and isinstance(node, ast.If) and _type_checking(node.test):
            todo.extend(node.orelse)
            continue
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
            continue
        # An import is a statement: only the statement lists are walked, not the expressions
        # (a tenth of the nodes; the whole walk took over a minute on a loaded 2-core machine).
        for field in _BODIES:
            todo.extend(getattr(node, field, ()))
    return found


#: The fields that hold statements (a module's, a class's or function's body, the branches of
#: if/for/while/try/with/match, an except clause, a match case).
_BODIES = ("body", "orelse", "finalbody", "handlers", "cases")


def import_graph(known: dict[str, Path], typing: bool = False) -> dict[str, set[str]]:
    """For each module, the package's modules it imports when it runs (and for type checking
    only, if ``typing``)."""
    graph: dict[str, set[str]] = {}
    for name, path in known.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for stmt in _imports(_tree(path), typing):
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


def test_no_import_cycles_even_through_type_checking_imports() -> None:
    found = cycles(import_graph(modules(), typing=True))
    new = [_show(c) for c in found if c not in KNOWN_TYPE_CYCLES and c not in KNOWN_CYCLES]
    assert not new, (
        "import cycles through TYPE_CHECKING imports (the type a module needs of another is"
        " a Protocol of its own, or the two are one concept):\n" + "\n".join(new)
    )
    gone = [_show(c) for c in KNOWN_TYPE_CYCLES if c not in found]
    assert not gone, "cycles fixed or changed: update KNOWN_TYPE_CYCLES\n" + "\n".join(gone)


# ---------------------------------------------------------------------- private names

#: Attribute names with a leading underscore that are public API by convention (namedtuple's
#: methods, ``os._exit``, ``sys._getframe``).
PUBLIC_UNDERSCORE = frozenset(
    {"_asdict", "_replace", "_fields", "_field_defaults", "_make", "_exit", "_getframe"}
)

_SELF = ("self", "cls")


def _private(name: str) -> bool:
    """``_x`` and ``__x`` are private; ``__x__`` (dunder), ``_x_`` (enum's sunder) and ``_`` not."""
    return (
        name.startswith("_")
        and not name.endswith("_")
        and name != "_"
        and name not in PUBLIC_UNDERSCORE
    )


def _owner(target: str) -> str | None:
    """The package a private module belongs to (``a.b`` for ``a.b._c.d``), or None if public."""
    parts = target.split(".")
    for i, part in enumerate(parts):
        if _private(part):
            return ".".join(parts[:i])
    return None


def _defines(tree: ast.AST) -> set[str]:
    """The private names a module defines: functions, classes, assignments at module or class
    level, ``__slots__`` entries, and attributes it stores on ``self``/``cls``."""
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            found.add(node.name)
            if isinstance(node, ast.ClassDef):
                for item in node.body:
                    targets: list[ast.expr] = []
                    if isinstance(item, ast.Assign):
                        targets = item.targets
                    elif isinstance(item, ast.AnnAssign):
                        targets = [item.target]
                    for target in targets:
                        if isinstance(target, ast.Name):
                            found.add(target.id)
                            if target.id == "__slots__" and isinstance(item.value, ast.Tuple):
                                found.update(
                                    e.value
                                    for e in item.value.elts
                                    if isinstance(e, ast.Constant) and isinstance(e.value, str)
                                )
        elif (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id in _SELF
        ):
            found.add(node.attr)
    module = tree.body if isinstance(tree, ast.Module) else []
    for stmt in module:
        for target in getattr(stmt, "targets", [getattr(stmt, "target", None)]):
            if isinstance(target, ast.Name):
                found.add(target.id)
    return found


def _is_self(node: ast.expr) -> bool:
    """``self``, ``cls``, ``super()``, ``type(self)``: the object's own class."""
    if isinstance(node, ast.Name):
        return node.id in _SELF
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and (
            node.func.id == "super"
            or (node.func.id == "type" and len(node.args) == 1 and _is_self(node.args[0]))
        )
    )


def leaks(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """Where a module reaches into another's privates, each as a short line.

    - ``from m import _x`` of a name (not a module) of another module ``m``;
    - an import of a private module (``a.b._c``) from outside its package (``a.b``);
    - ``obj._x`` (or ``getattr(obj, "_x")``) where ``obj`` is not ``self``/``cls`` and this
      module defines no ``_x`` of its own (one class reading its own private on another
      instance of itself is fine).
    """
    tree = _tree(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    own = _defines(tree)
    found: set[str] = set()

    def private_module(target: str) -> None:
        while target and target not in known:
            target = target.rpartition(".")[0]
        owner = _owner(target) if target else None
        if owner is not None and name != owner and not name.startswith(owner + "."):
            found.add(f"import {target}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                private_module(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            if source.split(".")[0] != name.split(".")[0]:
                continue  # another package's: not ours to check
            for alias in node.names:
                full = f"{source}.{alias.name}"
                if full in known:
                    private_module(full)
                elif _private(alias.name):
                    found.add(f"from {source} import {alias.name}")
                else:
                    private_module(source)
        elif isinstance(node, ast.Attribute):
            if _private(node.attr) and node.attr not in own and not _is_self(node.value):
                found.add(f".{node.attr}")
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in ("getattr", "setattr", "hasattr", "delattr")
            and len(node.args) >= 2
            and isinstance(node.args[1], ast.Constant)
            and isinstance(node.args[1].value, str)
            and _private(node.args[1].value)
            and node.args[1].value not in own
            and not _is_self(node.args[0])
        ):
            found.add(f".{node.args[1].value}")
    return found


def all_leaks(known: dict[str, Path]) -> set[tuple[str, str]]:
    """Every ``(module, leak)`` of the package."""
    return {(name, leak) for name, path in known.items() for leak in leaks(name, path, known)}


def test_no_module_uses_another_modules_privates() -> None:
    found = all_leaks(modules())
    new = sorted(f"{m}: {what}" for m, what in found - FRIENDS.keys())
    assert not new, (
        "private names used from another module (make the name public, with a docstring, or"
        " give the module what it needs through a public call):\n" + "\n".join(new)
    )
    gone = sorted(f"{m}: {what}" for m, what in FRIENDS.keys() - found)
    assert not gone, "no longer used: take them out of FRIENDS\n" + "\n".join(gone)


# ---------------------------------------------------------------------- loggers


def _logger_name_ok(arg: ast.expr) -> bool:
    if isinstance(arg, ast.IfExp):
        return _logger_name_ok(arg.body) and _logger_name_ok(arg.orelse)
    if isinstance(arg, ast.Name):
        return arg.id in ("__name__", "ACTION_LOGGER")
    if isinstance(arg, ast.Attribute):
        return arg.attr == "ACTION_LOGGER"
    if isinstance(arg, ast.Constant):
        return arg.value in LOGGER_NAMES
    if isinstance(arg, ast.JoinedStr) and len(arg.values) >= 2:  # f"{ACTION_LOGGER}.{node}"
        first, second = arg.values[0], arg.values[1]
        return (
            isinstance(first, ast.FormattedValue)
            and _logger_name_ok(first.value)
            and isinstance(first.value, ast.Name | ast.Attribute)
            and isinstance(second, ast.Constant)
            and str(second.value).startswith(".")
        )
    return False


def logger_names(path: Path) -> set[str]:
    """The names given to ``getLogger`` in a module that are not ``__name__``, the actions'
    logger or one of :data:`LOGGER_NAMES` (as written; ``getLogger()``, the root, too)."""
    found: set[str] = set()
    for node in ast.walk(_tree(path)):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        if called != "getLogger":
            continue
        if not node.args:
            found.add("")
        elif not _logger_name_ok(node.args[0]):
            arg = node.args[0]
            found.add(arg.value if isinstance(arg, ast.Constant) else ast.unparse(arg))
    return found


def test_every_logger_is_named_after_its_module_or_documented() -> None:
    found = {(n, logger) for n, p in modules().items() for logger in logger_names(p)}
    new = sorted(f"{m}: getLogger({logger!r})" for m, logger in found - KNOWN_LOGGERS.keys())
    assert not new, (
        "loggers named otherwise (logging.getLogger(__name__), or a name documented in"
        " LOGGER_NAMES):\n" + "\n".join(new)
    )
    gone = sorted(f"{m}: {logger}" for m, logger in KNOWN_LOGGERS.keys() - found)
    assert not gone, "fixed: take them out of KNOWN_LOGGERS\n" + "\n".join(gone)


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


def test_private_names_of_another_module_are_found(tmp_path: Path) -> None:
    root = _package(
        tmp_path,
        {
            "__init__.py": "",
            "a.py": (
                "_HIDDEN = 1\n"
                "class A:\n"
                "    __slots__ = ('_kept',)\n"
                "    def __init__(self):\n"
                "        self._mine = 1\n"
                "    def same(self, other: 'A') -> int:\n"
                "        return other._mine + other._kept + super()._base\n"
            ),
            "b.py": (
                "from pkg.a import _HIDDEN, A\n"
                "from pkg.sub import _inner\n"
                "from pkg.sub._inner import thing\n"
                "import pkg.a as a\n"
                "def f(x: A):\n"
                "    return x._mine, a._HIDDEN, getattr(x, '_kept'), x.__dict__, x._asdict()\n"
            ),
            "sub/__init__.py": "from pkg.sub._inner import thing\n",
            "sub/_inner.py": "thing = 1\n",
            "sub/user.py": "from pkg.sub import _inner\nfrom ._inner import thing\n",
        },
    )
    known = modules(root)
    assert leaks("pkg.a", known["pkg.a"], known) == set()
    assert leaks("pkg.b", known["pkg.b"], known) == {
        "from pkg.a import _HIDDEN",
        "import pkg.sub._inner",
        "._mine",
        "._HIDDEN",
        "._kept",
    }
    assert leaks("pkg.sub", known["pkg.sub"], known) == set()  # its own private module
    assert leaks("pkg.sub.user", known["pkg.sub.user"], known) == set()


def test_loggers_not_named_after_their_module_are_found(tmp_path: Path) -> None:
    root = _package(
        tmp_path,
        {
            "__init__.py": "",
            "ok.py": (
                "import logging\n"
                "from logging import getLogger\n"
                "from pkg.names import ACTION_LOGGER\n"
                "a = logging.getLogger(__name__)\n"
                "b = getLogger(ACTION_LOGGER)\n"
                "c = logging.getLogger(f'{ACTION_LOGGER}.{a}' if a else ACTION_LOGGER)\n"
                "d = logging.getLogger('temoto.engine.events')\n"
            ),
            "bad.py": (
                "import logging\n"
                "a = logging.getLogger('pkg.other')\n"
                "b = logging.getLogger()\n"
                "c = logging.getLogger(f'{ACTION_LOGGER}{a}')\n"
                "d = logging.getLogger('x' if a else __name__)\n"
            ),
        },
    )
    known = modules(root)
    assert logger_names(known["pkg.ok"]) == set()
    assert logger_names(known["pkg.bad"]) == {
        "pkg.other",
        "",
        "f'{ACTION_LOGGER}{a}'",
        "'x' if a else __name__",
    }
