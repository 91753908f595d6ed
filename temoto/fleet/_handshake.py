"""The N-to-N handshake of a shared run (thesis Algorithm 3): JOIN, READY, and their words.

Private to :mod:`temoto.fleet.actors`, whose module docstring describes the protocol
(``TEMOTO_HANDSHAKE``). :class:`Handshakes` runs :meth:`~FleetActorLink.handshake` (the JOIN
resends and the wait until every ordered pair of participants has heard each other), records
the JOINs and READYs of peers, agrees on the run id, and builds every ``handshake_t`` the link
sends (JOIN, READY, the heartbeats, END and LEAVE). It works on the link's
:class:`~temoto.fleet._actor_state.LinkState`.
"""

from __future__ import annotations

import collections
import math
import secrets
import struct
import time
from collections.abc import Mapping, Sequence
from typing import Any

from temoto.errors import FleetError, StateError
from temoto.fleet._actor_state import (
    HANDSHAKE_CHANNEL,
    JOIN,
    LEAVE,
    MAX_BACKOFF,
    READY,
    Ended,
    LinkState,
    Peer,
    Phase,
    Run,
    SessionKey,
    actors_json,
    logger,
    quoted,
)
from temoto.fleet.common import check_name, check_seconds, new
from temoto.lcm_types import handshake_t

__all__ = ["Handshakes"]

# A JOIN that answers newly heard peers waits this share of resend_s for more of them, so a
# large fleet that starts at once exchanges a few JOINs per actor, not one per pair; READY
# answers to late JOINs are as rare.
_ANSWER_WINDOW = 0.25
# ... except the first JOINs of a handshake, which answer at once: in a fleet of up to
# _ACTORS_PER_PERIOD every newly heard peer is answered at once (each actor sends at most one
# JOIN per peer), in a larger one the first _ANSWERS_AT_ONCE. With only those 3 whatever the
# fleet, the fourth peer an actor heard (in a handshake of 5, the one that started last) would
# wait for the resend period.
_ANSWERS_AT_ONCE = 3
# A handshake of more actors than this sends its JOINs (and READY answers) at most every
# resend_s * actors / _ACTORS_PER_PERIOD: every JOIN is decoded by every other actor, so the
# whole fleet sends about as many JOINs per second as this many actors would, and the work
# of each actor per second does not grow with the fleet (50 actors: a JOIN every 0.5 s).
_ACTORS_PER_PERIOD = 10


class Handshakes:
    """The handshakes of one link, and every ``handshake_t`` it sends.

    Args:
        state: The link's shared state (held, not copied: every part sees one table).
    """

    def __init__(self, state: LinkState) -> None:
        self._st = state  # shared with the link's other parts, by reference
        self._last_stamp = 0  # guarded by the lock

    def run(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> str:
        """See :meth:`FleetActorLink.handshake`."""
        check_name("graph", graph)
        check_name("session", session)
        timeout = check_seconds("timeout", timeout, zero=True)
        participants = tuple(sorted({check_name("an actor", a) for a in actors}))
        if self._st.actor not in participants:
            raise ValueError(f"actors {list(participants)} do not include this actor")
        if len(participants) == 1:
            return session
        key = (graph, session)
        with self._st.lock:
            self._st.check_open()
            now = self._st.core.now()
            run = self._st.runs.get(key)
            if run is not None and run.phase is Phase.JOINING:
                raise StateError(f"a handshake of graph '{graph}' session '{session}' is running")
            if run is None:
                run = self._st.new_run(key, now)
            ended = self._st.ended.pop(key, None)
            if ended is not None:
                run.seen |= ended.seen
            run.local = True
            run.actors = participants
            run.actors_text = actors_json(participants)
            run.me = participants.index(self._st.actor)
            run.phase = Phase.JOINING
            run.proposal = f"{session}@{secrets.token_hex(6)}"
            run.joins = 0
            run.run_id = ""
            # what peers said of an earlier run of this session does not stand for this one
            run.ended_peers.clear()
            run.left_reasons.clear()
            run.aborted = None
            run.frozen = {}
            msg = self.join_msg(run)
            run.first_stamp = msg.stamp_us
        deadline = now + timeout
        ready: Any = None
        gap = self.gap(run)  # the least time between two JOINs
        period = gap  # doubles while a resend brings nothing new (to MAX_BACKOFF)
        longest = max(gap, MAX_BACKOFF * self._st.resend_s)
        unheard = math.inf  # reports missing at the last resend
        try:
            while ready is None:
                self._st.send(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
                run.last_join = self._st.core.now()
                run.joins += 1
                next_send = run.last_join + period
                with self._st.lock:
                    while True:
                        self.check_joining(run)
                        missing = self.unheard(run)
                        if not missing:
                            run.phase = Phase.READY
                            run.frozen = {p: peer.stamp for p, peer in run.peers.items()}
                            self.agree(run)
                            ready = self.ready_msg(run)
                            # READY goes out now: the next heartbeat can wait a period
                            self._st.next_heartbeat = self._st.core.now() + self._st.heartbeat_s
                            self._st.timer_wake.notify()
                            break
                        now = self._st.core.now()
                        if now >= deadline:
                            raise FleetError(
                                f"handshake of graph '{graph}' session '{session}' with "
                                f"{quoted(participants)} timed out after {timeout:g} s: "
                                + self.status(run)
                            )
                        answer = run.answer_at
                        if answer is not None and now >= answer:  # newly heard peers
                            run.answer_at = None
                            msg = self.join_msg(run)
                            break
                        if now >= next_send:
                            slower = missing >= unheard and period < longest
                            period = min(period * 2, longest) if slower else gap
                            unheard = missing
                            msg = self.join_msg(run)
                            break
                        wake = min(next_send, deadline, math.inf if answer is None else answer)
                        self._st.core.wait(self._st.changed, wake - now)
        except BaseException:
            self.give_up(run)
            raise
        self._st.send_quietly(HANDSHAKE_CHANNEL, ready, "handshakes_sent")
        return run.run_id

    def check_joining(self, run: Run) -> None:
        """Raise if the running handshake of ``run`` cannot go on."""
        self._st.check_open()
        if run.aborted is not None:
            status = self.status(run)
            raise FleetError(
                f"handshake of graph '{run.graph}' session '{run.session}': {run.aborted}"
                + (f"; {status}" if status else "")
            )

    def gap(self, run: Run) -> float:
        """The least time between two JOINs (or READY answers) of ``run``.

        See ``_ACTORS_PER_PERIOD``.
        """
        return self._st.resend_s * max(1.0, len(run.actors) / _ACTORS_PER_PERIOD)

    def answers_at_once(self, run: Run) -> int:
        """How many JOINs of ``run`` (its first included) answer newly heard peers at once.

        Every one in a fleet of up to ``_ACTORS_PER_PERIOD``; the first ``_ANSWERS_AT_ONCE`` in
        a larger one, whose answers wait for more peers (module constants).
        """
        n = len(run.actors)
        return n if n <= _ACTORS_PER_PERIOD else _ANSWERS_AT_ONCE

    def report_done(self, run: Run, actor: str, report: Peer) -> bool:
        """Whether ``actor``'s newest report says it heard every other participant.

        This actor must be heard with a stamp of the current handshake call. Lock held.
        """
        if report.actors == run.actors_text:  # the same list: read the stamps by place
            stamps = report.stamps
            return (
                report.full and len(stamps) == len(run.actors) and stamps[run.me] >= run.first_stamp
            )
        heard = report.heard()
        for b in run.actors:
            if b != actor and heard.get(b, 0) < (run.first_stamp if b == self._st.actor else 1):
                return False
        return True

    def unheard(self, run: Run) -> int:
        """How many participants are not heard, or have no complete report, here.

        0: the handshake is done. Lock held.
        """
        count = 0
        for actor in run.actors:
            if actor == self._st.actor:
                continue
            report = run.peers.get(actor)
            if report is None or not self.report_done(run, actor, report):
                count += 1
        return count

    def missing(self, run: Run) -> dict[str, list[str]]:
        """Who has not (yet, freshly) been heard by whom: heard actor -> hearers."""
        me = self._st.actor
        missing: dict[str, list[str]] = {}
        for a in run.actors:
            report = run.peers.get(a)
            heard = {} if report is None else report.heard()
            for b in run.actors:
                if a == b:
                    continue
                if a == me:
                    ok = b in run.peers
                elif report is None:
                    ok = False
                elif b == me:
                    ok = heard.get(me, -1) >= run.first_stamp
                else:
                    ok = b in heard
                if not ok:
                    missing.setdefault(b, []).append(a)
        return missing

    def status(self, run: Run) -> str:
        """Why the handshake of ``run`` is not done yet, for an error message."""
        silent = [a for a in run.actors if a != self._st.actor and a not in run.peers]
        parts = []
        if silent:
            parts.append(f"no answer from {quoted(silent)}")
        unheard = []
        for b, hearers in sorted(self.missing(run).items()):
            shown = [h for h in hearers if h not in silent]
            if shown:
                unheard.append(f"'{b}' by {quoted(shown)}")
        if unheard:
            parts.append("not heard: " + ", ".join(unheard))
        for actor in sorted(run.warned):
            peer = run.peers.get(actor)
            if peer is not None:
                parts.append(f"'{actor}' lists the actors {list(peer.names())}")
        return "; ".join(parts)

    def check_same_actors(self, run: Run, actor: str) -> None:
        """Warn once per peer whose actor list for ``run`` differs from ours. Lock held."""
        peer = run.peers.get(actor)
        if peer is None or actor in run.warned or peer.actors == run.actors_text:
            return
        if set(peer.names()) == set(run.actors):
            return
        run.warned.add(actor)
        logger.warning(
            "handshake of graph '%s' session '%s': '%s' lists the actors %s, this actor %s",
            run.graph,
            run.session,
            actor,
            list(peer.names()),
            list(run.actors),
        )

    def give_up(self, run: Run) -> None:
        """Not locked: a handshake failed; forget the run's handshake and LEAVE it."""
        key = (run.graph, run.session)
        with self._st.lock:
            if self._st.runs.get(key) is not run or run.phase is not Phase.JOINING:
                return
            del self._st.runs[key]
            if run.seen:
                self._st.ended[key] = Ended(
                    run.actors, None, run.seen, self._st.core.now() + self._st.grace_s
                )
            leave = (
                None if self._st.core.closed else self.leave_msg(run.graph, run.session, run.actors)
            )
        if leave is not None:
            self._st.send_quietly(HANDSHAKE_CHANNEL, leave, "handshakes_sent")

    def stamp(self) -> int:
        """A handshake stamp: the wall clock in microseconds, strictly increasing."""
        self._last_stamp = max(self._last_stamp + 1, round(self._st.core.wall() * 1e6))
        return self._last_stamp

    def handshake_msg(
        self,
        phase: int,
        graph: str,
        session: str,
        actors: Sequence[str],
        heard: Mapping[str, int] | None,
    ) -> Any:
        """A handshake_t; ``heard`` (None: no heard list) is written by place in ``actors``."""
        msg = new(handshake_t)
        msg.phase, msg.graph, msg.session, msg.actor = phase, graph, session, self._st.actor
        msg.stamp_us = self.stamp()
        msg.result, msg.reason, msg.run_id = "", "", ""
        msg.actors = actors_json(actors) if actors else ""
        if heard is not None and actors:  # by place; this actor's place: this message's stamp
            own = {self._st.actor: msg.stamp_us}
            stamps = [own.get(a) or heard.get(a, 0) for a in actors]
            msg.heard = struct.pack(f">{len(stamps)}q", *stamps)
        else:
            msg.heard = b""
        return msg

    def join_msg(self, run: Run) -> Any:
        """A JOIN of ``run`` with every peer heard so far and this call's proposal. Lock held."""
        heard = {p: peer.stamp for p, peer in run.peers.items()}
        msg = self.handshake_msg(JOIN, run.graph, run.session, run.actors, heard)
        msg.run_id = run.proposal
        return msg

    def ready_msg(self, run: Run) -> Any:
        """A full READY of ``run``: the frozen heard list and the agreed run id. Lock held."""
        msg = self.handshake_msg(READY, run.graph, run.session, run.actors, run.frozen)
        msg.run_id = run.run_id
        return msg

    def all_ready(self, run: Run) -> bool:
        """Whether every other participant said READY (with its lists) in this run. Lock held.

        Until then the heartbeats of ``run`` are full READYs: a peer still in its handshake
        completes with one even if this actor's first READY was lost and it dies before
        answering a JOIN.
        """
        for actor in run.actors:
            if actor != self._st.actor:
                peer = run.peers.get(actor)
                if peer is None or peer.phase != READY:
                    return False
        return True

    def heartbeat_msg(self, run: Run) -> Any:
        """A READY of ``run`` without the actor and heard lists: liveness, and "still in it".

        The first READY and the answers to late JOINs carry the lists; a heartbeat need not
        (decoding a 50-actor heard list 50 times a period was most of a fleet's work).
        """
        msg = self.handshake_msg(READY, run.graph, run.session, (), None)
        msg.run_id = run.run_id
        return msg

    def agree(self, run: Run) -> None:
        """The handshake of ``run`` is done: agree on its run id. Lock held.

        The run id is the smallest proposal; the run is kept under it too, with what peers
        that ran ahead already said under it.
        """
        proposals = [run.proposal]
        for actor in run.actors:
            peer = run.peers.get(actor)
            if peer is not None and peer.run_id:
                proposals.append(peer.run_id)
        run.run_id = min(proposals)
        key = (run.graph, run.run_id)
        early = self._st.runs.get(key)
        if early is not None and early is not run:  # peers that ran ahead spoke of it already
            for node, notices in early.pending.items():
                run.pending.setdefault(node, collections.deque()).extend(notices)
            run.seen |= early.seen
            for actor, result in early.ended_peers.items():
                run.ended_peers.setdefault(actor, result)
            run.left_reasons.update(early.left_reasons)
            run.left_peers |= early.left_peers
        self._st.runs[key] = run

    def leave_msg(self, graph: str, session: str, actors: Sequence[str]) -> Any:
        """A LEAVE of a run (no reason: the peers report this actor lost). Lock held."""
        return self.handshake_msg(LEAVE, graph, session, actors, None)

    def decision_msg(
        self, key: SessionKey, actors: Sequence[str], decision: tuple[int, str, str]
    ) -> Any:
        """END with the run's result, or LEAVE with the abort's reason."""
        phase, result, reason = decision
        msg = self.handshake_msg(phase, key[0], key[1], actors, None)
        msg.result, msg.reason = result, reason
        return msg

    def on_join_or_ready(self, msg: Any, now: float) -> Any:
        """Record a JOIN or READY of a run; the answer to send, if any. Lock held."""
        key: SessionKey = (msg.graph, msg.session)
        actor: str = msg.actor
        run = self._st.runs.get(key)
        reply: Any = None
        if run is None or not run.local:
            ended = self._st.ended.get(key)
            known = ended is not None and actor in ended.actors
            if (
                known
                and ended is not None
                and ended.decision is not None
                and msg.phase == READY
                and msg.run_id == ended.run_id
            ):
                # it still runs the run that ended here (not a new one of the same session):
                # our END or LEAVE has not reached it yet; closing the link waits for it (real
                # time: FleetActorLink._linger)
                ended.speaking[actor] = time.monotonic()
            if (
                known
                and msg.phase == READY
                and ended is not None
                and ended.decision is not None
                and now >= ended.next_answer
            ):
                # a peer still in a run that ended here: tell it again how (END may be lost);
                # one answer per heartbeat period reaches every peer
                reply = self.decision_msg(ended.out_key or key, ended.actors, ended.decision)
                ended.next_answer = now + self._st.heartbeat_s / 2
            elif known and msg.phase == JOIN and ended is not None and ended.heard is not None:
                reply = self.handshake_msg(READY, *key, ended.actors, ended.heard)
                reply.run_id = ended.run_id  # the run id agreed: the late peer takes it too
            if msg.phase != JOIN:
                return reply  # a READY of a run not started here: liveness only
            if run is None:
                run = self._st.new_run(key, now)
        if msg.phase == READY and not msg.heard:
            return reply  # a heartbeat: liveness only; the peer's full READY still stands
        raw: bytes = msg.heard
        if len(raw) % 8:
            self._st.core.count("unexpected")  # not whole stamps
            return reply
        run.touched = now
        peer = run.peers.get(actor)
        first = peer is None
        rejoined = False
        if peer is None or msg.stamp_us > peer.stamp:
            rejoined = peer is not None and msg.phase == JOIN and peer.phase != JOIN
            stamps: tuple[int, ...] = struct.unpack(f">{len(raw) // 8}q", raw)
            full = bool(stamps) and min(stamps) > 0
            run.peers[actor] = Peer(msg.stamp_us, msg.phase, msg.actors, stamps, msg.run_id, full)
        if run.phase is Phase.JOINING:
            if actor in run.actors:
                self.check_same_actors(run, actor)
                if (first or rejoined) and run.answer_at is None:
                    # answered by the handshake's thread: the first JOINs at once (a small
                    # fleet is done in a round trip or two), later ones with every peer heard
                    # meanwhile, and never sooner than a resend period after the last JOIN
                    run.answer_at = (
                        now
                        if run.joins < self.answers_at_once(run)
                        else max(
                            now + self._st.resend_s * _ANSWER_WINDOW, run.last_join + self.gap(run)
                        )
                    )
            self._st.changed.notify_all()
        elif (
            run.phase is Phase.READY
            and msg.phase == JOIN
            and actor in run.actors
            and now >= run.next_ready_reply  # one READY answers every late peer
        ):
            reply = self.ready_msg(run)
            run.next_ready_reply = now + self.gap(run)
        return reply
