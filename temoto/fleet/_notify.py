"""The notification exchange: the end of an action, told to the other actors of its run.

Private to :mod:`temoto.fleet.actors`, whose module docstring describes the protocol
(``TEMOTO_NOTIFY`` and each actor's ``TEMOTO_ACK_<actor>``). :class:`Notices` sends a
notification until every other participant acknowledged it (:meth:`~FleetActorLink.notify`),
acknowledges and takes (once) the notifications of others, and hands each to the oldest
:meth:`~FleetActorLink.expect` waiting for it. It works on the link's
:class:`~temoto.fleet._actor_state.LinkState`.
"""

from __future__ import annotations

import collections
import itertools
import json
import time
from collections.abc import Mapping, Sequence
from typing import Any

from temoto.core.remote import ActorLostError, Cancel, RemoteResult
from temoto.core.states import Result
from temoto.errors import FleetError
from temoto.fleet._actor_state import (
    MAX_BACKOFF,
    NOTIFY_CHANNEL,
    LinkState,
    NodeKey,
    Notice,
    Outgoing,
    Run,
    SessionKey,
    Waiter,
    ack_channel,
    logger,
    quoted,
)
from temoto.fleet.common import check_name, check_seconds, new
from temoto.lcm_types import action_ack_t, action_notification_t
from temoto.transport.auth import Opened

__all__ = ["Notices"]


class Notices:
    """The notifications one link sends, acknowledges and delivers.

    Args:
        state: The link's shared state (held, not copied: every part sees one table).
    """

    def __init__(self, state: LinkState) -> None:
        self._st = state  # shared with the link's other parts, by reference
        self._ids = itertools.count(1)
        self._boot = f"{round(state.core.wall() * 1000):x}"  # keeps ids unique across restarts

    def notify(
        self,
        graph: str,
        session: str,
        action: str,
        result: Result,
        outputs: Mapping[str, Any],
        actors: Sequence[str],
        timeout: float,
    ) -> None:
        """See :meth:`FleetActorLink.notify`."""
        check_name("graph", graph)
        check_name("session", session)
        check_name("action", action)
        timeout = check_seconds("timeout", timeout, zero=True)
        if not isinstance(result, Result):
            raise ValueError(f"result must be a Result, got {result!r}")
        others = {check_name("an actor", a) for a in actors} - {self._st.actor}
        try:
            text = json.dumps(dict(outputs), sort_keys=True, separators=(",", ":"))
        except (TypeError, ValueError, RecursionError) as err:
            raise FleetError(f"the outputs of {action} are not JSON-ready: {err}") from err
        if not outputs:
            text = ""
        key = (graph, session)
        with self._st.lock:
            run = self._st.runs.get(key)
            left: set[str] = set()
            if run is not None:
                others -= set(run.ended_peers)  # finished there: they need nothing more
                left = run.left_peers
            gone = sorted(a for a in others if a in left or self._st.gone(a, self._st.core.now()))
        if gone:
            why = "left" if gone[0] in left else self._st.why_gone(gone[0])
            raise ActorLostError(
                f"{action} ({result.value}) of graph '{graph}' session '{session}': "
                + ", ".join(f"actor '{a}' was lost ({self._st.why_gone(a)})" for a in gone),
                actor=gone[0],
                why=why,
            )
        if not others:
            return
        msg = new(action_notification_t)
        msg.graph, msg.session, msg.action, msg.actor = graph, session, action, self._st.actor
        msg.result, msg.outputs = result.value, text
        with self._st.lock:
            self._st.check_open()
            serial = f"{self._boot}.{next(self._ids)}"
            msg.notification_id = f"{self._st.actor}/{graph}/{session}/{action}/{serial}"
            out = Outgoing(key, set(others), self._st.core.now())
            self._st.outgoing[msg.notification_id] = out
            self._st.timer_wake.notify()  # it watches the silence of the actors waited for
        deadline = self._st.core.now() + timeout
        period = self._st.resend_s  # doubles with every copy (to MAX_BACKOFF * resend_s)
        waiting = len(out.waiting)
        try:
            while True:
                self._st.send(NOTIFY_CHANNEL, msg, "notifications_sent")
                next_send = self._st.core.now() + period
                with self._st.lock:
                    while out.waiting:
                        if self._st.core.closed:
                            raise FleetError("the fleet link is closed")
                        if out.aborted is not None:
                            text = (
                                f"{action} ({result.value}) of graph '{graph}' session "
                                f"'{session}': {out.aborted} before {quoted(out.waiting)} "
                                "acknowledged it"
                            )
                            if out.lost is not None:
                                raise ActorLostError(text, actor=out.lost[0], why=out.lost[1])
                            raise FleetError(text)
                        now = self._st.core.now()
                        if now >= deadline:
                            raise FleetError(
                                f"{action} ({result.value}) of graph '{graph}' session "
                                f"'{session}' was not acknowledged by {quoted(out.waiting)} "
                                f"within {timeout:g} s"
                            )
                        if now >= next_send:
                            if len(out.waiting) < waiting:
                                # acknowledgements still coming in (a loaded fleet answers
                                # slowly): no copy yet, look again a resend_s later
                                waiting = len(out.waiting)
                                period = self._st.resend_s
                                next_send = now + period
                                continue
                            # a period without any acknowledgement: send again, later next time
                            period = min(period * 2, MAX_BACKOFF * self._st.resend_s)
                            break
                        self._st.core.wait(self._st.changed, min(next_send, deadline) - now)
                    else:
                        return
        finally:
            with self._st.lock:
                self._st.outgoing.pop(msg.notification_id, None)

    def expect(
        self, graph: str, session: str, action: str, actor: str, on_result: RemoteResult
    ) -> Cancel:
        """See :meth:`FleetActorLink.expect`."""
        key = (check_name("graph", graph), check_name("session", session))
        node = (check_name("action", action), check_name("actor", actor))
        with self._st.lock:
            self._st.check_open()
            run = self._st.runs.get(key)
            if run is None:
                run = self._st.new_run(key, self._st.core.now())
            run.local = True
            waiter = Waiter(run, node, on_result)
            pending = run.pending.get(node)
            if pending:
                notice = pending.popleft()
                if not pending:
                    del run.pending[node]
                self.schedule_delivery(waiter, notice)
            else:
                run.waiters.setdefault(node, collections.deque()).append(waiter)

        def cancel() -> None:
            with self._st.lock:
                waiter.active = False
                waiters = run.waiters.get(node)
                if waiters is not None and waiter in waiters:
                    waiters.remove(waiter)
                    if not waiters:
                        del run.waiters[node]

        return cancel

    def on_ack(self, opened: Opened) -> None:
        """An acknowledgement on this actor's :func:`ack_channel`."""
        msg = self._st.decode(opened, ("action_ack_t",))
        if msg is None:
            return
        actor: str = msg.actor
        if actor and not self._st.core.speaks_as(opened, actor, "actor"):
            return  # a member acknowledging in another's name (docs/security.md)
        with self._st.lock:
            if self._st.core.closed or not actor or actor == self._st.actor:
                return
            self._st.core.count("acks_received")
            self._st.heard_at[actor] = self._st.core.now()
            out = self._st.outgoing.get(msg.notification_id)
            if out is not None and actor in out.waiting:
                out.waiting.discard(actor)
                if not out.waiting:
                    self._st.changed.notify_all()

    def on_notify(self, opened: Opened) -> None:
        """A notification on ``TEMOTO_NOTIFY`` (the transport's thread): take it, acknowledge it."""
        msg = self._st.decode(opened, ("action_notification_t",))
        if msg is None:
            return
        actor: str = msg.actor
        if actor and not self._st.core.speaks_as(opened, actor, "actor"):
            return  # a member notifying in another's name (docs/security.md)
        with self._st.lock:
            if self._st.core.closed:
                return
            if not actor or actor == self._st.actor or not msg.notification_id:
                self._st.core.count("unexpected")
                return
            self._st.core.count("notifications_received")
            # Taken (its delivery queued) before the acknowledgement leaves: the sender's END,
            # which may follow the acknowledgement at once, is then handled after it.
            self.take(msg)
        ack = new(action_ack_t)
        ack.notification_id, ack.graph, ack.session = msg.notification_id, msg.graph, msg.session
        ack.actor = self._st.actor
        self._st.send_quietly(ack_channel(actor), ack, "acks_sent")

    def take(self, msg: Any) -> None:
        """Store or deliver a notification unless it is a duplicate. Lock held."""
        if self._st.core.closed:
            return
        now = self._st.core.now()
        self._st.heard_at[msg.actor] = now
        key: SessionKey = (msg.graph, msg.session)
        nid: str = msg.notification_id
        ended = self._st.ended.get(key)
        if ended is not None and ended.decision is not None:
            # it still waits for our acknowledgement of a run that ended here: an earlier one
            # may not have reached it (real time: see FleetActorLink._linger)
            ended.speaking[msg.actor] = time.monotonic()
        run = self._st.runs.get(key)
        if (run is not None and nid in run.seen) or (ended is not None and nid in ended.seen):
            self._st.core.count("duplicates")
            return
        if run is None:
            run = self._st.new_run(key, now)
        run.touched = now
        run.seen.add(nid)
        self.route(run, (msg.action, msg.actor), self.parse(msg))

    def parse(self, msg: Any) -> Notice:
        """Turn a notification into a notice; a bad result or outputs becomes an ERROR."""
        where = f"notification {msg.notification_id!r}"
        try:
            result = Result(msg.result)
        except ValueError:
            logger.warning("%s: unknown result %r, taken as on_error", where, msg.result)
            result = Result.ERROR
        outputs: Any = {}
        if msg.outputs:
            try:
                outputs = json.loads(msg.outputs)
            except (ValueError, RecursionError) as err:
                outputs = None
                logger.warning("%s: the outputs are not JSON (%s), taken as on_error", where, err)
            if not isinstance(outputs, dict):
                if outputs is not None:
                    logger.warning("%s: the outputs are not an object, taken as on_error", where)
                result, outputs = Result.ERROR, {}
        return Notice(msg.notification_id, result, outputs)

    def route(self, run: Run, node: NodeKey, notice: Notice, *, front: bool = False) -> None:
        """Give a notice to the oldest waiter of ``node``, or keep it for the next one."""
        waiters = run.waiters.get(node)
        while waiters:
            waiter = waiters.popleft()
            if not waiters:
                del run.waiters[node]
            if waiter.active:
                self.schedule_delivery(waiter, notice)
                return
        pending = run.pending.setdefault(node, collections.deque())
        if front:
            pending.appendleft(notice)
        else:
            pending.append(notice)

    def schedule_delivery(self, waiter: Waiter, notice: Notice) -> None:
        """Queue the delivery of a notice to a waiter (a cancelled one passes it on). Lock held."""

        def deliver() -> None:
            with self._st.lock:
                if not waiter.active:  # cancelled meanwhile: keep the notice for the next
                    run = waiter.run
                    if self._st.runs.get((run.graph, run.session)) is run:
                        self.route(run, waiter.key, notice, front=True)
                    return
                waiter.active = False
            waiter.on_result(notice.result, notice.outputs)

        self._st.schedule(deliver)
