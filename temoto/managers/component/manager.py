"""The Component Manager: components by type, reliability-ranked, with failover; pipelines.

See ``docs/component-manager.md``. Two servers on the registrar:

* ``"component"`` (:class:`ComponentManager`): a :class:`ComponentRequest` names a type; the
  manager ranks the candidates (priority, then reliability, then local before remote), starts
  the best one (a process through the Process Manager, or the same component on another robot
  through the RIS and the ``"remote"`` server) and keeps the *resource* — the type with its
  channels — alive across failures of the candidates behind it.
* ``"pipeline"`` (:class:`PipelineServer`): a :class:`PipelineRequest` names a template; each
  segment is a component resource (a registrar dependency of the pipeline), wired by channels.

Failover: the active candidate's process (or remote proxy) is held by the manager under the
client name ``<registrar>/<component id>``, *not* as a registrar dependency: a dependency's FATAL
would reach the component's consumers before the manager could substitute. On its FATAL (monitor
thread) a job goes to the manager's worker thread, which rates the candidate down, starts the
next one with the same channels (so the consumers and downstream segments keep receiving),
updates the response and tells the consumers (WARNING ``switched from A to B: ...``), then
releases the dead one. With no substitute (or ``failover=False``) the consumers get FATAL.

Reliabilities are kept in memory, and with ``reliability_file`` also in a file (format in
:mod:`temoto.managers.component.reliability`): read at construction, rewritten atomically after
each operation that recorded outcomes (a start, a failover, a release), outside the manager's
lock and after the substitute is started, one writer at a time.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from temoto.core.registrar import (
    LoadContext,
    Registrar,
    Resource,
    ResourceInfo,
    ResourceServer,
    Status,
    StatusUpdate,
)
from temoto.errors import (
    ComponentNotFoundError,
    ConfigError,
    ResourceBrokenError,
    ResourceClosedError,
    ResourceError,
    ResourceLoadError,
)
from temoto.managers.component.description import (
    ComponentDescription,
    PipelineTemplate,
    load_descriptions,
)
from temoto.managers.component.messages import (
    ComponentRequest,
    ComponentResponse,
    PipelineRequest,
    PipelineResponse,
)
from temoto.managers.component.reliability import Reliability, load_outcomes, save_outcomes
from temoto.managers.process import ProcessRequest, ProcessResponse

if TYPE_CHECKING:
    from temoto.fleet.ris import ResourceInfoSync

__all__ = [
    "COMPONENT_STATS",
    "COMPONENT_VARIABLE",
    "Candidate",
    "ComponentManager",
    "PipelineServer",
]

logger = logging.getLogger(__name__)

#: Environment variable naming the component a started process is (``robot/name``).
COMPONENT_VARIABLE = "TEMOTO_COMPONENT"

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


@dataclass(eq=False)
class _Active:
    """A loaded component resource and the candidate behind it (guarded by the manager lock)."""

    uid: str
    request: ComponentRequest
    client: str
    candidate: Candidate | None = None
    held: Resource[Any] | None = None
    held_gen: int = -1
    generation: int = 0
    response: ComponentResponse | None = None
    tried: list[str] = field(default_factory=list)
    switches: int = 0
    closing: bool = False


class ComponentManager(ResourceServer[ComponentRequest, ComponentResponse]):
    """The ``"component"`` server (and owner of the ``"pipeline"`` server).

    Creating it registers both servers. Components and templates come from description files
    (``files``, :meth:`add_file`) or code (:meth:`add`). Candidates on other robots (a
    description whose ``robot`` is another robot) are used when ``ris`` is given, a
    ``"remote"`` server (:class:`~temoto.fleet.resources.RemoteResources`) is registered and
    the RIS hears that robot offering ``"component"``.

    Args:
        registrar: The registrar to serve on (a Process Manager must serve ``"process"``
            there for local candidates).
        robot: This robot's name (default: the registrar's name).
        files: Description files to read now.
        ris: The Resource Info Synchronizer, for candidates on other robots.
        window: Outcomes the reliability average covers (upstream: 100).
        channel_prefix: Start of the abstract socket names the manager allocates.
        reliability_file: Where reliabilities survive a restart (JSON; see
            :mod:`~temoto.managers.component.reliability`), or None to keep them in memory
            only. Read now if it exists (outcomes of candidates not described yet are kept
            for when they are); rewritten atomically whenever outcomes were recorded. A
            failed write is logged (a warning once per streak of failures), counted in
            ``stats["reliability_write_errors"]`` and retried with the next write.

    Raises:
        ConfigError: A description file is malformed (``PipelineError`` for templates), or
            the reliability file cannot be read or used (the message names the file).
        ValueError: A server named ``"component"`` or ``"pipeline"`` is registered.
    """

    name: ClassVar[str] = "component"
    request_type: ClassVar[type[Any]] = ComponentRequest
    response_type: ClassVar[type[Any]] = ComponentResponse

    def __init__(
        self,
        registrar: Registrar,
        *,
        robot: str | None = None,
        files: Iterable[str | Path] = (),
        ris: ResourceInfoSync | None = None,
        window: int = 100,
        channel_prefix: str = "temoto",
        reliability_file: str | Path | None = None,
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
        self.channel_prefix = channel_prefix
        self._ris = ris
        self._lock = threading.Lock()
        self._components: dict[tuple[str, str], ComponentDescription] = {}
        self._templates: dict[str, PipelineTemplate] = {}
        self._reliability: dict[str, Reliability] = {}
        self._active: dict[str, _Active] = {}
        self._counts = dict.fromkeys(COMPONENT_STATS, 0)
        self._closed = False
        for file in files:
            self.add_file(file)
        self.pipelines = PipelineServer(self)
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._worker = threading.Thread(
            target=self._run_jobs, name="temoto-component-failover", daemon=True
        )
        self._starter = ThreadPoolExecutor(2, thread_name_prefix="temoto-component-start")
        self._worker.start()
        try:
            registrar.register(self)
            registrar.register(self.pipelines)
        except BaseException:
            self.shutdown()
            raise

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

    # ------------------------------------------------------------------ server hooks

    def on_load(self, request: ComponentRequest, ctx: LoadContext) -> ComponentResponse:
        """Start the best candidate (on a starter thread: not a registrar dependency)."""
        self._check_open()
        self.check_type(request.type, name=request.name, local_only=request.local_only)
        state = _Active(ctx.resource_id, request, f"{self.registrar.name}/{ctx.resource_id}")
        # What holds the candidates: if this process dies before the load returns, the
        # restarted registrar hands it to on_abandoned, which releases them.
        ctx.checkpoint({"client": state.client})
        with self._lock:
            self._active[state.uid] = state
        try:
            return self._starter.submit(self._start_next, state, "").result()
        except BaseException:
            with self._lock:
                self._active.pop(state.uid, None)
            raise
        finally:
            self._persist()  # candidates that failed to start were rated down

    def on_unload(self, request: ComponentRequest, response: ComponentResponse) -> None:
        """Stop the active candidate; it served until released: a success for its rating."""
        with self._lock:
            state = self._active.pop(response.resource_id, None)
            if state is not None:
                state.closing = True
                held, state.held, state.held_gen = state.held, None, -1
                candidate = state.candidate
        if state is None:
            # Restored from the catalog (what held its candidate died with the previous
            # process): release what it held, if anything still is.
            self.registrar.release_client(f"{self.registrar.name}/{response.resource_id}")
            return
        if held is None:
            return
        if candidate is not None:
            self._rate(candidate, 1.0)
            self._persist()
        self._release(held)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart: a component is not re-adopted; its candidate is released.

        The manager that watched the candidate and would fail it over died with the previous
        process, so the resource is reported FATAL (its consumers request it again; new equal
        requests load a fresh one) and the candidate's process is stopped now, not when the
        consumers get round to releasing the component.
        """
        if resource.failed:
            return None  # reported before the restart; released by on_unload
        self.registrar.release_client(f"{self.registrar.name}/{resource.id}")
        return Status.FATAL, "the Component Manager restarted; request the component again"

    def on_abandoned(self, request: ComponentRequest, progress: Mapping[str, Any] | None) -> None:
        """After a restart: a load was interrupted; release the candidate it may have started.

        Args:
            request: The request being loaded.
            progress: ``{"client": ...}``, the client name its candidates were held under.
        """
        client = (progress or {}).get("client")
        if isinstance(client, str) and client:
            released = self.registrar.release_client(client)
            if released:
                logger.info("interrupted load of %s: released its candidate", request.type)

    # ------------------------------------------------------------------ starting

    def _start_next(self, state: _Active, reason: str) -> ComponentResponse:
        """Start the best candidate not yet tried for this resource; the new response."""
        errors: list[str] = []
        while True:
            with self._lock:
                if state.closing or self._closed:
                    raise ResourceClosedError("the component is being released")
                tried = list(state.tried)
            found = self.candidates(
                state.request.type,
                name=state.request.name,
                local_only=state.request.local_only,
                exclude=tried,
            )
            found = [c for c in found if _fits(c.description, state.request)]
            if not found:
                what = f"type '{state.request.type}'" + (
                    f" named '{state.request.name}'" if state.request.name else ""
                )
                if errors:
                    raise ResourceLoadError(
                        f"no candidate of {what} could start: {'; '.join(errors)}",
                        origin=self.registrar.name,
                    )
                if tried:
                    raise ComponentNotFoundError(
                        f"no candidate of {what} left (failed: {', '.join(tried)})",
                        origin=self.registrar.name,
                    )
                raise ComponentNotFoundError(
                    f"no candidate of {what} fits the request's outputs, inputs and parameters",
                    origin=self.registrar.name,
                )
            candidate = found[0]
            if reason:
                logger.info("substituting %s for %s (%s)", candidate.key, state.uid, reason)
            try:
                return self._start(state, candidate)
            except ResourceClosedError:
                raise
            except Exception as err:
                self._count("start_failures")
                self._rate(candidate, 0.0)
                logger.warning("component %s failed to start: %s", candidate.key, err)
                errors.append(f"{candidate.key}: {err}")
                with self._lock:
                    state.tried.append(candidate.key)
                if not state.request.failover:
                    raise ResourceLoadError(
                        f"component {candidate.key} failed to start: {err}",
                        origin=self.registrar.name,
                    ) from err

    def _channel(self, uid: str, output: str) -> str:
        return f"unix:@{self.channel_prefix}-{self.registrar.name}-{uid}-{output}"

    def _start(self, state: _Active, candidate: Candidate) -> ComponentResponse:
        desc = candidate.description
        pinned = dict(state.request.outputs)
        outputs = {n: pinned.get(n) or self._channel(state.uid, n) for n in desc.outputs}
        inputs = dict(state.request.inputs)
        with self._lock:
            state.generation += 1
            gen = state.generation
        on_status = functools.partial(self._on_candidate_status, state, gen)
        if candidate.local:
            exe, args = desc.argv(self.robot, outputs, inputs, dict(state.request.parameters))
            env = (*desc.env, (COMPONENT_VARIABLE, candidate.key))
            res = self.registrar.call(
                "process",
                ProcessRequest(exe, tuple(args), env),
                client=state.client,
                on_status=on_status,
            )
            pid = res.response.pid if isinstance(res.response, ProcessResponse) else 0
        else:
            from temoto.fleet.resource_types import remote_request, response_of

            sub = ComponentRequest(
                desc.type,
                name=desc.name,
                outputs=tuple(outputs.items()),
                inputs=tuple(inputs.items()),
                parameters=state.request.parameters,
                local_only=True,
                failover=False,
            )
            res = self.registrar.call(
                "remote",
                remote_request(self.name, sub, candidate.robot),
                client=state.client,
                on_status=on_status,
            )
            pid = response_of(res, ComponentResponse).pid
        with self._lock:
            closing = state.closing or self._closed
            if not closing:
                state.held, state.held_gen, state.candidate = res, gen, candidate
                response = ComponentResponse(
                    state.uid,
                    desc.name,
                    desc.type,
                    candidate.robot,
                    tuple(outputs.items()),
                    tuple(inputs.items()),
                    pid,
                    candidate.reliability,
                    state.switches,
                    tuple(state.tried),
                )
                state.response = response
            self._counts["starts"] += 1
        if closing:
            self._release(res)
            raise ResourceClosedError("the component is being released")
        if self.registrar.info(res.resource_id).failed:  # died before its status could reach us
            taken = self._claim(state, gen)
            if taken is not None:
                self._release(taken)
                raise ResourceBrokenError(f"component {candidate.key} stopped at once")
        logger.info("component %s started for %s (pid %d)", candidate.key, state.uid, pid)
        return response

    # ------------------------------------------------------------------ failover

    def _on_candidate_status(self, state: _Active, gen: int, update: StatusUpdate) -> None:
        """Status of an active candidate (monitor or fleet thread): queue the reaction."""
        if update.status is Status.FATAL:
            self._jobs.put(functools.partial(self._failover, state, gen, update.message))
        elif update.status in (Status.WARNING, Status.ERROR):
            self._jobs.put(functools.partial(self._forward, state, gen, update))

    def _forward(self, state: _Active, gen: int, update: StatusUpdate) -> None:
        with self._lock:
            current = state.held_gen == gen and not state.closing
            key = state.candidate.key if state.candidate else "?"
        if current:
            self._send(state.uid, update.status, f"{key}: {update.message}")

    def _claim(self, state: _Active, gen: int) -> Resource[Any] | None:
        """Take the held candidate if it is still generation ``gen`` (one reaction per failure)."""
        with self._lock:
            if state.held_gen != gen or state.held is None or state.closing:
                return None
            held, state.held, state.held_gen = state.held, None, -1
            return held

    def _failover(self, state: _Active, gen: int, message: str) -> None:
        """Worker thread: the active candidate failed; substitute it or report FATAL."""
        try:
            self._substitute(state, gen, message)
        finally:
            self._persist()  # after the substitute started: the write does not delay it

    def _substitute(self, state: _Active, gen: int, message: str) -> None:
        taken = self._claim(state, gen)
        if taken is None:
            return
        with self._lock:
            old = state.candidate
            assert old is not None
            state.tried.append(old.key)
            allowed = state.request.failover
        self._count("failures")
        self._rate(old, 0.0)
        logger.warning("component %s of %s failed: %s", old.key, state.uid, message)
        if not allowed:
            self._release(taken)
            self._count("exhausted")
            self._send(
                state.uid,
                Status.FATAL,
                f"component {old.key} failed ({message}); the request allows no failover",
            )
            return
        try:
            with self._lock:
                state.switches += 1
            response = self._start_next(state, message)
        except ResourceClosedError:
            self._release(taken)
            return
        except Exception as err:
            self._release(taken)
            self._count("exhausted")
            self._send(
                state.uid,
                Status.FATAL,
                f"component {old.key} failed ({message}) and no substitute could start: {err}",
            )
            return
        self._count("failovers")
        try:
            self.registrar.update_response(state.uid, response)
        except ResourceError as err:
            logger.debug("component %s is gone: %s", state.uid, err)
        self._send(
            state.uid,
            Status.WARNING,
            f"switched from {old.key} to {response.robot}/{response.name}: {message}",
        )
        self._release(taken)  # after: cleaning up the dead one does not delay the substitute

    def _send(self, uid: str, status: Status, message: str) -> None:
        try:
            self.registrar.send_status(uid, status, message)
        except ResourceError as err:
            logger.debug("status for %s not sent: %s", uid, err)

    def _release(self, held: Resource[Any]) -> None:
        try:
            self.registrar.release(held.id)
        except ResourceError as err:
            logger.debug("releasing %s: %s", held.id, err)

    def _run_jobs(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except Exception:
                logger.exception("component failover job raised")

    # ------------------------------------------------------------------ queries, lifecycle

    def active(self) -> dict[str, ComponentResponse]:
        """The loaded component resources and their active candidates.

        Returns:
            Component resource id -> its current response.
        """
        with self._lock:
            return {uid: s.response for uid, s in self._active.items() if s.response is not None}

    def _check_open(self) -> None:
        with self._lock:
            if self._closed:
                raise ResourceClosedError("the Component Manager is shut down")

    def shutdown(self) -> None:
        """Stop the worker and starter threads (idempotent).

        Components stay loaded: consumers release them (which stops their processes, and
        still records their outcome). With a reliability file, a write that failed is retried.

        Returns:
            None.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._jobs.put(None)
        if self._worker.is_alive():
            self._worker.join()
        self._starter.shutdown(wait=True)
        self._persist()

    def __enter__(self) -> ComponentManager:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def _fits(desc: ComponentDescription, request: ComponentRequest) -> bool:
    """Whether a candidate can serve a request's bound outputs, inputs and parameters."""
    outputs = {n for n, _ in request.outputs}
    inputs = {n for n, _ in request.inputs}
    params = {n for n, _ in request.parameters}
    return (
        outputs <= set(desc.outputs)
        and inputs == set(desc.inputs)
        and params <= {n for n, _ in desc.parameters}
    )


class PipelineServer(ResourceServer[PipelineRequest, PipelineResponse]):
    """The ``"pipeline"`` server: components composed by a template (made by the manager).

    Each segment is a ``"component"`` resource requested while the pipeline loads, so it is a
    registrar dependency: released with the pipeline, and its statuses (WARNING on a
    failover, FATAL when no substitute is left) reach the pipeline's consumers. Links are
    channels the manager allocates; a substitute segment is started on the same channels,
    which is how the pipeline is re-wired without restarting the other segments.

    Args:
        manager: The Component Manager.
    """

    name: ClassVar[str] = "pipeline"
    request_type: ClassVar[type[Any]] = PipelineRequest
    response_type: ClassVar[type[Any]] = PipelineResponse

    def __init__(self, manager: ComponentManager) -> None:
        self.manager = manager

    def on_load(self, request: PipelineRequest, ctx: LoadContext) -> PipelineResponse:
        """Check every segment's type, then request the segments producer first."""
        manager = self.manager
        template = manager.template(request.template)
        order = template.order()
        for seg in order:  # every type first: nothing is started for a request that cannot be
            try:
                manager.check_type(seg.type, local_only=request.local_only)
            except ComponentNotFoundError as err:
                raise ComponentNotFoundError(
                    f"template '{template.name}' segment '{seg.name}': {err}",
                    origin=manager.registrar.name,
                ) from None
        pinned = dict(request.outputs)
        unknown = set(pinned) - {n for n, _ in template.outputs}
        if unknown:
            raise ComponentNotFoundError(
                f"template '{template.name}' has no output(s) {', '.join(sorted(unknown))}",
                origin=manager.registrar.name,
            )
        links: dict[str, str] = {}
        for out, link in template.outputs:
            links[link] = pinned.get(out) or manager._channel(ctx.resource_id, link)
        for seg in order:
            for _, link in seg.inputs:
                links.setdefault(link, manager._channel(ctx.resource_id, link))
        segments = []
        for seg in order:
            outputs = {
                link.partition(".")[2]: ch
                for link, ch in links.items()
                if link.partition(".")[0] == seg.name
            }
            inputs = {inp: links[link] for inp, link in seg.inputs}
            component = ComponentRequest(
                seg.type,
                outputs=tuple(outputs.items()),
                inputs=tuple(inputs.items()),
                parameters=seg.parameters,
                local_only=request.local_only,
                failover=request.failover,
            )
            res = manager.registrar.call(manager.name, component)  # a dependency
            segments.append((seg.name, res.resource_id))
        return PipelineResponse(
            template.name,
            tuple((out, links[link]) for out, link in template.outputs),
            tuple(segments),
            tuple(sorted(links.items())),
        )

    def on_unload(self, request: PipelineRequest, response: PipelineResponse) -> None:
        """Nothing: the segments are dependencies, released by the registrar."""

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        """A segment failed for good (FATAL): the pipeline is failed too.

        Its consumers already got the segment's FATAL; marking the pipeline failed keeps new
        equal requests from sharing a pipeline with a dead segment (they load a fresh one).

        Args:
            resource: The pipeline.
            status: The status (of the pipeline or, up the chain, of a segment).
            message: What happened.
        """
        if status is Status.FATAL and not resource.failed:
            try:
                self.manager.registrar.send_status(
                    resource.id, Status.FATAL, f"a segment failed: {message}"
                )
            except ResourceError as err:
                logger.debug("pipeline %s is gone: %s", resource.id, err)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart: the pipeline is live only if every segment still is.

        The registrar asks the segments (components) first; one that is gone or failed makes
        the pipeline FATAL, so that it is never shared with nothing behind it.

        Args:
            resource: A restored pipeline.

        Returns:
            None if every segment is live (or the pipeline had failed before), else FATAL.
        """
        if resource.failed:
            return None
        response = resource.response
        registrar = self.manager.registrar
        for segment, uid in response.segments:
            try:
                failed = registrar.info(uid).failed
            except ResourceError:
                failed = True
            if failed:
                return (
                    Status.FATAL,
                    f"pipeline '{response.template}': segment '{segment}' did not survive the"
                    " restart; request the pipeline again",
                )
        return None
