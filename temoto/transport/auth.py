r"""Fleet security: sealed envelopes, per-boot sessions, encryption (docs/security.md).

Every fleet message travels in an ``envelope_t`` (:mod:`temoto.lcm_types`). :meth:`FleetAuth.seal`
wraps an inner message into one; :meth:`FleetAuth.open` checks a received one and returns its
content, or None after counting why it was dropped.

A keyed fleet (a shared fleet key, or :class:`~temoto.transport.identity.Credentials`: an
identity per member and a roster) writes envelope version 2: members exchange hellos on
:data:`HELLO_CHANNEL` that give every peer a grant of this boot's sending key, bound to the
peer's own boot (X25519), and every payload is encrypted with ChaCha20-Poly1305; with a roster
each message also carries one MAC per recipient, so a member cannot speak as another. A message
captured before a receiver restarted is refused by it whatever the clocks say (the argument is
in docs/security.md). An ``--insecure`` fleet writes version 1 envelopes without a mac. The
checks, in order:

=================  ===============================================================================
``garbage``        not a canonically encoded envelope (wrong fingerprint, truncated, trailing bytes)
``version``        an envelope version this code does not know
``fleet``          another fleet's message
``self``           our own message, echoed back by multicast
``unsigned``       no mac, but this fleet has a key
``unexpected_mac`` a mac, but this fleet runs insecure (keyed and insecure fleets never mix)
``unknown_member`` a sender not (or no longer) in the roster: never added, or revoked
``forged``         the mac, signature or AEAD tag is wrong: another key, a changed byte, another
                   channel, or a member speaking as another
``no_session``     a keyed sender whose session key we were not granted (yet): before the
                   hellos crossed, or a message from before our restart; or one its sender
                   sealed before the grant that overtook it (asked for once); triggers our hello
``not_for_us``     a message addressed to other members only
``stale``          (insecure fleets) the sender's stamp is more than ``window_s`` from our clock
``replayed``       a sequence number already seen, or too far below the highest seen, or a
                   hello of a boot the sender has left
=================  ===============================================================================

Drops that mean a member cannot be heard (every reason but ``self``, the multicast echo,
``fleet``, another fleet on the same network, ``no_session`` and ``not_for_us``, normal while
hellos cross, which are logged at DEBUG only) are logged at
WARNING, naming the claimed sender and the reason: the first drop of each sender and reason at
once, later ones as one summary line with counts per sender and reason, :data:`DROP_SUMMARY_S`
(1 s) after the first of them at most and at most once per that interval: a
:class:`~temoto.transport.link.FleetLink` writes it when it is due
(:meth:`FleetAuth.drop_summary_due_in`, :meth:`FleetAuth.log_drop_summary`) whether more drops
come or not, and the member writes what is left when it stops. :attr:`FleetAuth.stats` always
has the exact counts.

Every check covers the channel too: a captured message cannot be replayed on another channel.
Replay protection follows IPsec (RFC 4303 §3.4.3): per sender session, the highest sequence
number seen and a bitmap of the 64 below it; reordering inside that window is accepted, a
duplicate or anything older is not.

:class:`FleetLink` wires a :class:`FleetAuth` to a :class:`~temoto.transport.base.Transport`
and runs the hellos.
"""

from __future__ import annotations

import base64
import binascii
import logging
import math
import os
import string
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, final

from temoto.lcm_types import envelope_t
from temoto.transport._drops import (
    DROP_REASONS,
    DROP_SUMMARY_S,
    EXPLAIN,
    KEY_ENV,
    QUIET_REASONS,
    WARN_EXPLAIN,
    DropLog,
    claimed,
)
from temoto.transport._envelope import HELLO_TYPE, Writer
from temoto.transport._envelope import parse as parse_envelope
from temoto.transport.base import LogLimiter
from temoto.transport.identity import Credentials, RosterError

if TYPE_CHECKING:
    from temoto.transport._secure import SecureSession

__all__ = [
    "DROP_REASONS",
    "DROP_SUMMARY_S",
    "ENVELOPE_VERSION",
    "HELLO_CHANNEL",
    "KEY_ENV",
    "MIN_KEY_BYTES",
    "REPLAY_WINDOW",
    "FleetAuth",
    "Opened",
    "key_from_env",
    "key_from_text",
]

logger = logging.getLogger(__name__)

#: The envelope format of insecure fleets (keyed fleets write version 2, docs/security.md).
ENVELOPE_VERSION = 1
#: The channel of the keyed fleets' hellos (session key grants).
HELLO_CHANNEL = "TEMOTO_KEYS"
#: The shortest key accepted, in bytes (the HMAC-SHA256 output size).
MIN_KEY_BYTES = 32
#: How many sequence numbers below the highest seen are still accepted once (reordering).
REPLAY_WINDOW = 64
_SECURE_VERSION = 2
#: Seconds between two looks at the roster file when sealing (opening looks every time).
_SEAL_ROSTER_CHECK_S = 0.05
_WINDOW_MASK = (1 << REPLAY_WINDOW) - 1
# A sender not heard for this many windows is forgotten; its old messages are stale by then.
_FORGET_AFTER_WINDOWS = 10
_HEX_DIGITS = frozenset(string.hexdigits)
# Members warned about replays shown to them after a restart (once each), at most this many.
_MAX_REPLAY_WARNED = 256


def key_from_text(text: str) -> bytes:
    """Decode a fleet key written as hex or base64 (whitespace is ignored; hex is tried first).

    Args:
        text: The key, e.g. the output of ``python -c "import secrets;
            print(secrets.token_hex(32))"``.

    Returns:
        The key bytes, at least :data:`MIN_KEY_BYTES` of them.

    Raises:
        ValueError: If the text is empty, neither hex nor base64, or too short a key.
    """
    cleaned = "".join(text.split())
    if not cleaned:
        raise ValueError("the fleet key is empty")
    key: bytes | None = None
    if len(cleaned) % 2 == 0 and _HEX_DIGITS.issuperset(cleaned):
        key = bytes.fromhex(cleaned)
    else:
        padded = cleaned + "=" * (-len(cleaned) % 4)
        for altchars in (None, b"-_"):
            try:
                key = base64.b64decode(padded, altchars=altchars, validate=True)
            except (binascii.Error, ValueError):
                continue
            break
    if key is None:
        raise ValueError(
            "the fleet key is neither hex nor base64 (make one with: "
            'python -c "import secrets; print(secrets.token_hex(32))")'
        )
    if len(key) < MIN_KEY_BYTES:
        raise ValueError(
            f"the fleet key is {len(key)} bytes long; at least {MIN_KEY_BYTES} are needed "
            f"({2 * MIN_KEY_BYTES} hex digits)"
        )
    return key


def key_from_env(environ: Mapping[str, str] | None = None) -> bytes | None:
    """Read the fleet key from :data:`KEY_ENV` (``TEMOTO_FLEET_KEY``).

    Args:
        environ: The environment to read; ``os.environ`` when None.

    Returns:
        The key, or None when the variable is unset or blank.

    Raises:
        ValueError: If the variable is set but does not hold a valid key (the message names it).
    """
    text = (os.environ if environ is None else environ).get(KEY_ENV)
    if text is None or not text.strip():
        return None
    try:
        return key_from_text(text)
    except ValueError as err:
        raise ValueError(f"{KEY_ENV}: {err}") from None


@dataclass(frozen=True, slots=True)
class Opened:
    """The content of an envelope that passed every check.

    Attributes:
        channel: The channel it came on.
        sender: The sender's id (authenticated: with a roster, the member itself sent it).
        type: The inner message's type name (e.g. ``"handshake_t"``).
        payload: The inner message, LCM-encoded (decrypted).
        seq: The sender's sequence number.
        stamp_us: Insecure fleets: the sender's wall clock when sealing, microseconds since
            the epoch; keyed fleets: the sender's session id.
    """

    channel: str
    sender: str
    type: str
    payload: bytes
    seq: int
    stamp_us: int


@dataclass(slots=True)
class _Peer:
    """Replay state of one sender."""

    highest: int  # highest sequence number accepted
    bitmap: int  # bit i set: highest - i was accepted (bit 0 is highest itself)
    heard: float  # our clock at the last accepted message


@final
class FleetAuth:
    """Seals outgoing and checks incoming envelopes of one fleet member.

    A keyed member exchanges hellos before its peers can open its messages: a
    :class:`FleetLink` does that; used alone, publish what :meth:`take_outgoing` returns after
    every :meth:`seal` and :meth:`open`.

    Args:
        fleet: The fleet name; envelopes of other fleets are dropped.
        sender: This member's id, unique in the fleet.
        key: The shared fleet key (at least 32 bytes; see :func:`key_from_text`), or the
            member's credentials (as ``credentials``), or None together with ``insecure=True``
            or ``credentials``.
        insecure: Run without a key: seal without a mac and accept only envelopes without one.
            Anyone on the network can then forge, alter or replay messages; logged as a warning.
        window_s: Insecure fleets: largest accepted difference between a sender's stamp and our
            clock.
        clock: Wall clock in seconds since the epoch (injected by tests).
        credentials: This member's identity and the fleet roster, instead of a shared key:
            hellos are signed and every message carries a MAC per recipient.
        roster_check_s: Seconds between two looks at the roster file (default: at every
            message opened, so a revocation takes effect at the next message; at most every
            50 ms when sealing).

    Raises:
        ValueError: If a name is empty, the key is missing without ``insecure=True``, given
            together with it or with credentials, or too short, the identity's name is not
            ``sender``, or ``window_s`` is not positive.
        TypeError: If the key is not bytes.
    """

    def __init__(
        self,
        fleet: str,
        sender: str,
        key: bytes | Credentials | None,
        *,
        insecure: bool = False,
        window_s: float = 30.0,
        clock: Callable[[], float] = time.time,
        credentials: Credentials | None = None,
        roster_check_s: float = 0.0,
    ) -> None:
        for what, name in (("fleet", fleet), ("sender", sender)):
            if not isinstance(name, str) or not name:
                raise ValueError(f"the {what} name must be a non-empty string, got {name!r}")
        if isinstance(key, Credentials):
            if credentials is not None:
                raise ValueError("credentials given twice")
            key, credentials = None, key
        if credentials is not None:
            if key is not None or insecure:
                raise ValueError("credentials exclude a fleet key and insecure=True")
            if credentials.identity.name != sender:
                from temoto.errors import ConfigError  # a ValueError the CLI reports in a line

                raise ConfigError(
                    f"the fleet identity names {credentials.identity.name!r}, but this member"
                    f" is {sender!r} (--actor): give it its own identity file"
                )
        elif key is None and not insecure:
            raise ValueError(
                f"no fleet key for fleet {fleet!r}: set {KEY_ENV} (hex or base64, at least "
                f"{MIN_KEY_BYTES} bytes) or run insecure explicitly (--insecure)"
            )
        if key is not None:
            if insecure:
                raise ValueError("a fleet key and insecure=True exclude each other")
            if not isinstance(key, bytes | bytearray):
                raise TypeError(f"the fleet key must be bytes, got {type(key).__name__}")
            if len(key) < MIN_KEY_BYTES:
                raise ValueError(
                    f"the fleet key is {len(key)} bytes long; at least {MIN_KEY_BYTES} are needed"
                )
            key = bytes(key)
        if not (window_s > 0 and math.isfinite(window_s)):
            raise ValueError(f"window_s must be a positive number of seconds, got {window_s!r}")
        self.fleet = fleet
        self.sender = sender
        self.window_s = float(window_s)
        self._key = key
        self._clock = clock
        self._seq_lock = threading.Lock()
        self._seq = round(clock() * 1e6) - 1  # the first message carries the boot time
        self._lock = threading.Lock()  # guards _counts, _peers, _next_prune, _secure
        self._secure: SecureSession | None = None
        self.credentials = credentials
        self.roster_check_s = float(roster_check_s)
        self._last_roster_check: float | None = None
        if not insecure:
            from temoto.transport._secure import SecureSession

            self._secure = SecureSession(fleet, sender, key, credentials, clock)
        self._counts = dict.fromkeys(("accepted", "hello", *DROP_REASONS), 0)
        self._peers: dict[str, _Peer] = {}
        self._next_prune = clock() + self.window_s
        self._log = LogLimiter()  # the DEBUG lines of quiet drops
        self._drop_log = DropLog(DROP_SUMMARY_S)  # guarded by _lock
        self._replays_warned: set[str] = set()  # guarded by _lock
        self._writer = Writer(ENVELOPE_VERSION, fleet, sender)
        if insecure:
            logger.warning(
                "fleet %r runs INSECURE (no key): anyone on the network can forge, alter or "
                "replay its messages; set %s to authenticate them",
                fleet,
                KEY_ENV,
            )

    def __repr__(self) -> str:
        mode = "insecure" if self.insecure else "roster" if self.credentials else "keyed"
        return f"<FleetAuth fleet={self.fleet!r} sender={self.sender!r} {mode}>"

    @property
    def insecure(self) -> bool:
        """Whether this member runs without a key."""
        return self._secure is None

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters: ``accepted``, ``hello`` and one per :data:`DROP_REASONS`.

        ``hello``: the hellos taken in (keyed fleets).
        """
        with self._lock:
            return dict(self._counts)

    # --- sending ------------------------------------------------------------------------------

    def seal(self, channel: str, type_name: str, payload: bytes) -> bytes:
        """Wrap an inner message into an envelope for ``channel``; thread-safe.

        Args:
            channel: The channel it will be published on (covered by the mac).
            type_name: The inner message's type name.
            payload: The inner message, LCM-encoded.

        Returns:
            The encoded envelope, with a mac unless this member is insecure.

        Raises:
            TypeError: If ``payload`` is not bytes.
        """
        if not isinstance(payload, bytes | bytearray):
            raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
        if self._secure is not None:
            with self._lock:
                # what we send matters less than what we take in: a removed member gets
                # our new session key at most _SEAL_ROSTER_CHECK_S late, and opens nothing
                self._check_roster(_SEAL_ROSTER_CHECK_S)
                return self._secure.seal(channel, type_name, bytes(payload))
        with self._seq_lock:
            self._seq += 1
            seq = self._seq
        return self._writer.write(seq, round(self._clock() * 1e6), type_name, bytes(payload), b"")

    def take_outgoing(self) -> list[tuple[str, bytes]]:
        """What this member must publish now: a due hello, re-sent first messages (keyed fleets).

        Returns:
            (channel, data) pairs, in order; empty for insecure fleets.
        """
        secure = self._secure
        if secure is None or not secure.pending:  # the common case, without the lock
            return []
        with self._lock:
            self._check_roster(_SEAL_ROSTER_CHECK_S)
            out = secure.take_outgoing()
            replays = secure.take_replays()
            first: dict[str, int] = {}
            for name, count in replays.items():
                if name not in self._replays_warned and (
                    len(self._replays_warned) < _MAX_REPLAY_WARNED
                ):
                    self._replays_warned.add(name)
                    first[name] = count
        for name, count in first.items():
            logger.warning(
                "fleet %r: %s, restarted, was shown %d message(s) of ours that its earlier boot"
                " may have opened: a replay of captured traffic (or a copy in flight while it"
                " restarted); refused there, not sent again (this warning once per member)",
                self.fleet,
                claimed(name),
                count,
            )
        return out

    @property
    def peers(self) -> frozenset[str]:
        """Members whose messages this member can open now.

        Keyed fleets: they granted us their session; empty for insecure fleets (no sessions).
        """
        if self._secure is None:
            return frozenset()
        with self._lock:
            return self._secure.peers()

    def refusal(self, who: str, action: str, target: str) -> str | None:
        """Why the fleet policy refuses ``who`` doing ``action`` on ``target``.

        Only fleets with a roster have a policy (its ``permissions``); without one, or without
        a roster (a shared fleet key or ``--insecure``: nobody is told apart), everything is
        allowed.

        Args:
            who: The authenticated sender (:attr:`Opened.sender`).
            action: One of :data:`~temoto.transport.identity.ACTIONS`, e.g. ``"graph.start"``.
            target: The robot or resource server it concerns.

        Returns:
            None when allowed; else the reason, to answer and log.
        """
        if self.credentials is None:
            return None
        with self._lock:
            self._check_roster()
            roster = self.credentials.roster
            policy = roster.policy
        if policy is None or policy.allows(who, action, target):
            return None
        where = f" in {str(roster.path)!r}" if roster.path is not None else ""
        return f"permission denied: {who!r} may not {action} on {target!r} (fleet policy{where})"

    def want_hello(self) -> None:
        """Send a hello with the next :meth:`take_outgoing` the hello pace allows (keyed fleets).

        For a member that waits to hear peers without sending anything: a hello of ours that
        was lost (over Zenoh, one published before the router knew any subscriber) is sent
        again, and a peer that hears it answers with its grant. Nothing for insecure fleets.
        """
        secure = self._secure
        if secure is None:
            return
        with self._lock:
            secure.want_hello()

    def hello_due_in(self) -> float | None:
        """Seconds until a held-back hello may be sent (keyed fleets; hellos are rate-limited).

        Returns:
            The delay after which :meth:`take_outgoing` will return it, or None when no hello
            is held back.
        """
        secure = self._secure
        if secure is None or not secure.pending:
            return None
        with self._lock:
            return secure.hello_due_in()

    def _check_roster(self, every: float = 0.0) -> None:
        """Re-read a changed roster file; forget removed members at once. ``_lock`` held.

        Args:
            every: Look at the file at most this often (and at most every ``roster_check_s``).
        """
        if self.credentials is None or self._secure is None:
            return
        now = self._clock()
        last = self._last_roster_check
        if last is not None and last <= now < last + max(every, self.roster_check_s):
            return
        self._last_roster_check = now
        roster = self.credentials.roster
        before = set(roster.members)
        try:
            changed = roster.refresh()
        except RosterError as err:
            logger.error("fleet %r: keeping the roster as it was: %s", self.fleet, err)
            return
        if not changed:
            return
        gone = before - set(roster.members)
        gone |= {name for name, key in roster.revoked if roster.key_of(name) != key}
        logger.warning(
            "fleet %r: the roster changed (%d members); refusing %s from now on",
            self.fleet,
            len(roster.members),
            ", ".join(map(repr, sorted(gone))) or "nobody new",
        )
        self._secure.forget(gone)

    # --- receiving ----------------------------------------------------------------------------

    def open(self, channel: str, data: bytes) -> Opened | None:
        """Check a received envelope; thread-safe, never raises for any ``data``.

        Args:
            channel: The channel it came on.
            data: The received bytes.

        Returns:
            Its content, or None if it was dropped (counted in :attr:`stats` by reason).
        """
        result = self._check(channel, data)
        if isinstance(result, Opened):
            return result
        reason, sender, detail = result
        if reason == "hello":
            return None
        first, summary = False, None
        with self._lock:
            self._counts[reason] += 1
            if reason not in QUIET_REASONS:
                first, summary = self._drop_log.drop(sender, reason, self._clock())
        if first:
            what, hint = WARN_EXPLAIN[reason]
            logger.warning(
                "fleet %r: dropped a message on %r from %s: %s%s; %s (further drops are"
                " summarised at most every %g s)",
                self.fleet,
                channel,
                claimed(sender),
                what,
                detail,
                hint,
                DROP_SUMMARY_S,
            )
        elif summary is not None:
            logger.warning("fleet %r: %s", self.fleet, summary)
        if reason in QUIET_REASONS and logger.isEnabledFor(logging.DEBUG):
            held = self._log.allow(reason)
            if held is not None:
                more = f" ({held} more since the last report)" if held else ""
                logger.debug(
                    "fleet %r: dropped a message on %r from %s: %s%s",
                    self.fleet,
                    channel,
                    claimed(sender),
                    EXPLAIN[reason],
                    more,
                )
        return None

    def drop_summary_due_in(self) -> float | None:
        """Seconds until the summary of the drops held back is due (see :meth:`log_drop_summary`).

        Returns:
            The delay (0 when due already), or None when no drop is held back.
        """
        with self._lock:
            due = self._drop_log.due()
            return None if due is None else max(0.0, due - self._clock())

    def log_drop_summary(self) -> None:
        """Log the summary of drops held back since the last line (WARNING), if there are any.

        A :class:`~temoto.transport.link.FleetLink` calls it when :meth:`drop_summary_due_in`
        says; call it when the member stops, so that the drops of its last moments are reported
        too.
        """
        with self._lock:
            line = self._drop_log.flush(self._clock())
        if line is not None:
            logger.warning("fleet %r: %s", self.fleet, line)

    # --- internals ----------------------------------------------------------------------------

    def _check(self, channel: str, data: bytes) -> Opened | tuple[str, str | None, str]:
        """Run the checks of :meth:`open`.

        Returns:
            The content; or why it is dropped, from whom (None: unknown) and details for the
            log line (``""`` or ``" (...)"``).
        """
        # Only the canonical encoding is accepted: LCM's decoder ignores trailing bytes, reads
        # short arrays without complaint and replaces bad UTF-8, none of which must leave a
        # second spelling of a message.
        env = parse_envelope(data)
        if env is None:
            return "garbage", None, ""
        sender: str = env.sender
        version: int = env.version
        if version not in (ENVELOPE_VERSION, _SECURE_VERSION):
            return "version", sender, f" (version {version})"
        if env.fleet != self.fleet:
            return "fleet", sender, ""
        if sender == self.sender:
            return "self", sender, ""
        mac_size: int = env.mac_size
        if self._secure is None:
            if mac_size != 0 or version != ENVELOPE_VERSION:
                return "unexpected_mac", sender, ""
        elif version == ENVELOPE_VERSION:
            if mac_size == 0:
                return "unsigned", sender, ""
            return "version", sender, " (version 1: an older TeMoto with a fleet key)"
        else:
            return self._check_secure(channel, env, data)
        now = self._clock()
        stamp_us: int = env.stamp_us
        skew = stamp_us / 1e6 - now
        if abs(skew) > self.window_s:
            return "stale", sender, f" ({skew:+.1f} s from our clock, window ±{self.window_s:g} s)"
        seq: int = env.seq
        with self._lock:
            if not self._admit(sender, seq, now):
                return "replayed", sender, ""
            self._counts["accepted"] += 1
            if now >= self._next_prune:
                self._prune(now)
        return Opened(channel, sender, env.type, env.payload, seq, stamp_us)

    def _check_secure(
        self, channel: str, env: envelope_t, data: bytes
    ) -> Opened | tuple[str, str | None, str]:
        """The checks of a version 2 envelope (keyed fleets)."""
        assert self._secure is not None
        sender: str = env.sender
        with self._lock:
            self._check_roster()
            if self.credentials is not None and self.credentials.roster.key_of(sender) is None:
                return "unknown_member", sender, ""
            if channel == HELLO_CHANNEL and env.type == HELLO_TYPE:
                reason = self._secure.open_hello(env, data)
                if reason is not None:
                    return reason, sender, ""
                self._counts["hello"] += 1
                return "hello", sender, ""
            sealed = self._secure.open_data(channel, env)
            if isinstance(sealed, str):
                return sealed, sender, ""
            self._counts["accepted"] += 1
        return Opened(channel, sender, sealed.type, sealed.payload, sealed.seq, sealed.session)

    def _admit(self, sender: str, seq: int, now: float) -> bool:
        """Apply the replay window; called with ``_lock`` held. True if ``seq`` is new."""
        peer = self._peers.get(sender)
        if peer is None:
            self._peers[sender] = _Peer(seq, 1, now)
            return True
        if seq > peer.highest:
            shift = seq - peer.highest
            peer.bitmap = (
                ((peer.bitmap << shift) | 1) & _WINDOW_MASK if shift < REPLAY_WINDOW else 1
            )
            peer.highest = seq
        else:
            behind = peer.highest - seq
            if behind >= REPLAY_WINDOW or peer.bitmap >> behind & 1:
                return False
            peer.bitmap |= 1 << behind
        peer.heard = now
        return True

    def _prune(self, now: float) -> None:
        """Forget senders not heard for a long time; called with ``_lock`` held."""
        horizon = now - _FORGET_AFTER_WINDOWS * self.window_s
        for sender in [s for s, peer in self._peers.items() if peer.heard < horizon]:
            del self._peers[sender]
        self._next_prune = now + self.window_s
