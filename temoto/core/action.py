"""The Action base class: what an action author subclasses.

An action is a class with hooks the engine calls (the template method)::

    class TaAddString(Action):
        def on_run(self) -> bool:
            self.outputs["result"] = self.inputs.get_string("str_a") + " and " + ...
            return True

Beside its module lies ``ta_add_string.umrf.json`` describing the name, type and parameters.
The engine makes **one instance per node and keeps it for the life of the graph run**, so an
action may keep state between runs of a cycle.

Hooks and where they run:

* ``on_init()``: once, in a worker thread, before the first ``on_run``.
* ``on_run() -> bool``: in a worker thread; ``True``/``False`` become the ``on_true``/
  ``on_false`` results, an exception ``on_error``, anything but a bool is a ``TypeError``
  (``on_error``). Long work must notice stops: use :meth:`Action.sleep`,
  :meth:`Action.wait_for` or :meth:`Action.wait_until_stopped`, or check
  :attr:`Action.stop_requested`. The engine waits ``stop_timeout`` seconds (default 5) for
  ``on_run`` to return after a stop, then marks the node ERROR.
* ``on_pause()``, ``on_resume()``, ``on_stop()``: in a worker thread, concurrently with
  ``on_run``; keep them short and thread-safe.

**Inline actions.** An action whose ``on_run`` never waits (no helper that sleeps or waits, no
I/O, no resource acquisition: a computation, a comparison, a relay) declares so with the class
attribute ``blocking = False``. The engine then runs it on the thread that evolves its graph,
right after the evolution step that made it ready, without handing it to another worker; the
inline actions that become ready together run back to back in one loop. Stop, pause, resume,
modify and ``stop_timeout`` behave as for any action (``on_run`` still runs outside the
engine's lock); the difference is cost: an inline action saves the hand-off to a worker, and an
inline action that does block holds up the inline actions queued behind it on its thread.
``blocking = True`` (the default) keeps every run on a worker of its own.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar

from temoto.core.control import RunControl
from temoto.core.params import NO_VALUE, Parameter
from temoto.core.registrar.messages import Resource, Status, StatusUpdate
from temoto.core.states import Result
from temoto.core.umrf import LogMessage
from temoto.core.values import NO_INPUTS, NO_OUTPUTS, NO_VALUES, Inputs, Outputs
from temoto.errors import ActionError, ResourceError, StopRequested

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.registrar.registry import Registrar

__all__ = ["ACTION_LOGGER", "LOG_LENGTH", "Action", "Inputs", "Outputs", "RunControl"]

#: How many runtime log messages a node keeps (newest first), as upstream.
LOG_LENGTH = 10
#: The logger the actions log under: a node's is ``temoto.action.<graph>.<node>``
#: (:attr:`Action.logger`; the recorder and the log displays read it, ``docs/recording.md``).
ACTION_LOGGER = "temoto.action"


# results of on_run, as globals (a member lookup on the enum class costs several times more)
_R_TRUE = Result.TRUE
_R_FALSE = Result.FALSE
_R_STOPPED = Result.STOPPED
_R_ERROR = Result.ERROR

#: Shared by every action that holds no resource (never written: acquire makes its own dict).
_NOTHING_HELD: dict[str, Any] = {}
#: The parameter declarations of an unbound action: none.
_NO_PARAMS: Mapping[str, Parameter] = MappingProxyType({})


class Action(ABC):
    """Base class of every action plugin.

    Subclasses implement :meth:`on_run` and optionally the other ``on_*`` hooks. They are
    created by the engine with no arguments; configuration comes from the input parameters.
    ``__init__`` may be overridden (call ``super().__init__()``) but must not block.

    Attributes:
        blocking: Class attribute. True (the default): ``on_run`` may wait (sleep, wait for a
            device or a resource), so each run gets a worker thread. False: ``on_run`` never
            waits, and the engine runs it inline on the thread that evolves the graph (see the
            module docstring and ``docs/engine.md``).
    """

    #: Whether ``on_run`` may wait; ``False`` declares an inline action (read when a graph is
    #: planned, per class).
    blocking: ClassVar[bool] = True

    # Defaults live on the class: an instance stores only what the engine binds (see initialize),
    # so creating one per node costs no __init__ call of ours.
    _control: RunControl | None = None
    _log: deque[LogMessage] | None = None  # made by the first log() call
    _logger: logging.Logger | None = None
    _name = "Action"  # the class name until bound (set per subclass)
    _graph = ""
    _inputs = NO_INPUTS  # replaced by each run's own (_begin)
    _outputs = NO_OUTPUTS
    _input_params: Mapping[str, Parameter] = _NO_PARAMS
    _output_params: Mapping[str, Parameter] = _NO_PARAMS
    _registrar: Registrar | None = None
    _resources: dict[str, Resource[Any]] = _NOTHING_HELD  # own dict on first acquire

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._name = cls.__name__

    # ---- hooks: override these -------------------------------------------------------------

    def on_init(self) -> None:  # noqa: B027 - optional hook
        """Once per node, in a worker thread, before the first run. Default: nothing."""

    @abstractmethod
    def on_run(self) -> bool:
        """Do the action's work. Runs in a worker thread.

        Returns:
            True for the ``on_true`` result, False for ``on_false``.
        """

    def on_pause(self) -> None:  # noqa: B027 - optional hook
        """The graph is being paused. The helpers already block while paused."""

    def on_resume(self) -> None:  # noqa: B027 - optional hook
        """The graph resumed after a pause."""

    def on_stop(self) -> None:  # noqa: B027 - optional hook
        """A stop was requested; make ``on_run`` return soon (helpers already raise)."""

    def on_resource_status(self, update: StatusUpdate) -> None:  # noqa: B027 - optional hook
        """A resource this action acquired reported a status (runs in the reporter's thread).

        ERROR and FATAL also make the next helper call (``sleep``, ``wait_for``,
        ``wait_until_stopped``, ``check_resources``) raise ``ResourceBrokenError``.
        """

    # ---- engine binding (not for action authors) ---------------------------------------------

    @property
    def _client(self) -> str:
        """The client name this node's resources are requested under (``<graph>/<node>``)."""
        return f"{self._graph}/{self._name}"

    def _begin(self, values: dict[str, Any]) -> None:
        """Engine: a run starts with these input values (the dict is handed over, not copied)."""
        if values or self._input_params:
            self._inputs = Inputs.over(values, self._input_params)
        else:  # nothing to read: share the empty view (fewer objects for the collector)
            self._inputs = NO_INPUTS
        self._outputs = Outputs(self._output_params) if self._output_params else NO_OUTPUTS

    # ---- framework calls (the engine makes them; not overridden) -----------------------------

    def initialize(
        self,
        control: RunControl,
        name: str,
        graph: str,
        inputs: Mapping[str, Parameter],
        outputs: Mapping[str, Parameter],
        registrar: Registrar | None = None,
    ) -> None:
        """Bind this instance to its node, then call :meth:`on_init`. Framework call.

        Args:
            control: The node's stop and pause signals.
            name: The node's full name (``<Name>_<instance_id>``).
            graph: The graph run's name.
            inputs: The node's input parameter definitions.
            outputs: The node's output parameter definitions.
            registrar: Where :meth:`acquire` requests resources, if anywhere.

        Returns:
            None.

        Raises:
            Exception: Whatever ``on_init`` raises (the engine marks the node ERROR).
        """
        self._control = control
        self._name = name
        self._graph = graph
        self._input_params = inputs
        self._output_params = outputs
        if registrar is not None:
            self._registrar = registrar
        self.on_init()

    def run_once(
        self, values: dict[str, Any]
    ) -> tuple[Result, dict[str, Any], BaseException | None]:
        """One run of :meth:`on_run` with these input values. Framework call.

        The values dict is handed over, not copied. ``True``/``False`` become ``Result.TRUE``/
        ``Result.FALSE``; :class:`~temoto.errors.StopRequested` ``Result.STOPPED``; anything
        raised, or a return value that is not a bool (a ``TypeError``), ``Result.ERROR`` with an
        :class:`~temoto.errors.ActionError` naming the node and caused by the exception.

        Args:
            values: The run's input values, by name.

        Returns:
            ``(result, outputs, error)``: the outputs set during the run (also after a failure;
            a shared empty dict if none, never to be mutated) and the error or None.
        """
        if values or self._input_params or self._output_params:
            self._begin(values)  # else: the shared empty views it holds already
        error: BaseException | None = None
        try:
            ok = self.on_run()
            if ok is True:
                result = _R_TRUE
            elif ok is False:
                result = _R_FALSE
            else:
                raise TypeError(f"on_run() must return True or False, not {type(ok).__name__}")
        except StopRequested:
            result = _R_STOPPED
        except BaseException as err:
            result = _R_ERROR
            error = ActionError(f"{self._name} failed: {err}", graph=self._graph, node=self._name)
            error.__cause__ = err
        outputs = self._outputs
        return result, (NO_VALUES if outputs is NO_OUTPUTS else outputs.take()), error

    def log_snapshot(self) -> tuple[LogMessage, ...]:
        """The runtime log as it is now, newest first; safe while the action logs. Framework call.

        Returns:
            The messages (at most :data:`LOG_LENGTH`).
        """
        log = self._log
        # deque.copy() is one C call: safe while the action's thread appends
        return tuple(log.copy()) if log is not None else ()

    @property
    def holds_resources(self) -> bool:
        """Whether this node holds resources it acquired (framework read, cheap)."""
        return bool(self._resources)

    # ---- what actions call ------------------------------------------------------------------

    @property
    def name(self) -> str:
        """The node's full name (``<Name>_<instance_id>``)."""
        return self._name

    @property
    def graph_name(self) -> str:
        """The name of the graph run this node belongs to."""
        return self._graph

    @property
    def inputs(self) -> Inputs:
        """The input values of the current run."""
        return self._inputs

    @property
    def outputs(self) -> Outputs:
        """Where the current run writes its outputs (children receive them)."""
        return self._outputs

    @property
    def clock(self) -> Clock:
        """The engine's clock; measure durations with ``self.clock.monotonic()``."""
        return self._ctl.clock

    @property
    def logger(self) -> logging.Logger:
        """This node's logger (``temoto.action.<graph>.<node>``), made on first use."""
        if self._logger is None:
            self._logger = logging.getLogger(
                f"{ACTION_LOGGER}.{self._graph}.{self._name}" if self._graph else ACTION_LOGGER
            )
        return self._logger

    @property
    def _ctl(self) -> RunControl:
        if self._control is None:
            raise RuntimeError(
                f"{self._name} is not bound to an engine (create it through a graph)"
            )
        return self._control

    @property
    def stop_requested(self) -> bool:
        """Whether the engine asked this run to stop."""
        return self._ctl.stop

    @property
    def paused(self) -> bool:
        """Whether the graph is paused."""
        return self._ctl.paused

    @property
    def registrar(self) -> Registrar | None:
        """The engine's registrar (what manager clients use to find their manager), or None."""
        return self._registrar

    def acquire(
        self, server: str, request: Any, *, priority: int = 0, exclusive: bool = False
    ) -> Resource[Any]:
        """Request a resource from the engine's registrar, held for this node.

        Resources an action acquires are released automatically when its graph run ends or
        its node is removed (release earlier with :meth:`release`). Their failures reach
        :meth:`on_resource_status` and make the helpers raise ``ResourceBrokenError``.

        Args:
            server: The resource server (manager) name, e.g. ``"process"``.
            request: Its request object.
            priority: Higher pre-empts lower on exclusive resources.
            exclusive: Want the resource alone.

        Returns:
            The reference (``.response`` holds what the server returned).

        Raises:
            RuntimeError: If the engine has no registrar.
            ResourceError: If the resource cannot be had (see ``Registrar.call``).
        """
        if self._registrar is None:
            raise RuntimeError(f"{self._name}: this engine has no resource registrar")
        resource = self._registrar.call(
            server,
            request,
            client=self._client,
            priority=priority,
            exclusive=exclusive,
            on_status=self._resource_status,
        )
        if self._resources is _NOTHING_HELD:
            self._resources = {}
            if self._control is not None:
                self._control.acquired = True
        self._resources[resource.id] = resource
        return resource

    def release(self, resource: Resource[Any]) -> None:
        """Release a resource acquired with :meth:`acquire` before the graph ends.

        Args:
            resource: What :meth:`acquire` returned.

        Returns:
            None.

        Raises:
            ResourceError: If it was already released.
        """
        if self._registrar is None:
            raise RuntimeError(f"{self._name}: this engine has no resource registrar")
        if self._resources is not _NOTHING_HELD:
            self._resources.pop(resource.id, None)
        self._registrar.release(resource.id)

    def check_resources(self) -> None:
        """Raise if an acquired resource failed since the last check.

        Returns:
            None.

        Raises:
            ResourceBrokenError: For the oldest unreported failure.
        """
        ctl = self._ctl
        with ctl.cond:
            ctl.raise_broken()

    def _resource_status(self, update: StatusUpdate) -> None:
        try:
            self.on_resource_status(update)
        except Exception:
            self.logger.exception("on_resource_status raised")
        if update.status in (Status.ERROR, Status.FATAL) and self._control is not None:
            self._control.report_broken(update)

    def release_resources(self) -> int:
        """Release every resource this node holds (its graph ended, or it was removed).

        Framework call; the engine makes it on a worker. Resources already released by their
        owner or the registrar are skipped.

        Returns:
            How many were released.
        """
        held, self._resources = self._resources, _NOTHING_HELD
        if self._registrar is None:
            return 0
        count = 0
        for ref_id in reversed(list(held)):  # the reverse of acquisition order
            try:
                self._registrar.release(ref_id)
                count += 1
            except ResourceError:
                pass  # already released by its owner or the registrar
        return count

    def log(self, message: str) -> None:
        """Write to the action's runtime log (kept in feedback, newest first) and the logger.

        Args:
            message: The text.

        Returns:
            None.
        """
        stamp = int(self._ctl.clock.time() * 1000) if self._control is not None else 0
        if self._log is None:
            self._log = deque(maxlen=LOG_LENGTH)
            if self._control is not None:
                self._control.logged = True
        self._log.appendleft(LogMessage(stamp, str(message)))
        self.logger.info("%s", message)

    def sleep(self, seconds: float) -> None:
        """Sleep for ``seconds`` of clock time; while paused, wait for the resume too.

        Args:
            seconds: The duration.

        Returns:
            None.

        Raises:
            StopRequested: As soon as a stop is requested.
            ResourceBrokenError: If a resource this action acquired failed.
        """
        ctl = self._ctl
        deadline = ctl.clock.monotonic() + seconds
        with ctl.cond:
            while True:
                if ctl.stop:
                    raise StopRequested(self._name)
                ctl.raise_broken()
                remaining = deadline - ctl.clock.monotonic()
                if not ctl.paused and remaining <= 0:
                    return
                ctl.clock.wait(ctl.cond, None if ctl.paused else remaining)

    def wait_until_stopped(self, timeout: float | None = None) -> bool:
        """Block until a stop is requested or the timeout passes (pauses do not end it).

        Args:
            timeout: Clock seconds, or None to wait for the stop.

        Returns:
            True if a stop was requested, False on timeout.

        Raises:
            ResourceBrokenError: If a resource this action acquired failed.
        """
        ctl = self._ctl
        deadline = None if timeout is None else ctl.clock.monotonic() + timeout
        with ctl.cond:
            while not ctl.stop:
                ctl.raise_broken()
                if deadline is None:
                    ctl.clock.wait(ctl.cond, None)
                    continue
                remaining = deadline - ctl.clock.monotonic()
                if remaining <= 0:
                    return False
                ctl.clock.wait(ctl.cond, remaining)
            return True

    def wait_for(self, predicate: Callable[[], bool], timeout: float | None = None) -> bool:
        """Block until ``predicate()`` is true; re-checked whenever :meth:`wake` is called.

        Call :meth:`wake` from the thread that changes what the predicate reads (a
        subscription callback, a driver thread). No polling is done.

        Args:
            predicate: A cheap, thread-safe check.
            timeout: Clock seconds, or None to wait without limit.

        Returns:
            True when the predicate holds, False on timeout.

        Raises:
            StopRequested: As soon as a stop is requested.
            ResourceBrokenError: If a resource this action acquired failed.
        """
        ctl = self._ctl
        deadline = None if timeout is None else ctl.clock.monotonic() + timeout
        with ctl.cond:
            while True:
                if ctl.stop:
                    raise StopRequested(self._name)
                ctl.raise_broken()
                if not ctl.paused and predicate():
                    return True
                remaining = None if deadline is None else deadline - ctl.clock.monotonic()
                if remaining is not None and remaining <= 0 and not ctl.paused:
                    return False
                ctl.clock.wait(ctl.cond, None if ctl.paused else remaining)

    def wake(self) -> None:
        """Make :meth:`wait_for` re-check its predicate. Safe from any thread.

        Returns:
            None.
        """
        ctl = self._ctl
        with ctl.cond:
            ctl.cond.notify_all()


#: Value of an input that holds no data (re-exported for action authors).
NO_DATA = NO_VALUE
