"""The Component Manager's catalog: what components exist, and which to try first.

:class:`ComponentCatalog` is the half of
:class:`~temoto.managers.component.manager.ComponentManager` that knows the descriptions and
templates (from files or code, all or nothing per call), ranks the candidates for a type
(:class:`Candidate`: priority, then reliability, then local before remote; remote ones only
while the RIS hears their robot offering ``"component"``), explains why no candidate is
available, keeps each candidate's reliability and writes it to the reliability file (format in
:mod:`temoto.managers.component.reliability`) after each operation that recorded outcomes. The
manager adds starting, failover and the registrar hooks on top of it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from temoto.core.registrar import Registrar
from temoto.errors import ComponentNotFoundError, ConfigError
from temoto.managers.component.description import (
    ComponentDescription,
    PipelineTemplate,
    load_descriptions,
)
from temoto.managers.component.reliability import Reliability, load_outcomes, save_outcomes

if TYPE_CHECKING:
    from temoto.fleet.ris import ResourceInfoSync

__all__ = ["COMPONENT_STATS", "Candidate", "ComponentCatalog"]

logger = logging.getLogger(__name__)

#: Counters in :attr:`ComponentManager.stats`.
COMPONENT_STATS = (
    "starts",
    "start_failures",
    "failures",
    "failovers",
    "exhausted",
    "reliability_write_errors",
)


@dataclass(frozen=True)
class Candidate:
    """One way to provide a component type (a snapshot, for ranking).

    Attributes:
        description: The component's description.
        robot: The robot hosting it.
        local: Whether that is this manager's robot.
        reliability: Its reliability when the snapshot was taken.
    """

    description: ComponentDescription
    robot: str
    local: bool
    reliability: float

    @property
    def key(self) -> str:
        """``robot/name``: the candidate's identity (and its reliability's key)."""
        return f"{self.robot}/{self.description.name}"

    def rank(self) -> tuple[int, float, bool, str]:
        """Sort key, best first: priority, reliability, local before remote, key."""
        return (-self.description.priority, -self.reliability, not self.local, self.key)


class ComponentCatalog:
    """Descriptions, templates, candidates and their reliabilities (see the module docstring).

    The base of :class:`~temoto.managers.component.manager.ComponentManager`, whose docstring
    describes the arguments; ``name`` is the server name the RIS is asked about.

    Raises:
        ValueError: ``window`` below 1.
        ConfigError: The reliability file cannot be read or used.
    """

    name: ClassVar[str] = "component"

    def __init__(
        self,
        registrar: Registrar,
        *,
        robot: str | None,
        ris: ResourceInfoSync | None,
        window: int,
        reliability_file: str | Path | None,
    ) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._store = None if reliability_file is None else Path(reliability_file)
        #: Restored outcomes of candidates not described yet (applied by :meth:`add`).
        self._saved = {} if self._store is None else load_outcomes(self._store, window)
        self._store_lock = threading.Lock()  # one writer of the file at a time
        self._unsaved = 0  # outcomes recorded since the last successful write
        self._store_failing = False  # in a streak of failed writes (guarded by _store_lock)
        self.registrar = registrar
        self.robot = robot or registrar.name
        self.window = window
        self._ris = ris
        self._lock = threading.Lock()
        self._components: dict[tuple[str, str], ComponentDescription] = {}
        self._templates: dict[str, PipelineTemplate] = {}
        self._reliability: dict[str, Reliability] = {}
        self._counts = dict.fromkeys(COMPONENT_STATS, 0)

    # ------------------------------------------------------------------ descriptions

    def add(
        self,
        components: Iterable[ComponentDescription] = (),
        templates: Iterable[PipelineTemplate] = (),
    ) -> None:
        """Add components and templates, all or nothing.

        Args:
            components: Descriptions (a ``(robot, name)`` must be new).
            templates: Templates (a name must be new).

        Returns:
            None.

        Raises:
            ConfigError: A duplicate; nothing was added.
        """
        comps = list(components)
        temps = list(templates)
        with self._lock:
            seen: set[tuple[str, str]] = set()
            for desc in comps:
                key = (desc.robot or self.robot, desc.name)
                if key in self._components or key in seen:
                    raise ConfigError(
                        f"component '{key[1]}' of robot '{key[0]}' is described twice",
                        file=desc.source or None,
                    )
                seen.add(key)
            names = [t.name for t in temps]
            for tpl in temps:
                if tpl.name in self._templates or names.count(tpl.name) > 1:
                    raise ConfigError(
                        f"template '{tpl.name}' is described twice", file=tpl.source or None
                    )
            for desc in comps:
                robot = desc.robot or self.robot
                self._components[(robot, desc.name)] = desc
                cand = f"{robot}/{desc.name}"
                if cand not in self._reliability:  # restored outcomes apply from the start
                    history = self._saved.pop(cand, [])
                    self._reliability[cand] = Reliability(desc.reliability, self.window, history)
            for tpl in temps:
                self._templates[tpl.name] = tpl

    def add_file(self, path: str | Path) -> None:
        """Read a description file and add what it describes (all or nothing).

        Args:
            path: A ``.yaml``/``.yml``/``.json`` file.

        Returns:
            None.

        Raises:
            ConfigError: Unreadable, malformed or duplicate (``PipelineError`` for a cyclic
                or malformed template); nothing was added.
        """
        components, templates = load_descriptions(path)
        self.add(components, templates)

    def descriptions(self, type: str | None = None) -> list[ComponentDescription]:  # noqa: A002
        """The known components (of one type, or all).

        Args:
            type: A component type, or None.

        Returns:
            Descriptions, sorted by robot and name.
        """
        with self._lock:
            items = sorted(self._components.items())
        return [d for _, d in items if type is None or d.type == type]

    def types(self) -> list[str]:
        """The known component types (local and remote descriptions), sorted."""
        with self._lock:
            return sorted({d.type for d in self._components.values()})

    def template(self, name: str) -> PipelineTemplate:
        """A pipeline template.

        Args:
            name: Its name.

        Returns:
            The template.

        Raises:
            ComponentNotFoundError: No template of that name.
        """
        with self._lock:
            tpl = self._templates.get(name)
            known = sorted(self._templates)
        if tpl is None:
            raise ComponentNotFoundError(
                f"no pipeline template named '{name}' (known: {', '.join(known) or 'none'})",
                origin=self.registrar.name,
            )
        return tpl

    def templates(self) -> list[str]:
        """Names of the known templates, sorted."""
        with self._lock:
            return sorted(self._templates)

    # ------------------------------------------------------------------ ranking

    def reliability(self, name: str, robot: str = "") -> float:
        """A candidate's reliability (as this manager sees it).

        Args:
            name: The description name.
            robot: Its robot ("" = this one).

        Returns:
            The value in [0, 1].

        Raises:
            ComponentNotFoundError: No such candidate.
        """
        key = f"{robot or self.robot}/{name}"
        with self._lock:
            rel = self._reliability.get(key)
            if rel is None:
                raise ComponentNotFoundError(f"no component '{key}'", origin=self.registrar.name)
            return rel.value

    def candidates(
        self,
        type: str,  # noqa: A002
        *,
        name: str = "",
        local_only: bool = False,
        exclude: Sequence[str] = (),
    ) -> list[Candidate]:
        """The available candidates for a type, best first (this is the failover order).

        Best = higher priority, then higher reliability, then local before remote, then
        ``robot/name``. Remote candidates count only if their robot is heard offering
        ``"component"``.

        Args:
            type: The component type.
            name: Only this description name ("" = all).
            local_only: Only this robot's.
            exclude: ``robot/name`` keys to leave out.

        Returns:
            Candidates.
        """
        remote_ok = self._remote_robots() if not local_only else set()
        with self._lock:
            found = []
            for (robot, cname), desc in self._components.items():
                if desc.type != type or (name and cname != name):
                    continue
                local = robot == self.robot
                if not local and robot not in remote_ok:
                    continue
                key = f"{robot}/{cname}"
                if key in exclude:
                    continue
                found.append(Candidate(desc, robot, local, self._reliability[key].value))
        found.sort(key=Candidate.rank)
        return found

    def check_type(self, type: str, *, name: str = "", local_only: bool = False) -> None:  # noqa: A002
        """Raise unless some candidate can provide the type now.

        Args:
            type: The component type.
            name: Only this description name.
            local_only: Only this robot's.

        Returns:
            None.

        Raises:
            ComponentNotFoundError: Unknown type, or no candidate available (the message says
                which and why).
        """
        if self.candidates(type, name=name, local_only=local_only):
            return
        raise ComponentNotFoundError(
            self._why_none(type, name, local_only), origin=self.registrar.name
        )

    def _why_none(self, type_: str, name: str, local_only: bool) -> str:
        with self._lock:
            of_type = [(r, n) for (r, n), d in self._components.items() if d.type == type_]
            known = sorted({d.type for d in self._components.values()})
        if not of_type:
            return f"no component of type '{type_}' (known types: {', '.join(known) or 'none'})"
        named = [(r, n) for r, n in of_type if not name or n == name]
        if not named:
            return f"no component '{name}' of type '{type_}'"
        remote = sorted({r for r, _ in named if r != self.robot})
        if local_only:
            return f"no local component of type '{type_}' (others on: {', '.join(remote)})"
        return (
            f"no component of type '{type_}' is available: robot(s) {', '.join(remote)}"
            " not heard offering 'component' (or no RIS / remote server here)"
        )

    def _remote_robots(self) -> set[str]:
        if self._ris is None or "remote" not in self.registrar.servers():
            return set()
        return set(self._ris.providers(self.name))

    def _rate(self, candidate: Candidate, outcome: float) -> float:
        """Record an outcome (in memory; :meth:`_persist` writes the file afterwards)."""
        with self._lock:
            value = self._reliability[candidate.key].adjust(outcome)
            if self._store is not None:
                self._unsaved += 1
            return value

    def _persist(self) -> None:
        """Write the reliability file if outcomes were recorded since the last write.

        Called after an operation (start, failover, release), outside the manager's lock, by
        whichever thread did it; ``_store_lock`` serialises writers, and the state is taken
        inside it, so the last write holds the newest state. An ``OSError`` is counted and
        logged, never raised (the next write retries).
        """
        if self._store is None or not self._unsaved:  # unlocked read: whoever rated persists
            return
        with self._store_lock:
            with self._lock:
                unsaved, self._unsaved = self._unsaved, 0
                if not unsaved:
                    return
                state = dict(self._saved)
                for key, rel in self._reliability.items():
                    outcomes = rel.outcomes()
                    if outcomes:
                        state[key] = outcomes
            try:
                save_outcomes(self._store, self.window, state)
            except OSError as err:
                with self._lock:
                    self._unsaved += unsaved
                    self._counts["reliability_write_errors"] += 1
                if not self._store_failing:
                    self._store_failing = True
                    logger.warning(
                        "cannot write the reliability file %s (kept in memory; retried with "
                        "the next outcome): %s",
                        self._store,
                        err,
                    )
                else:
                    logger.debug("reliability file %s still not written: %s", self._store, err)
                return
            if self._store_failing:
                self._store_failing = False
                logger.info("reliability file %s written again", self._store)

    @property
    def stats(self) -> dict[str, int]:
        """Counters (:data:`COMPONENT_STATS`), e.g. ``failovers``, ``reliability_write_errors``."""
        with self._lock:
            return dict(self._counts)

    def _count(self, what: str) -> None:
        with self._lock:
            self._counts[what] += 1
