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

Code: :mod:`~temoto.managers.component.catalog` (:class:`ComponentCatalog`, the manager's base:
descriptions, ranking, reliabilities and their file), this module (loading, starting a
candidate, failover, the ``"component"`` hooks) and
:mod:`~temoto.managers.component.pipeline_server` (:class:`PipelineServer`).
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
from collections.abc import Callable, Iterable, Mapping
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
    ResourceBrokenError,
    ResourceClosedError,
    ResourceError,
    ResourceLoadError,
)
from temoto.managers.component.catalog import COMPONENT_STATS, Candidate, ComponentCatalog
from temoto.managers.component.description import ComponentDescription
from temoto.managers.component.messages import (
    ComponentRequest,
    ComponentResponse,
)
from temoto.managers.component.pipeline_server import PipelineServer
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


class ComponentManager(ComponentCatalog, ResourceServer[ComponentRequest, ComponentResponse]):
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
        super().__init__(
            registrar, robot=robot, ris=ris, window=window, reliability_file=reliability_file
        )
        self.channel_prefix = channel_prefix
        self._active: dict[str, _Active] = {}
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

    def channel(self, uid: str, output: str) -> str:
        """The channel this manager allocates to one output of a resource.

        Args:
            uid: The resource's id (a component's, or a pipeline's for its links).
            output: The output's (or the pipeline link's) name.

        Returns:
            An abstract Unix socket address, unique to this manager, resource and output.
        """
        return f"unix:@{self.channel_prefix}-{self.registrar.name}-{uid}-{output}"

    def _start(self, state: _Active, candidate: Candidate) -> ComponentResponse:
        desc = candidate.description
        pinned = dict(state.request.outputs)
        outputs = {n: pinned.get(n) or self.channel(state.uid, n) for n in desc.outputs}
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
