"""Remote control of running instances: graph commands and live feedback over the fleet.

Upstream TeMoto drives its Action Engines through ROS topics (docs/design.md §4.5); here the same
commands travel as ``graph_command_t`` on ``TEMOTO_GRAPH_CMD``, addressed to target actors:

* :class:`GraphControlServer` runs in every instance. It carries out the commands that name its
  actor (start, stop, pause, resume, modify) on its :class:`~temoto.core.engine.ActionEngine`
  and answers each with a ``graph_command_reply_t`` on ``TEMOTO_GRAPH_REPLY``. It publishes a
  ``graph_feedback_t`` (the run's state and every node's state) on ``TEMOTO_GRAPH_FEEDBACK``
  when a run changes — at most every ``feedback_interval_s`` per run, so a busy graph costs a
  bounded number of messages — and every run it knows every ``feedback_period_s``, so a
  watcher that starts late sees everything within one period.
* :class:`GraphCommander` is the client: it sends a command and gathers the replies of every
  target, re-sending every ``resend_s`` until each target answered (the network may drop a
  datagram). A server answers a re-sent command (same ``request_id``) with the reply it gave,
  without running the command again; while the command still runs it stays silent.

Every message is authenticated by the :class:`~temoto.transport.link.FleetLink` (a host
without the fleet key cannot start a graph: its commands are dropped and counted). A message
that is well formed but meaningless (no targets, an unknown command) is counted and dropped; a
command that fails (no such graph, an invalid graph, a graph already running) is answered with
``ERROR`` and the engine's message. In a fleet with a roster, a command its sender may not give
on this robot (``graph.start`` ... ``graph.modify`` in the roster's ``permissions``,
docs/security.md) is answered with ``ERROR`` and the reason, logged at WARNING and counted as
``refused``.
"""

from __future__ import annotations

import collections
import itertools
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Final

from temoto.clock import Clock, MonotonicClock
from temoto.core.documents import graph_from_document
from temoto.core.engine import ActionEngine
from temoto.core.graph import UmrfGraph
from temoto.core.instrument import Instrument
from temoto.core.planning import graph_inputs_from_text
from temoto.core.states import GraphState, NodeState, Result
from temoto.errors import (
    FleetError,
    GraphNotFoundError,
    TemotoError,
    TransportError,
)
from temoto.fleet.common import IMPOSTOR, Closing, SpeakerCheck, check_clock, decode_or_count, new
from temoto.lcm_types import graph_command_reply_t, graph_command_t, graph_feedback_t, node_state_t
from temoto.transport import codec
from temoto.transport.auth import Opened
from temoto.transport.base import Subscription
from temoto.transport.link import FleetLink

__all__ = [
    "COMMANDS",
    "COMMAND_CHANNEL",
    "FEEDBACK_CHANNEL",
    "REPLY_CHANNEL",
    "CommandOutcome",
    "CommandReply",
    "GraphCommander",
    "GraphControlServer",
    "GraphFeedback",
]

logger = logging.getLogger(__name__)

#: Channel of ``graph_command_t``.
COMMAND_CHANNEL: Final = "TEMOTO_GRAPH_CMD"
#: Channel of ``graph_command_reply_t``.
REPLY_CHANNEL: Final = "TEMOTO_GRAPH_REPLY"
#: Channel of ``graph_feedback_t``.
FEEDBACK_CHANNEL: Final = "TEMOTO_GRAPH_FEEDBACK"

#: Command names and their ``graph_command_t.command`` codes.
COMMANDS: Final[Mapping[str, int]] = {
    "start": 1,
    "stop": 2,
    "pause": 3,
    "resume": 4,
    "modify": 5,
}
_NAMES: Final = {code: name for name, code in COMMANDS.items()}
_OK: Final = 1  # graph_command_reply_t.OK
_ERROR: Final = 2
_REPLIES_KEPT: Final = 512  # answers kept for re-sent commands
_ENDED_KEPT: Final = 64  # ended runs still included in the periodic feedback
_GONE: Final = GraphState.FINISHED
_ENDED_STATES: Final = frozenset(
    (GraphState.FINISHED, GraphState.STOPPED, GraphState.ERROR, GraphState.HALTED)
)


# ===================================================================================== server


class _Changes(Instrument):
    """Marks runs changed (called with the engine's lock held: only sets flags)."""

    def __init__(self, wake: threading.Condition) -> None:
        self._wake = wake
        self.changed: set[str] = set()

    def _mark(self, graph: str) -> None:
        with self._wake:
            self.changed.add(graph)
            self._wake.notify()

    def graph_started(self, graph: str, t: float) -> None:
        """A run started."""
        self._mark(graph)

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """A node changed."""
        self._mark(graph)

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """A run ended."""
        self._mark(graph)


class GraphControlServer(Closing):
    """Carries out graph commands addressed to an engine's actor; publishes its feedback.

    Args:
        engine: The instance's engine; its ``actor`` is the name commands must target.
        link: The authenticated fleet link.
        feedback_interval_s: The shortest time between two feedbacks of one run.
        feedback_period_s: Every run known is published this often, changed or not.
        stop_timeout: Seconds a ``stop`` command waits for the actions to stop.
        workers: Commands carried out at once (a start waits for the handshake of a shared
            graph; a stop waits for the actions).
        clock: Where time is read (default: :class:`~temoto.clock.MonotonicClock`).

    Raises:
        ValueError: The engine has no actor name, or a period is not positive.
        TypeError: If ``clock`` is not a :class:`~temoto.clock.Clock`.
    """

    #: The counters of :attr:`stats`.
    STATS: Final = (
        "commands",  # commands for this actor taken (re-sends not included)
        "resent",  # re-sent commands answered from the kept reply
        "ignored",  # commands for other actors
        "failed",  # commands answered with ERROR
        "refused",  # of those, refused by the fleet policy (docs/security.md)
        "feedback_sent",
        "decode_errors",
        "unexpected",  # well-formed but meaningless: wrong type, no targets, unknown command
        "send_errors",
    )

    def __init__(
        self,
        engine: ActionEngine,
        link: FleetLink,
        *,
        feedback_interval_s: float = 0.05,
        feedback_period_s: float = 1.0,
        stop_timeout: float | None = 10.0,
        workers: int = 4,
        clock: Clock | None = None,
    ) -> None:
        if not engine.actor:
            raise ValueError("the engine needs an actor name to take remote commands")
        if not feedback_interval_s > 0 or not feedback_period_s > 0:
            raise ValueError("feedback_interval_s and feedback_period_s must be positive")
        self.engine = engine
        self.actor = engine.actor
        self.feedback_interval_s = float(feedback_interval_s)
        self.feedback_period_s = float(feedback_period_s)
        self.stop_timeout = stop_timeout
        self._link = link
        self._time: Clock = MonotonicClock() if clock is None else check_clock("clock", clock)
        self._clock = self._time.monotonic
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(self.STATS, 0)
        self._replies: collections.OrderedDict[str, Any] = collections.OrderedDict()
        self._running: set[str] = set()
        self._closed = False
        self._wake = threading.Condition()
        self._changes = _Changes(self._wake)
        self._known: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._last_sent: dict[str, float] = {}
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="temoto-graph-command")
        self._feeder = threading.Thread(
            target=self._feed, name="temoto-graph-feedback", daemon=True
        )
        engine.add_instrument(self._changes)
        self._feeder.start()
        self._subscription: Subscription | None = None
        try:
            self._subscription = link.listen(COMMAND_CHANNEL, self._on_command, queue_capacity=256)
        except BaseException:
            self.close()
            raise

    @property
    def stats(self) -> dict[str, int]:
        """Counters (see :attr:`STATS`)."""
        with self._lock:
            return dict(self._counts)

    def close(self) -> None:
        """Stop taking commands and publishing feedback; wait for running commands."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._subscription is not None:
            self._subscription.unsubscribe()
        with self._wake:
            self._wake.notify_all()
        self._feeder.join(5.0)
        self._pool.shutdown(wait=True, cancel_futures=True)

    # ---- commands --------------------------------------------------------------------------

    def _on_command(self, opened: Opened) -> None:
        """Transport thread: take a command for this actor, or answer a re-sent one."""
        msg = decode_or_count(opened, ("graph_command_t",), self._counts, self._lock)
        if msg is None:
            return
        targets = list(msg.targets)
        with self._lock:
            if self._closed:
                return
            if not targets or not msg.request_id or msg.command not in _NAMES:
                self._counts["unexpected"] += 1
                return
            if self.actor not in targets:
                self._counts["ignored"] += 1
                return
            kept = self._replies.get(msg.request_id)
            if kept is None and msg.request_id in self._running:
                return  # still being carried out: the reply comes when it is done
            if kept is None:
                self._running.add(msg.request_id)
                self._counts["commands"] += 1
            else:
                self._counts["resent"] += 1
        if kept is not None:
            self._send_reply(kept)
            return
        try:
            self._pool.submit(self._carry_out, msg, opened.sender)
        except RuntimeError:  # closed meanwhile
            with self._lock:
                self._running.discard(msg.request_id)

    def _carry_out(self, msg: Any, sender: str) -> None:
        """Worker thread: run one command on the engine and answer it."""
        reply = new(graph_command_reply_t)
        reply.request_id, reply.actor = msg.request_id, self.actor
        reply.graph, reply.session = msg.graph, msg.session
        reply.code, reply.result, reply.message, reply.errors = _OK, "", "", "[]"
        refusal = self._link.auth.refusal(sender, f"graph.{_NAMES[msg.command]}", self.actor)
        if refusal is not None:  # the fleet policy (docs/security.md): answered and logged
            reply.code, reply.message = _ERROR, refusal
            reply.errors = json.dumps([f"PermissionError: {refusal}"])
            logger.warning(
                "actor %r: refused graph command %s from %r (%s): %s",
                self.actor,
                _NAMES[msg.command],
                sender,
                msg.request_id,
                refusal,
            )
        try:
            if refusal is None:
                reply.graph, reply.session, reply.result, reply.message = self._execute(msg)
        except (TemotoError, ValueError, TypeError, KeyError, TimeoutError) as err:
            text = err.args[0] if isinstance(err, KeyError) and err.args else str(err)
            reply.code, reply.message = _ERROR, text or type(err).__name__
            reply.errors = json.dumps([f"{type(err).__name__}: {err}"])
            logger.warning(
                "graph command %s from %s failed: %s", _NAMES[msg.command], msg.request_id, err
            )
        except Exception as err:  # a bug: answer it rather than leave the commander waiting
            logger.exception("graph command %s failed", msg.request_id)
            reply.code, reply.message = _ERROR, f"internal error: {err!r}"
            reply.errors = json.dumps([repr(err)])
        with self._lock:
            self._running.discard(msg.request_id)
            self._replies[msg.request_id] = reply
            while len(self._replies) > _REPLIES_KEPT:
                self._replies.popitem(last=False)
            if reply.code == _ERROR:
                self._counts["failed"] += 1
            if refusal is not None:
                self._counts["refused"] += 1
        self._send_reply(reply)

    def _execute(self, msg: Any) -> tuple[str, str, str, str]:
        """Run a command: (graph, session, result, message) for the reply; raises on failure."""
        command = _NAMES[msg.command]
        engine = self.engine
        model = _graph_of(msg.graph_json) if msg.graph_json else None
        if command == "start":
            graph: str | UmrfGraph = model if model is not None else msg.graph
            if not graph:
                raise ValueError("start: name an indexed graph or send its UMRF JSON")
            if model is None:
                model = engine.graphs.get(msg.graph)
            params = graph_inputs_from_text(model, _params_of(msg.params))
            run = engine.start(model, params, name=msg.session or None)
            return model.name, run, "", f"started '{run}'"
        run = msg.session or msg.graph or (model.name if model is not None else "")
        if not run:
            raise ValueError(f"{command}: name the graph or the session")
        if command == "stop":
            result = engine.stop(run, timeout=self.stop_timeout)
            return msg.graph, run, result.value, f"stopped '{run}'"
        if command == "pause":
            engine.pause(run)
            return msg.graph, run, "", f"paused '{run}'"
        if command == "resume":
            engine.resume(run, msg.continue_from or None)
            return msg.graph, run, "", f"resumed '{run}'"
        if model is None:
            raise ValueError("modify: send the new graph's UMRF JSON")
        engine.modify(run, model, msg.continue_from or None)
        return model.name, run, "", f"modified '{run}'"

    def _send_reply(self, reply: Any) -> None:
        self._send(REPLY_CHANNEL, reply)

    def _send(self, channel: str, msg: Any) -> bool:
        try:
            self._link.send(channel, *codec.encode(msg))
        except (TransportError, ValueError) as err:
            with self._lock:
                self._counts["send_errors"] += 1
            logger.warning("actor %r: cannot send on %s: %s", self.actor, channel, err)
            return False
        return True

    # ---- feedback --------------------------------------------------------------------------

    def _feed(self) -> None:
        """Feedback thread: publish changed runs (rate-limited) and every run periodically."""
        next_all = self._clock()
        while True:
            with self._wake:
                while True:
                    if self._closed:
                        return
                    now = self._clock()
                    due = self._due(now)
                    if due or now >= next_all:
                        break
                    waits = [next_all - now]
                    waits += [
                        self._last_sent.get(g, -1e9) + self.feedback_interval_s - now
                        for g in self._changes.changed
                    ]
                    self._time.wait(self._wake, max(0.001, min(waits)))
                if now >= next_all:
                    due = set(self._known) | self._changes.changed
                    next_all = now + self.feedback_period_s
                self._changes.changed -= due
                for graph in due:
                    self._last_sent[graph] = now
            for graph in sorted(due):
                self._publish(graph)

    def _due(self, now: float) -> set[str]:
        """Changed runs whose last feedback is old enough. ``_wake`` held."""
        return {
            g
            for g in self._changes.changed
            if now - self._last_sent.get(g, -1e9) >= self.feedback_interval_s
        }

    def _publish(self, graph: str) -> None:
        """Send the feedback of one run (forgotten when the engine no longer knows it)."""
        try:
            nodes = self.engine.node_states(graph)
            outcome = self.engine.outcome(graph)
        except GraphNotFoundError:
            with self._wake:
                self._known.pop(graph, None)
                self._last_sent.pop(graph, None)
            return
        states = self.engine.running_graphs() if len(self._known) >= _ENDED_KEPT else {}
        with self._wake:  # never call the engine with _wake held: its instrument takes _wake
            self._known[graph] = None
            self._known.move_to_end(graph)
            ended = [g for g in self._known if states.get(g, _GONE) in _ENDED_STATES]
            for old in ended[: max(0, len(self._known) - _ENDED_KEPT)]:
                del self._known[old]
        msg = new(graph_feedback_t)
        msg.actor, msg.graph, msg.session = self.actor, graph, graph
        msg.state = outcome.state.value
        msg.result = outcome.result.value if outcome.result is not None else ""
        msg.nodes = []
        for name, state in nodes.items():
            node = new(node_state_t)
            node.name, node.state, node.result = name, state.value, ""
            msg.nodes.append(node)
        msg.nodes_count = len(msg.nodes)
        if self._send(FEEDBACK_CHANNEL, msg):
            with self._lock:
                self._counts["feedback_sent"] += 1


def _graph_of(text: str) -> UmrfGraph:
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"the graph is not JSON: {err}") from None
    return graph_from_document(raw)


def _params_of(text: str) -> dict[str, str]:
    if not text:
        return {}
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"the parameters are not JSON: {err}") from None
    if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
        raise ValueError("the parameters must be a JSON object of strings")
    return raw


# ===================================================================================== client


@dataclass(frozen=True, slots=True)
class CommandReply:
    """One target's answer to a graph command.

    Attributes:
        actor: The target that answered.
        ok: Whether it carried the command out.
        graph: The graph's name.
        session: The run's name there.
        result: The run's result after a ``stop`` (``on_stopped``, ...), else empty.
        message: What happened, or why it failed.
        errors: The errors behind a failure.
    """

    actor: str
    ok: bool
    graph: str
    session: str
    result: str
    message: str
    errors: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """The answers to one command.

    Attributes:
        command: The command's name.
        replies: The answers, by target.
        missing: Targets that did not answer in time.
    """

    command: str
    replies: Mapping[str, CommandReply]
    missing: tuple[str, ...]

    @property
    def ok(self) -> bool:
        """Every target answered and carried the command out."""
        return not self.missing and all(r.ok for r in self.replies.values())


@dataclass(frozen=True, slots=True)
class GraphFeedback:
    """The state of one run on one actor, as published by its instance.

    Attributes:
        actor: The instance's actor.
        graph: The run's name.
        state: The run's state (``RUNNING``, ``FINISHED``, ...).
        result: Its result once ended, else empty.
        nodes: ``(node, state)`` pairs, sorted by node name.
    """

    actor: str
    graph: str
    state: str
    result: str
    nodes: tuple[tuple[str, str], ...]


class GraphCommander(Closing):
    """Sends graph commands to instances and watches their feedback.

    Args:
        link: The authenticated fleet link (its sender id names this commander).
        resend_s: A command is re-sent this often until every target answered.
        clock: Where resends and command timeouts are timed (default: the monotonic clock);
            a :class:`~temoto.clock.ManualClock` makes them virtual in tests and simulations.

    Raises:
        ValueError: ``resend_s`` is not positive.
        TypeError: ``clock`` is not a :class:`~temoto.clock.Clock`.
    """

    def __init__(
        self, link: FleetLink, *, resend_s: float = 0.25, clock: Clock | None = None
    ) -> None:
        if not resend_s > 0:
            raise ValueError("resend_s must be positive")
        self.resend_s = float(resend_s)
        self._time: Clock = MonotonicClock() if clock is None else check_clock("clock", clock)
        self._link = link
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._pending: dict[str, dict[str, CommandReply]] = {}
        self._watchers: list[Callable[[GraphFeedback], None]] = []
        self._ids = itertools.count(1)
        self._prefix = f"{socket.gethostname()}/{os.getpid()}/{time.time_ns()}"
        self._stats = {"decode_errors": 0, "unexpected": 0, IMPOSTOR: 0}
        self._speaks_as = SpeakerCheck("graph commander")
        self._closed = False
        self._subs = [
            link.listen(REPLY_CHANNEL, self._on_reply),
            link.listen(FEEDBACK_CHANNEL, self._on_feedback),
        ]

    def close(self) -> None:
        """Stop listening; waiting commands fail."""
        with self._lock:
            self._closed = True
            self._changed.notify_all()
        for sub in self._subs:
            sub.unsubscribe()

    def command(
        self,
        command: str,
        targets: Iterable[str],
        *,
        graph: str = "",
        session: str = "",
        graph_json: Mapping[str, Any] | None = None,
        params: Mapping[str, str] | None = None,
        continue_from: str = "",
        timeout: float = 10.0,
    ) -> CommandOutcome:
        """Send a command to ``targets`` and wait for each one's answer.

        Args:
            command: ``start``, ``stop``, ``pause``, ``resume`` or ``modify``.
            targets: The actors that must carry it out.
            graph: The graph's name (an indexed graph to start, or the run to control).
            session: The run's name when it differs from the graph's.
            graph_json: A UMRF graph document to start, or the new graph of a ``modify``.
            params: Graph inputs as text, by name (converted by the graph's declared types).
            continue_from: Where ``resume`` / ``modify`` continue (an action's full name).
            timeout: Seconds to wait for every answer.

        Returns:
            The answers, and the targets that did not answer.

        Raises:
            ValueError: An unknown command, no targets, or nothing to name the graph.
            FleetError: The commander is closed or cannot send.
        """
        code = COMMANDS.get(command)
        if code is None:
            raise ValueError(f"unknown command {command!r} (known: {', '.join(COMMANDS)})")
        wanted = sorted(set(targets))
        if not wanted or not all(isinstance(t, str) and t for t in wanted):
            raise ValueError("name at least one target actor")
        if graph_json is not None and not graph:
            graph = str(graph_json.get("graph_name", ""))
        if not (graph or session):
            raise ValueError(f"{command}: name the graph")
        msg = new(graph_command_t)
        msg.request_id = f"{self._prefix}/{next(self._ids)}"
        msg.command, msg.targets, msg.targets_count = code, wanted, len(wanted)
        msg.graph, msg.session, msg.continue_from = graph, session, continue_from
        msg.graph_json = json.dumps(graph_json) if graph_json is not None else ""
        msg.params = json.dumps(dict(params)) if params else ""
        now = self._time.monotonic
        deadline = now() + timeout
        with self._lock:
            if self._closed:
                raise FleetError("the commander is closed")
            got = self._pending[msg.request_id] = {}
        try:
            while True:
                try:
                    self._link.send(COMMAND_CHANNEL, *codec.encode(msg))
                except (TransportError, ValueError) as err:
                    raise FleetError(f"cannot send the command: {err}") from err
                next_send = now() + self.resend_s
                with self._lock:
                    while len(got) < len(wanted) and not self._closed:
                        t = now()
                        if t >= deadline or t >= next_send:
                            break
                        self._time.wait(self._changed, min(deadline, next_send) - t)
                    if self._closed:
                        raise FleetError("the commander is closed")
                    if len(got) >= len(wanted) or now() >= deadline:
                        missing = tuple(t for t in wanted if t not in got)
                        return CommandOutcome(command, dict(got), missing)
        finally:
            with self._lock:
                self._pending.pop(msg.request_id, None)

    def watch(self, on_feedback: Callable[[GraphFeedback], None]) -> Callable[[], None]:
        """Call ``on_feedback`` for every feedback heard (on the transport's thread).

        Args:
            on_feedback: The callback; keep it short.

        Returns:
            A function that stops the watch.
        """
        with self._lock:
            self._watchers.append(on_feedback)

        def cancel() -> None:
            with self._lock:
                if on_feedback in self._watchers:
                    self._watchers.remove(on_feedback)

        return cancel

    @property
    def stats(self) -> dict[str, int]:
        """Dropped messages: ``decode_errors``, ``unexpected``, ``impostor``.

        ``impostor``: replies and feedback naming another actor than their authenticated sender
        (docs/security.md).
        """
        with self._lock:
            return dict(self._stats)

    def _on_reply(self, opened: Opened) -> None:
        msg = decode_or_count(opened, ("graph_command_reply_t",), self._stats, self._lock)
        if msg is None or not self._speaks_as(opened, msg.actor, "actor", self._stats, self._lock):
            return
        try:
            errors = tuple(str(e) for e in json.loads(msg.errors or "[]"))
        except (json.JSONDecodeError, TypeError):
            errors = (msg.errors,)
        reply = CommandReply(
            msg.actor,
            msg.code == _OK,
            msg.graph,
            msg.session,
            msg.result,
            msg.message,
            errors,
        )
        with self._lock:
            got = self._pending.get(msg.request_id)
            if got is None or not msg.actor:
                return  # an answer to another commander, or a late one
            got[msg.actor] = reply
            self._changed.notify_all()

    def _on_feedback(self, opened: Opened) -> None:
        msg = decode_or_count(opened, ("graph_feedback_t",), self._stats, self._lock)
        if msg is None or not self._speaks_as(opened, msg.actor, "actor", self._stats, self._lock):
            return
        feedback = GraphFeedback(
            msg.actor,
            msg.graph,
            msg.state,
            msg.result,
            tuple((n.name, n.state) for n in msg.nodes),
        )
        with self._lock:
            watchers = list(self._watchers)
        for watcher in watchers:
            try:
                watcher(feedback)
            except Exception:
                logger.exception("a feedback watcher raised")
