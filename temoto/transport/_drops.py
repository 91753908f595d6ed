"""What the fleet's authentication drops, and how it says so (:mod:`temoto.transport.auth`).

The reasons a received envelope is dropped (:data:`DROP_REASONS`, the keys of
``FleetAuth.stats``), what each means in a log line, and :class:`DropLog`: the first drop of
each sender and reason at WARNING, later ones summarised, per sender and reason, at most
:data:`DROP_SUMMARY_S` seconds after the first of them (a ``FleetLink`` writes the summary when
it is due, whether more drops come or not) and at most once per that interval. Kept apart
from the checks themselves so that the module deciding what a message means stays short
enough to read at once.
"""

from __future__ import annotations

__all__ = [
    "DROP_REASONS",
    "DROP_SUMMARY_S",
    "EXPLAIN",
    "KEY_ENV",
    "QUIET_REASONS",
    "WARN_EXPLAIN",
    "DropLog",
    "claimed",
]

#: The environment variable holding the fleet key (hex or base64).
KEY_ENV = "TEMOTO_FLEET_KEY"

#: Why :meth:`FleetAuth.open` drops a message, in the order it checks; keys of ``stats``.
DROP_REASONS = (
    "garbage",
    "version",
    "fleet",
    "self",
    "unsigned",
    "unexpected_mac",
    "unknown_member",
    "forged",
    "no_session",
    "not_for_us",
    "stale",
    "replayed",
)

#: Drops that are normal on a shared network and logged at DEBUG only; the others at WARNING.
QUIET_REASONS = frozenset({"self", "fleet", "no_session", "not_for_us"})
#: A summary line of dropped messages (WARNING) comes at most this long after the first drop it
#: counts, and at most once per this interval, more drops or not: a summary that waited for the
#: next drop or the stop would leave a repeated attack unseen.
DROP_SUMMARY_S = 1.0
#: At most this many (sender, reason) pairs get a line of their own; any later pair (a stranger
#: inventing sender names) is only counted in the summaries.
_MAX_FIRST_LINES = 64
#: A claimed sender name is cut to this many characters in a log line.
_MAX_NAME_CHARS = 64
#: A summary line lists at most this many (sender, reason) pairs.
_MAX_SUMMARY_PAIRS = 8

EXPLAIN = {
    "garbage": "not an envelope",
    "version": "unknown envelope version",
    "fleet": "another fleet",
    "self": "our own message",
    "unsigned": "no mac, but this fleet has a key",
    "unexpected_mac": "a mac, but this fleet runs insecure",
    "unknown_member": "not a member of the roster",
    "forged": "wrong mac",
    "no_session": "no session key granted by this sender (yet)",
    "not_for_us": "addressed to other members",
    "stale": "stamp outside the time window",
    "replayed": "sequence number already seen or too old",
}


#: What a WARNING says about each reason it logs: what was wrong, and what to check.
WARN_EXPLAIN = {
    "garbage": ("not a well-formed envelope", "damaged, truncated, or another program's message"),
    "version": ("an unknown envelope version", "does the sender run another TeMoto version?"),
    "unsigned": ("no mac, but this fleet has a key", "does the sender run --insecure?"),
    "unexpected_mac": ("a mac, but this member runs --insecure", "the sender has a fleet key"),
    "unknown_member": (
        "not a member of the roster",
        "never added, or revoked (temoto keys list ROSTER)",
    ),
    "forged": (
        "wrong mac",
        f"sealed with another fleet key (check {KEY_ENV} or --fleet-key-file), changed, or a"
        " member speaking as another",
    ),
    "no_session": ("no session key granted", "the hellos have not crossed yet"),
    "not_for_us": ("addressed to other members", "normal"),
    "stale": ("time stamp outside the window", "are the clocks synchronised (NTP)?"),
    "replayed": (
        "sequence number already seen or too old",
        "a replayed message, or two members using this name",
    ),
}


def claimed(sender: str | None) -> str:
    """A claimed sender name for a log line: quoted, escaped, cut (it is the sender's text)."""
    if sender is None:
        return "an unknown sender"
    if len(sender) > _MAX_NAME_CHARS:
        return repr(sender[:_MAX_NAME_CHARS]) + "..."
    return repr(sender)


class DropLog:
    """Decides which authentication drops are logged at WARNING, and summarises the rest.

    The first drop of each (sender, reason) is logged at once (up to :data:`_MAX_FIRST_LINES`
    pairs); later ones are counted and written as one summary line ``interval_s`` after the
    first of them (:meth:`due`; a drop that comes later writes it too): at most one line per
    interval, and never later than that after a drop. Not thread-safe: the caller holds a lock.

    Args:
        interval_s: Seconds between two summary lines.
    """

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._first: set[tuple[str | None, str]] = set()
        self._pending: dict[tuple[str | None, str], int] = {}
        self._since: float | None = None  # when the first drop held back came

    def drop(self, sender: str | None, reason: str, now: float) -> tuple[bool, str | None]:
        """Record one drop.

        Args:
            sender: The claimed sender, or None when unknown.
            reason: Why it was dropped (one of :data:`DROP_REASONS`).
            now: The current time in seconds.

        Returns:
            Whether this drop gets a line of its own, and a summary line to log now (or None).
        """
        key = (sender, reason)
        if key not in self._first and len(self._first) < _MAX_FIRST_LINES:
            self._first.add(key)
            return True, None
        if not self._pending or self._since is None or now < self._since:  # or clock went back
            self._since = now
        self._pending[key] = self._pending.get(key, 0) + 1
        if now - self._since < self.interval_s:
            return False, None
        return False, self.flush(now)

    def due(self) -> float | None:
        """When the summary of the drops held back is due (None: none is held back).

        Returns:
            The time, on the clock of :meth:`drop`.
        """
        if not self._pending or self._since is None:
            return None
        return self._since + self.interval_s

    def flush(self, now: float) -> str | None:
        """The summary of the drops held back so far (None if there are none); starts anew.

        Args:
            now: The current time in seconds.

        Returns:
            The summary line, or None.
        """
        if not self._pending:
            return None
        since = now if self._since is None else self._since
        pairs = sorted(self._pending.items(), key=lambda item: -item[1])
        total = sum(n for _, n in pairs)
        shown = ", ".join(
            f"{n} from {claimed(who)} ({WARN_EXPLAIN[why][0]})"
            for (who, why), n in pairs[:_MAX_SUMMARY_PAIRS]
        )
        if len(pairs) > _MAX_SUMMARY_PAIRS:
            rest = sum(n for _, n in pairs[_MAX_SUMMARY_PAIRS:])
            shown += f" and {rest} from {len(pairs) - _MAX_SUMMARY_PAIRS} other senders/reasons"
        line = f"dropped {total} more messages in the last {max(0.0, now - since):.1f} s: {shown}"
        self._pending.clear()
        self._since = None
        return line
