"""Supervision of the other actors: watches, silences, ends and aborts; the link's threads.

Private to :mod:`temoto.fleet.actors`. :class:`Supervisor` keeps the watches of
:meth:`~FleetActorLink.watch` and reports to them an actor that falls silent for
``silence_s``, leaves, ends its run (END) or aborts it (LEAVE with a reason); it runs the
link's timer thread (``temoto-fleet-actors``: heartbeats, silences, repeated LEAVEs, expiry of
kept state) and its callback thread (``temoto-fleet-actors-calls``). It works on the link's
:class:`~temoto.fleet._actor_state.LinkState`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from temoto.core.remote import Cancel
from temoto.core.states import Result
from temoto.fleet._actor_state import (
    HANDSHAKE_CHANNEL,
    LEAVE,
    READY,
    LinkState,
    Phase,
    SessionKey,
    Watch,
    logger,
)
from temoto.fleet._handshake import Handshakes
from temoto.fleet.common import check_name

__all__ = ["Supervisor"]


class Supervisor:
    """The watches of one link, and its timer and callback threads.

    Args:
        state: The link's shared state (held, not copied: every part sees one table).
        handshakes: Builds the heartbeats and the repeated LEAVEs.
    """

    def __init__(self, state: LinkState, handshakes: Handshakes) -> None:
        self._st = state  # shared with the link's other parts, by reference
        self._handshakes = handshakes

    def watch(
        self,
        actors: Sequence[str],
        on_lost: Callable[[str, str], None],
        *,
        graph: str = "",
        session: str = "",
        on_end: Callable[[str, Result], None] | None = None,
        on_abort: Callable[[str, str], None] | None = None,
    ) -> Cancel:
        """See :meth:`FleetActorLink.watch`."""
        names = {check_name("an actor", a) for a in actors} - {self._st.actor}
        key = (graph, session) if graph or session else None
        with self._st.lock:
            self._st.check_open()
            run = self._st.runs.get(key) if key is not None else None
            watch = Watch(names, on_lost, self._st.core.now(), key, on_end, on_abort)
            self._st.watches.append(watch)
            if run is not None:
                for actor, result in sorted(run.ended_peers.items()):
                    self.report_end(watch, actor, result)
                for actor, reason in sorted(run.left_reasons.items()):
                    self.report_abort(watch, actor, reason)
            for actor in sorted(names & self._st.left):
                self.report_lost(watch, actor, "left")
            self._st.timer_wake.notify()

        def cancel() -> None:
            with self._st.lock:
                watch.active = False
                if watch in self._st.watches:
                    self._st.watches.remove(watch)
                    self._st.timer_wake.notify()

        return cancel

    def report_lost(self, watch: Watch, actor: str, reason: str) -> None:
        """A watched actor is lost: tell the watch (once per actor). Lock held."""
        if not watch.active or actor not in watch.actors or actor in watch.reported:
            return
        watch.reported.add(actor)
        self._st.core.count("lost")

        def call() -> None:
            with self._st.lock:
                if not watch.active:
                    return
            watch.on_lost(actor, reason)

        self._st.schedule(call)

    def report_end(self, watch: Watch, actor: str, result: str) -> None:
        """A watched peer's run finished with ``result``: stop watching it, tell. Lock held."""
        if not watch.active or actor not in watch.actors:
            return
        watch.actors.discard(actor)
        on_end = watch.on_end
        if on_end is None:
            return
        try:
            taken = Result(result)
        except ValueError:
            logger.warning(
                "actor %r: END of %r with unknown result %r", self._st.actor, actor, result
            )
            return

        def call() -> None:
            with self._st.lock:
                if not watch.active:
                    return
            on_end(actor, taken)

        self._st.schedule(call)

    def report_abort(self, watch: Watch, actor: str, reason: str) -> None:
        """A watched peer aborted the run with ``reason``. Lock held."""
        on_abort = watch.on_abort
        if on_abort is None:
            self.report_lost(watch, actor, "left")
            return
        if not watch.active or (actor, reason) in watch.aborts:
            return
        watch.aborts.add((actor, reason))
        self._st.core.count("lost")

        def call() -> None:
            with self._st.lock:
                if not watch.active:
                    return
            on_abort(actor, reason)

        self._st.schedule(call)

    def on_leave(self, actor: str, graph: str, session: str, reason: str = "") -> None:
        """A peer gave up a run (or, with no graph and session, left the fleet). Lock held."""
        fleet = not graph and not session
        if fleet:
            self._st.left.add(actor)
            runs = self._st.distinct_runs()
        else:
            ended = self._st.ended.get((graph, session))
            if ended is not None:
                ended.speaking.pop(actor, None)
            run = self._st.runs.get((graph, session))
            if run is None and reason and (graph, session) not in self._st.ended:
                # kept for a later watch
                run = self._st.new_run((graph, session), self._st.core.now())
            runs = [] if run is None else [run]
        lost = fleet
        for run in runs:
            run.left_peers.add(actor)
            if reason and not fleet:
                run.left_reasons[actor] = reason
            if run.phase is not Phase.JOINING:
                run.peers.pop(actor, None)  # kept: its JOIN no longer stands
            if not run.local or actor not in run.actors:
                continue
            if run.phase is Phase.JOINING:
                run.aborted = f"'{actor}' {'left the fleet' if fleet else 'gave up'}"
                self._st.changed.notify_all()
            elif run.phase is Phase.READY:
                lost = True
        why = "left the fleet" if fleet else "gave up the run"
        for out in self._st.outgoing.values():  # it will not acknowledge: do not wait for it
            if actor in out.waiting and (fleet or out.key == (graph, session)):
                out.aborted = f"'{actor}' {why}"
                out.lost = (actor, "left")
                self._st.changed.notify_all()
        for watch in self._st.watches:
            if reason and not fleet and watch.key == (graph, session):
                self.report_abort(watch, actor, reason)  # also once the run ended here
            elif lost:
                self.report_lost(watch, actor, "left")

    def on_end(self, actor: str, key: SessionKey, result: str = "") -> None:
        """A peer's run finished: stop waiting for it in that run, take its result. Lock held."""
        run = self._st.runs.get(key)
        ended = self._st.ended.get(key)
        if ended is not None:
            ended.speaking.pop(actor, None)  # it ended too: it needs no word from us
        if run is None and key not in self._st.ended:
            run = self._st.new_run(
                key, self._st.core.now()
            )  # kept for a watch of a run not started yet
        if run is not None:
            run.ended_peers.setdefault(actor, result)
        for out in self._st.outgoing.values():
            if out.key == key and actor in out.waiting:
                out.waiting.discard(actor)  # it needs nothing more of this run
                self._st.changed.notify_all()
        for watch in self._st.watches:
            if watch.key == key:
                self.report_end(watch, actor, result)

    def run_timer(self) -> None:
        """Heartbeats, silence checks, expiry of kept state."""
        while True:
            with self._st.lock:
                if self._st.core.closed:
                    return
                now = self._st.core.now()
                wake = math.inf
                ready = [r for r in self._st.distinct_runs() if r.local and r.phase is Phase.READY]
                graced = any(e.heard is not None for e in self._st.ended.values())
                msgs: list[Any] = []
                if ready or graced or self._st.watches:
                    if now >= self._st.next_heartbeat:
                        msgs = [
                            self._handshakes.heartbeat_msg(r)
                            if self._handshakes.all_ready(r)
                            else self._handshakes.ready_msg(r)
                            for r in ready
                        ]
                        if not msgs:
                            msgs.append(self._handshakes.handshake_msg(READY, "", "", (), None))
                        self._st.next_heartbeat = now + self._st.heartbeat_s
                    wake = self._st.next_heartbeat
                else:
                    self._st.next_heartbeat = now
                wake = min(wake, self.check_silences(now), self.expire(now))
                repeats, due = self.repeats(now)
                msgs += repeats
                wake = min(wake, due)
                if not msgs:
                    self._st.core.wait(
                        self._st.timer_wake, None if wake == math.inf else max(0.0, wake - now)
                    )
                    continue
            for msg in msgs:
                self._st.send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")

    def repeats(self, now: float) -> tuple[list[Any], float]:
        """The LEAVEs to say again, and when next to look. Lock held.

        Each is said every ``resend_s`` for ``silence_s`` after the abort: a peer that aborted
        the run too (settling there) no longer sends heartbeats of it to answer.
        """
        msgs: list[Any] = []
        wake = math.inf
        for key, ended in self._st.ended.items():
            if ended.decision is None or ended.decision[0] != LEAVE:
                continue  # an END is answered to the heartbeats of peers still in the run
            if now >= ended.decided + self._st.silence_s:
                continue
            if ended.out_key not in (None, key):
                continue  # the same run under its session's name: said under its run id
            if now >= ended.next_repeat:
                msgs.append(self._handshakes.decision_msg(key, ended.actors, ended.decision))
                ended.next_repeat = now + self._st.resend_s
            wake = min(wake, ended.next_repeat)
        return msgs, wake

    def check_silences(self, now: float) -> float:
        """Report silent watched actors; fail notifications waiting for silent actors.

        Returns when the next may fall silent. Lock held.
        """
        wake = math.inf
        for out in self._st.outgoing.values():
            if out.aborted is not None:
                continue
            for actor in sorted(out.waiting):
                due = max(self._st.heard_at.get(actor, -math.inf), out.started) + self._st.silence_s
                if now >= due:
                    out.aborted = f"'{actor}' was not heard for {self._st.silence_s:g} s"
                    out.lost = (actor, f"not heard for {self._st.silence_s:g} s")
                    self._st.changed.notify_all()
                    break
                wake = min(wake, due)
        for watch in self._st.watches:
            for actor in watch.actors - watch.reported:
                due = (
                    max(self._st.heard_at.get(actor, -math.inf), watch.started) + self._st.silence_s
                )
                if now >= due:
                    self.report_lost(watch, actor, f"not heard for {self._st.silence_s:g} s")
                else:
                    wake = min(wake, due)
        return wake

    def expire(self, now: float) -> float:
        """Drop ended runs after their grace and stray runs; when next to look. Lock held."""
        wake = math.inf
        for key, ended in list(self._st.ended.items()):
            if now >= ended.until:
                del self._st.ended[key]
            else:
                wake = min(wake, ended.until)
        for key, run in list(self._st.runs.items()):
            if not run.local:
                due = run.touched + self._st.stray_s
                if now >= due:
                    del self._st.runs[key]
                else:
                    wake = min(wake, due)
        return wake

    def run_calls(self) -> None:
        """Run the callbacks, in order."""
        while True:
            with self._st.lock:
                while not self._st.calls and not self._st.core.closed:
                    self._st.calls_ready.wait()
                if self._st.core.closed:
                    return
                call = self._st.calls.popleft()
            try:
                call()
            except Exception:
                with self._st.lock:
                    self._st.core.count("callback_errors")
                logger.exception("actor %r: a fleet callback raised", self._st.actor)
