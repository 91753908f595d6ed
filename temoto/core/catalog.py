"""Where actions and graphs are found: the action catalog and the graph index.

Descriptions are the index; code is imported lazily. :class:`ActionCatalog` reads
``*umrf.json`` files (directories scanned to depth 2, like upstream, plus packages named by the
``temoto.action_packages`` entry-point group) **without importing action code**. The class is
imported when a graph that uses the action starts; a module that fails to import fails only
those graphs, with a :class:`~temoto.errors.PluginLoadError` that chains the cause.

:class:`GraphIndex` reads ``*graph.json`` files the same way. Files that fail to parse are
skipped, logged, and listed in ``problems``. Refreshing is explicit (:meth:`refresh`): there is
no polling thread.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import logging
import sys
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from temoto.core.action import Action
from temoto.core.documents import load_graph, load_umrf
from temoto.core.graph import UmrfGraph
from temoto.core.umrf import Umrf, snake_case
from temoto.errors import (
    ActionNotFoundError,
    ConfigError,
    GraphNotFoundError,
    PluginConflictError,
    PluginLoadError,
)

__all__ = ["ACTION_PACKAGES_GROUP", "ActionCatalog", "ActionEntry", "GraphIndex", "scan_files"]

logger = logging.getLogger(__name__)

#: Entry-point group through which installed distributions offer action packages.
ACTION_PACKAGES_GROUP = "temoto.action_packages"

#: How deep below a given directory files are looked for (upstream: 2).
SCAN_DEPTH = 2


def scan_files(root: Path, marker: str, depth: int = SCAN_DEPTH) -> list[Path]:
    """Files under ``root`` (down to ``depth`` levels) whose name contains ``marker``.

    Unreadable directories are skipped.

    Args:
        root: The directory.
        marker: A substring of the file name (``umrf.json``, ``graph.json``).
        depth: Levels of sub-directories to enter.

    Returns:
        The files, sorted (deterministic across file systems).
    """
    found: list[Path] = []
    level = [root]
    for current in range(depth + 1):
        nxt: list[Path] = []
        for folder in level:
            try:
                children = sorted(folder.iterdir())
            except OSError:
                continue
            for child in children:
                if child.is_dir():
                    if current < depth and not child.name.startswith((".", "__")):
                        nxt.append(child)
                elif marker in child.name:
                    found.append(child)
        level = nxt
    return sorted(found)


@dataclass(frozen=True, slots=True)
class ActionEntry:
    """One known action: its description and where its code is.

    Attributes:
        description: The parsed ``*.umrf.json``.
        origin: Where it came from (a file path, an entry point, "registered in code").
        module: A dotted module name to import (entry-point packages), or None.
        module_file: A file to import the module from (directories), or None.
        cls: The class, when registered in code.
    """

    description: Umrf
    origin: str
    module: str | None = None
    module_file: Path | None = None
    cls: type[Action] | None = None


class ActionCatalog:
    """Action descriptions by name, and lazy access to their classes.

    Args:
        paths: Directories to scan (depth ≤ 2) for ``*umrf.json`` files.
        use_entry_points: Also scan packages named by the ``temoto.action_packages`` group.

    Raises:
        ConfigError: If a path is not a directory.
    """

    def __init__(self, paths: Iterable[str | Path] = (), *, use_entry_points: bool = True) -> None:
        self._paths: list[Path] = []
        self._use_entry_points = use_entry_points
        self._registered: dict[str, ActionEntry] = {}
        self._entries: dict[str, list[ActionEntry]] = {}
        self._classes: dict[str, type[Action]] = {}
        self._lock = threading.Lock()
        self._generation = 0
        self.problems: list[tuple[str, str]] = []
        for path in paths:
            self._paths.append(_check_dir(path, "action"))
        self.refresh()

    @property
    def generation(self) -> int:
        """Grows whenever the catalog may have changed (``register``, ``refresh``)."""
        return self._generation

    # ---- building ---------------------------------------------------------------------------

    def add_path(self, path: str | Path) -> int:
        """Add a directory of actions and index it.

        Args:
            path: The directory.

        Returns:
            How many action descriptions it holds (0 is logged as a warning).

        Raises:
            ConfigError: If the path is not a directory.
        """
        folder = _check_dir(path, "action")
        if folder not in self._paths:
            self._paths.append(folder)
        self.refresh()
        count = sum(
            1
            for entries in self._entries.values()
            for e in entries
            if Path(e.origin).is_relative_to(folder)
        )
        if not count:
            logger.warning("no *umrf.json action descriptions under %s", folder)
        return count

    def register(self, cls: type[Action], description: Umrf) -> None:
        """Add an action defined in code (tests, embedded use).

        Args:
            cls: The Action subclass.
            description: Its description (name, type, parameters).

        Returns:
            None.

        Raises:
            TypeError: If ``cls`` is not an Action subclass.
        """
        if not (isinstance(cls, type) and issubclass(cls, Action)):
            raise TypeError(f"{cls!r} is not a subclass of temoto.Action")
        entry = ActionEntry(
            description, f"registered in code ({cls.__module__}.{cls.__qualname__})", cls=cls
        )
        with self._lock:
            self._registered[description.name] = entry
            self._entries.setdefault(description.name, []).insert(0, entry)
            self._entries[description.name] = _dedupe(self._entries[description.name])
            self._classes.pop(description.name, None)
            self._generation += 1

    def refresh(self) -> None:
        """Re-read every description (new files appear, removed ones vanish).

        Unreadable files are logged and listed in :attr:`problems`.

        Returns:
            None.
        """
        entries: dict[str, list[ActionEntry]] = {}
        problems: list[tuple[str, str]] = []
        for name, entry in self._registered.items():
            entries.setdefault(name, []).append(entry)
        for folder in self._paths:
            for file in scan_files(folder, "umrf.json"):
                self._index_file(file, None, folder, entries, problems)
        if self._use_entry_points:
            from importlib.metadata import entry_points  # slow to import; only needed here

            for ep in entry_points(group=ACTION_PACKAGES_GROUP):
                self._index_package(ep.value, f"entry point {ep.name}", entries, problems)
        with self._lock:
            self._entries = entries
            self._classes = {k: v for k, v in self._classes.items() if k in entries}
            self.problems = problems
            self._generation += 1

    def _index_package(
        self,
        package: str,
        origin: str,
        entries: dict[str, list[ActionEntry]],
        problems: list[tuple[str, str]],
    ) -> None:
        try:
            spec = importlib.util.find_spec(package)
        except (ImportError, ValueError) as err:
            problems.append((origin, f"cannot locate package {package!r}: {err}"))
            return
        if spec is None or not spec.submodule_search_locations:
            problems.append((origin, f"{package!r} is not a package"))
            return
        for location in spec.submodule_search_locations:
            root = Path(location)
            for file in scan_files(root, "umrf.json"):
                self._index_file(file, package, root, entries, problems)

    def _index_file(
        self,
        file: Path,
        package: str | None,
        root: Path,
        entries: dict[str, list[ActionEntry]],
        problems: list[tuple[str, str]],
    ) -> None:
        warnings: list[str] = []
        try:
            desc = load_umrf(file, warnings=warnings)
        except ConfigError as err:
            logger.error("skipping action description: %s", err)
            problems.append((str(file), str(err)))
            return
        for text in warnings:
            logger.debug("%s: %s", file, text)
        module_file = _module_beside(file, desc.name)
        module: str | None = None
        if package is not None and module_file is not None:
            rel = module_file.relative_to(root).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            module = ".".join([package, *parts])
            module_file = None
        entry = ActionEntry(desc, str(file), module=module, module_file=module_file)
        entries[desc.name] = _dedupe([*entries.get(desc.name, []), entry])

    # ---- lookup -----------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Names of every known action.

        Returns:
            Sorted names.
        """
        with self._lock:
            return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._entries

    def __iter__(self) -> Iterator[Umrf]:
        with self._lock:
            found = [e[0].description for e in self._entries.values()]
        return iter(found)

    def entry(self, name: str) -> ActionEntry:
        """The single source of an action.

        Args:
            name: Action name.

        Returns:
            Its entry.

        Raises:
            ActionNotFoundError: If unknown.
            PluginConflictError: If several sources offer it.
        """
        with self._lock:
            entries = self._entries.get(name)
        if not entries:
            raise ActionNotFoundError(f"no action named '{name}' is known")
        if len(entries) > 1:
            origins = "; ".join(e.origin for e in entries)
            raise PluginConflictError(f"action '{name}' is offered by several sources: {origins}")
        return entries[0]

    def find(self, name: str) -> Umrf | None:
        """The description of an action, if exactly one source offers it.

        Args:
            name: Action name.

        Returns:
            The description, or None if unknown.

        Raises:
            PluginConflictError: If several sources offer it.
        """
        try:
            return self.entry(name).description
        except ActionNotFoundError:
            return None

    def load_class(self, name: str) -> type[Action]:
        """Import (once) and return the class implementing an action.

        Args:
            name: Action name.

        Returns:
            The Action subclass.

        Raises:
            ActionNotFoundError: If the action or its code is unknown.
            PluginConflictError: If several sources offer it.
            PluginLoadError: If importing the module fails or it has no such Action class.
        """
        with self._lock:
            cached = self._classes.get(name)
        if cached is not None:
            return cached
        entry = self.entry(name)
        cls = entry.cls or _import_class(entry)
        with self._lock:
            self._classes[name] = cls
        return cls


def _dedupe(entries: list[ActionEntry]) -> list[ActionEntry]:
    """Drop entries that describe the same action from the same file (re-scans)."""
    seen: set[str] = set()
    out = []
    for entry in entries:
        if entry.origin not in seen:
            seen.add(entry.origin)
            out.append(entry)
    return out


def _check_dir(path: str | Path, what: str) -> Path:
    folder = Path(path).expanduser().resolve()
    if not folder.is_dir():
        raise ConfigError(f"{what} path is not a directory", file=str(path))
    return folder


def _module_beside(description: Path, name: str) -> Path | None:
    """The Python module that implements the action described by ``description``."""
    stem = description.name.split("umrf.json")[0].rstrip(".")
    folder = description.parent
    candidates = [folder / f"{snake_case(name)}.py", folder / "__init__.py"]
    if stem:  # "<stem>.umrf.json"; a plain (legacy) "umrf.json" names no module
        candidates.insert(0, folder / f"{stem}.py")
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


def _import_class(entry: ActionEntry) -> type[Action]:
    name = entry.description.name
    where = entry.module or (str(entry.module_file) if entry.module_file else None)
    if where is None:
        raise ActionNotFoundError(
            f"action '{name}' is described in {entry.origin} but no Python module lies beside it"
            f" (expected {snake_case(name)}.py or __init__.py in that folder)"
        )
    try:
        if entry.module is not None:
            module = importlib.import_module(entry.module)
        else:
            assert entry.module_file is not None
            module = _import_file(entry.module_file)
    except Exception as err:  # a broken plugin must not take the engine down
        raise PluginLoadError(f"cannot import action '{name}' from {where}: {err}") from err
    cls = getattr(module, name, None)
    if not (isinstance(cls, type) and issubclass(cls, Action)):
        raise PluginLoadError(f"{where} defines no Action subclass named '{name}'")
    return cls


#: Action files are imported one at a time: a module is in ``sys.modules`` while its code runs,
#: and a second importer must wait for the end of it, not take the half-made module (two
#: engines of one process starting graphs with the same action got "defines no Action subclass").
_FILE_IMPORT = threading.RLock()


def _import_file(file: Path) -> ModuleType:
    digest = hashlib.sha1(str(file.parent).encode(), usedforsecurity=False).hexdigest()[:10]
    is_package = file.name == "__init__.py"
    stem = file.parent.name if is_package else file.stem
    modname = f"_temoto_action_{digest}_{stem}"
    with _FILE_IMPORT:
        done = sys.modules.get(modname)
        if done is not None:
            return done
        spec = importlib.util.spec_from_file_location(
            modname, file, submodule_search_locations=[str(file.parent)] if is_package else None
        )
        if spec is None or spec.loader is None:
            raise ImportError(f"cannot build an import spec for {file}")
        module = importlib.util.module_from_spec(spec)
        sys.modules[modname] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[modname]
            raise
        return module


class GraphIndex:
    """Graphs found on disk (``*graph.json``, depth ≤ 2), by name.

    Args:
        paths: Directories to scan.

    Raises:
        ConfigError: If a path is not a directory.
    """

    def __init__(self, paths: Iterable[str | Path] = ()) -> None:
        self._paths = [_check_dir(p, "graph") for p in paths]
        self._graphs: dict[str, list[UmrfGraph]] = {}
        self._lock = threading.Lock()
        self._generation = 0
        self.problems: list[tuple[str, str]] = []
        self.refresh()

    @property
    def generation(self) -> int:
        """Grows whenever the index may have changed (``add``, ``refresh``)."""
        return self._generation

    def add_path(self, path: str | Path) -> None:
        """Add a directory of graphs and index it.

        Args:
            path: The directory.

        Returns:
            None.

        Raises:
            ConfigError: If the path is not a directory.
        """
        folder = _check_dir(path, "graph")
        if folder not in self._paths:
            self._paths.append(folder)
        self.refresh()

    def add(self, graph: UmrfGraph) -> None:
        """Index a graph held in memory.

        Args:
            graph: The graph.

        Returns:
            None.
        """
        with self._lock:
            self._graphs.setdefault(graph.name, []).append(graph)
            self._generation += 1

    def refresh(self) -> None:
        """Re-read every graph file.

        Unreadable files are logged and listed in :attr:`problems`.

        Returns:
            None.
        """
        graphs: dict[str, list[UmrfGraph]] = {}
        problems: list[tuple[str, str]] = []
        for folder in self._paths:
            for file in scan_files(folder, "graph.json"):
                try:
                    graph = load_graph(file)
                except ConfigError as err:
                    logger.error("skipping graph: %s", err)
                    problems.append((str(file), str(err)))
                    continue
                graphs.setdefault(graph.name, []).append(graph)
        with self._lock:
            memory = [g for gs in self._graphs.values() for g in gs if g.source is None]
            for graph in memory:
                graphs.setdefault(graph.name, []).append(graph)
            self._graphs = graphs
            self.problems = problems
            self._generation += 1

    def names(self) -> list[str]:
        """Names of every indexed graph.

        Returns:
            Sorted names.
        """
        with self._lock:
            return sorted(self._graphs)

    def all(self) -> list[UmrfGraph]:
        """Every indexed graph.

        Returns:
            The graphs, by name then file.
        """
        with self._lock:
            return [g for name in sorted(self._graphs) for g in self._graphs[name]]

    def get(self, name: str) -> UmrfGraph:
        """The graph of that name.

        Args:
            name: Graph name.

        Returns:
            The graph.

        Raises:
            GraphNotFoundError: If no graph has that name.
            PluginConflictError: If several different graphs have it.
        """
        with self._lock:
            found = list(self._graphs.get(name, ()))
        if not found:
            raise GraphNotFoundError(f"no graph named '{name}' is indexed")
        return _single(name, found)

    def find_subgraph(self, action: Umrf) -> UmrfGraph | None:
        """The graph that can run ``action`` as a sub-graph (same name and signature).

        Args:
            action: The graph action.

        Returns:
            The graph, or None.

        Raises:
            PluginConflictError: If several different graphs match.
        """
        with self._lock:
            found = [g for g in self._graphs.get(action.name, ()) if g.signature().matches(action)]
        return _single(action.name, found) if found else None


def _single(name: str, found: list[UmrfGraph]) -> UmrfGraph:
    first = found[0]
    if any(g != first for g in found[1:]):
        origins = "; ".join(g.source or "memory" for g in found)
        raise PluginConflictError(f"several different graphs are named '{name}': {origins}")
    return first
