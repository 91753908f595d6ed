"""Per-boot sessions of a keyed fleet: hellos, key grants, AEAD envelopes (docs/security.md).

Private to :mod:`temoto.transport.auth`, whose :class:`~temoto.transport.auth.FleetAuth` owns
one :class:`SecureSession` when it has a fleet key or credentials. Not thread-safe: the caller
holds a lock. Sans-IO: it never publishes; messages it wants sent (hellos, re-sent backlog)
are queued and taken with :meth:`SecureSession.take_outgoing`.

Every boot of a member makes an ephemeral X25519 key pair and a random sending key ``G`` with a
random session id. Its hello (channel :data:`HELLO_CHANNEL`) carries the ephemeral public key
and, for every peer whose ephemeral key it heard, a *grant*: ``G``, the session id and the
sender's current sequence number (the *floor*), encrypted under a key derived from the two
ephemeral keys. A hello is authenticated with the fleet key (HMAC-SHA256) or, with a roster,
the sender's Ed25519 signature. A receiver opens data of a session only after a grant for its
own current ephemeral key, and only above the floor: every message sealed before the receiver
booted has a sequence number at or below the floor of any grant the receiver can read.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from temoto.lcm_types import envelope_t
from temoto.transport._envelope import HELLO_TYPE, Writer, parse_hello
from temoto.transport.identity import Credentials

HELLO_CHANNEL: Final = "TEMOTO_KEYS"  #: The channel of hellos.
SECURE_VERSION: Final = 2  #: The envelope version of keyed fleets.
#: Seconds between two hellos at least (a flood of undecryptable messages costs little), in
#: a fleet of up to :data:`_PEERS_PER_GAP` other members; a larger fleet waits longer, so that
#: the hellos the whole fleet sends per second (each one read by every member) stay as many as
#: that many members would send: 50 members send a hello every 0.25 s at most. Hellos that
#: answer a new peer go out at once.
HELLO_MIN_S: Final = 0.05
_PEERS_PER_GAP: Final = 10
#: A peer's grant is on its way for this long after our hello that gave the peer our key (it
#: answers that hello with its own): its messages that come meanwhile do not make us ask for
#: it, and a peer that asks for our grant within this time of our last one to it is not sent
#: another. Every hello reaches the whole fleet; when N members start together, asking for
#: grants that were in flight made hellos grow as N³ (docs/security.md).
GRANT_WAIT_S: Final = 0.25
#: A peer that received messages of ours it could not open (no grant yet: the hellos were
#: crossing) names them in its hello; we re-send them to it if they are at most this old.
BACKLOG_S: Final = 2.0
#: A peer whose hello we heard, and which we granted our session, but whose grant has not come
#: this long after ours (times the hello pace of a large fleet: its answer may wait for it) is
#: asked for it in each of our hellos, for :data:`ASK_FOR_S` after its last hello. A lost
#: grant was not sent again while its peer sent us nothing we could not open: a member waiting
#: for its peers (``FleetLink.wait_for_peers``, which says hello again) waited in vain.
ASK_S: Final = 0.5
ASK_FOR_S: Final = 30.0
_MISSED_MAX: Final = 256  # the last this many per sender session; as many senders at most
#: At most this many of the newest missed messages are asked for again at once (all that are
#: kept: a burst sent while the hellos cross arrives whole).
_RESEND_MAX: Final = _MISSED_MAX
_BACKLOG_MAX: Final = 256
_TAG: Final = 16  # Poly1305 tag
_RECIPIENT: Final = 4  # recipient tag
_MAC: Final = 16  # per-recipient MAC (roster fleets)
_HINT: Final = 8  # prefix of the recipient's ephemeral key in a grant
_GRANT_PLAIN: Final = struct.Struct(">32sQQ")  # G, session id, floor
_GRANT_SIZE: Final = 12 + _GRANT_PLAIN.size + _TAG
_WINDOW: Final = 64
_WINDOW_MASK: Final = (1 << _WINDOW) - 1
_SALT: Final = b"temoto fleet v2"
_AD_CACHE_MAX: Final = 1024  # (channel, sender, type) prefixes of the associated data
_SEQ_SESSION: Final = struct.Struct(">IQQI")  # the ad's tail: 16, seq, session, len(tags)


def _blob(*parts: bytes) -> bytes:
    """Length-prefixed concatenation: no two tuples of parts give the same bytes."""
    return b"".join(struct.pack(">I", len(p)) + p for p in parts)


def _kdf(key: bytes, label: bytes, size: int = 32) -> bytes:
    return hashlib.blake2b(label, key=key, digest_size=size).digest()


def _s(text: str) -> bytes:
    return text.encode("utf-8", "surrogatepass")


@dataclass(slots=True)
class _Pair:
    """The keys this member shares with one boot of a peer (from both ephemeral keys)."""

    e_pub: bytes
    grant_out: ChaCha20Poly1305  # grants we send to it
    grant_in: ChaCha20Poly1305  # grants it sends to us
    mac_out: bytes  # our per-recipient MACs for it (roster fleets)
    mac_in: bytes  # its MACs for us
    tag_out: bytes  # it, as a recipient of our messages
    tag_in: bytes  # we, as a recipient of its messages
    first_floor: int | None = None  # floor of the first grant we sent it (our session)
    owed: bool = True  # our next hello carries a grant for it
    granted_at: float | None = None  # our clock when our last hello granted it our session
    opens: bool = False  # it granted us a session of its (an RxSession holds this pair)
    session: int = 0  # its session id, from its newest hello: what we ask it to grant
    heard_at: float = 0.0  # our clock when that hello came


@dataclass(slots=True)
class _Peer:
    current: _Pair | None = None  # proven: it sent us a grant for our current key
    candidate: _Pair | None = None  # heard in a hello, not yet proven
    retired: set[bytes] = field(default_factory=set)  # older ephemeral keys of this name
    # Our sequence numbers (floor, last] that an older boot of this name held a grant for:
    # it may have opened them, so they are never re-sent to a later boot.
    opened: list[tuple[int, int]] = field(default_factory=list)

    def drop(self, pair: _Pair | None, seq: int) -> None:
        """Remember what a pair we stop using could open."""
        if pair is not None and pair.first_floor is not None:
            self.opened.append((pair.first_floor, seq))
            del self.opened[:-64]  # keep the newest; older ones are far out of the backlog

    def could_open(self, seq: int, pair: _Pair) -> bool:
        """Whether a boot of this name other than ``pair``'s may have opened ``seq``."""
        live = [
            (p.first_floor, seq)
            for p in (self.current, self.candidate)
            if p is not None and p is not pair and p.first_floor is not None
        ]
        return any(low < seq <= high for low, high in (*self.opened, *live))


@dataclass(slots=True)
class RxSession:
    """A peer's sending session we can open: its key and our replay window."""

    sender: str
    aead: ChaCha20Poly1305
    pair: _Pair
    highest: int
    bitmap: int
    floor: int  # of its grant: what it sealed at or below was sealed before the grant
    # Sequence numbers at or below the floor that we asked for again (at most once each).
    asked: set[int] = field(default_factory=set)


@dataclass(slots=True)
class Sealed:
    """What :meth:`SecureSession.open_data` found (the caller builds ``Opened``)."""

    type: str
    payload: bytes
    seq: int
    session: int


class SecureSession:
    """The keyed part of one member's :class:`~temoto.transport.auth.FleetAuth`.

    Args:
        fleet: The fleet name.
        sender: This member's name.
        key: The shared fleet key (hellos carry its HMAC), or None with ``credentials``.
        credentials: Identity and roster (hellos are signed; data carries a MAC per recipient).
        clock: Seconds, for the hello rate limit and the backlog.
    """

    def __init__(
        self,
        fleet: str,
        sender: str,
        key: bytes | None,
        credentials: Credentials | None,
        clock: Callable[[], float],
    ) -> None:
        self.fleet = fleet
        self.sender = sender
        self._key = key
        self.credentials = credentials
        self._clock = clock
        self._e = X25519PrivateKey.generate()
        self.e_pub = self._e.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        self._peers: dict[str, _Peer] = {}
        self.rx: dict[tuple[str, int], RxSession] = {}
        self._outgoing: list[tuple[str, bytes]] = []
        self._urgent = True  # a hello that moves a handshake on: sent at once
        # A hello that may help (it asks for grants): sent from this time on (None: none is
        # wanted), at most every HELLO_MIN_S.
        self._wanted_at: float | None = None
        # Per (sender, session) we lack: the sequence numbers we got and could not open.
        self._missed: dict[tuple[str, int], deque[int]] = {}
        self._resend: list[tuple[str, _Pair, list[int]]] = []  # with the next take_outgoing
        # Per peer: the messages it asked for that an earlier boot of it held a grant for
        # (never sent again: a replay shown to the restarted peer), since the last take_replays.
        self._replays: dict[str, int] = {}
        self._last_hello: float | None = None
        self._born = clock()
        self._backlog: deque[tuple[int, float, str, str, bytes]] = deque(maxlen=_BACKLOG_MAX)
        self._writer = Writer(SECURE_VERSION, fleet, sender)
        self._me = _blob(_s(sender))  # how hellos name us (grants for us, what we are asked)
        self._ad_heads: dict[tuple[str, str, str], bytes] = {}
        self._rotate()

    @property
    def roster_mode(self) -> bool:
        """Whether members have their own keys (per-recipient MACs, signed hellos)."""
        return self.credentials is not None

    def _rotate(self) -> None:
        """A new sending key and session id; every peer gets a new grant."""
        self._g = os.urandom(32)
        self._aead = ChaCha20Poly1305(self._g)
        self.session = int.from_bytes(os.urandom(8), "big") >> 1 or 1
        self.seq = 0
        for peer in self._peers.values():
            peer.opened.clear()  # about the old session's numbers
            for pair in (peer.current, peer.candidate):
                if pair is not None:
                    pair.first_floor = None
                    pair.owed = True
                    pair.granted_at = None
        self._backlog.clear()
        self._urgent = True

    # --- roster -------------------------------------------------------------------------------

    def forget(self, names: set[str]) -> None:
        """Drop everything of members removed from the roster and rotate our sending key."""
        for name in names:
            self._peers.pop(name, None)
        for key in [k for k in self.rx if k[0] in names]:
            del self.rx[key]
        self._rotate()

    # --- hellos -------------------------------------------------------------------------------

    def want_hello(self, at: float | None = None) -> None:
        """Ask for a hello (sent with the first :meth:`take_outgoing` the rate limit allows).

        Args:
            at: Not before this time of the clock (default: now).
        """
        if at is None:
            at = self._clock()
        if self._wanted_at is None or at < self._wanted_at:
            self._wanted_at = at

    def peers(self) -> frozenset[str]:
        """Names whose current boot granted us its session (we can open their messages)."""
        return frozenset(
            name
            for (name, _), rx in self.rx.items()
            if (peer := self._peers.get(name)) is not None and peer.current is rx.pair
        )

    @property
    def pending(self) -> bool:
        """Whether :meth:`take_outgoing` may have something.

        Read without the lock: a thread that made something pending reads its own write.
        """
        return (
            self._urgent
            or self._wanted_at is not None
            or bool(self._outgoing)
            or bool(self._resend)
        )

    def hello_due_in(self) -> float | None:
        """Seconds until a held-back hello may go out (None: none is held back)."""
        if self._urgent:
            return 0.0
        if self._wanted_at is None:
            return None
        now = self._clock()
        due = self._wanted_at
        if self._last_hello is not None and self._last_hello <= now:
            due = max(due, self._last_hello + self._gap())
        return max(0.0, due - now)

    def _answer(self) -> None:
        """Ask for a hello that moves a handshake on: at once in a small fleet.

        In a large one it goes with the next hello the pace allows (:meth:`_gap`), so that the
        members that start together are answered together, in a few hellos.
        """
        if len(self._peers) <= _PEERS_PER_GAP:
            self._urgent = True
        else:
            self.want_hello()

    def _gap(self) -> float:
        """The least time between two hellos that do not answer a new peer."""
        return HELLO_MIN_S * max(1.0, len(self._peers) / _PEERS_PER_GAP)

    def take_outgoing(self) -> list[tuple[str, bytes]]:
        """The (channel, bytes) to publish now: a due hello first, then re-sent messages."""
        now = self._clock()
        if self._urgent or (
            self._wanted_at is not None
            and self._wanted_at <= now
            and (
                self._last_hello is None
                or now - self._last_hello >= self._gap()
                or now < self._last_hello
            )
        ):
            self._urgent = False
            self._wanted_at = None
            self._last_hello = now
            self._outgoing[:0] = [(HELLO_CHANNEL, self._hello(now))]
        if self._resend:  # copies for peers that asked (they hold our grant: no hello needed)
            resend, self._resend = self._resend, []
            self._resend_backlog(resend, now)
        out, self._outgoing = self._outgoing, []
        return out

    def _lacking(self, now: float) -> list[tuple[str, int]]:
        """(name, session) of the peers heard lately whose grant we lack, to ask for.

        Only those we granted ours :data:`ASK_S` (times the pace of a large fleet) ago or more:
        their answer had time to come. Those asked for already (``_missed``) apart.
        """
        wait = ASK_S * max(1.0, self._gap() / HELLO_MIN_S)
        return [
            (name, pair.session)
            for name, peer in sorted(self._peers.items())
            for pair in {id(p): p for p in (peer.current, peer.candidate) if p}.values()
            if not pair.opens
            and now - pair.heard_at < ASK_FOR_S
            and pair.granted_at is not None
            and now - pair.granted_at >= wait
            and (name, pair.session) not in self._missed
        ]

    def _pair(self, name: str, e_pub: bytes) -> _Pair:
        shared = self._e.exchange(X25519PublicKey.from_public_bytes(e_pub))
        me, it = (_s(self.sender), self.e_pub), (_s(name), e_pub)
        lo, hi = sorted((me, it))
        root = hashlib.blake2b(
            _blob(_SALT, _s(self.fleet), *lo, *hi, shared), digest_size=32
        ).digest()

        def way(src: tuple[bytes, bytes], dst: tuple[bytes, bytes], what: bytes) -> bytes:
            return _kdf(root, _blob(what, *src, *dst))

        return _Pair(
            e_pub=e_pub,
            grant_out=ChaCha20Poly1305(way(me, it, b"grant")),
            grant_in=ChaCha20Poly1305(way(it, me, b"grant")),
            mac_out=way(me, it, b"mac"),
            mac_in=way(it, me, b"mac"),
            tag_out=way(me, it, b"tag")[:_RECIPIENT],
            tag_in=way(it, me, b"tag")[:_RECIPIENT],
        )

    def _hello(self, now: float) -> bytes:
        parts = [self.e_pub, struct.pack(">H", 0)]
        count = 0
        fresh: list[_Pair] = []
        for name, peer in sorted(self._peers.items()):
            for pair in {id(p): p for p in (peer.current, peer.candidate) if p}.values():
                if not pair.owed:  # granted already: hellos stay small in a large fleet
                    continue
                pair.owed = False
                pair.granted_at = now
                if pair.first_floor is None:
                    pair.first_floor = self.seq
                    fresh.append(pair)
                nonce = os.urandom(12)
                plain = _GRANT_PLAIN.pack(self._g, self.session, self.seq)
                ad = _blob(_s(self.fleet), _s(self.sender), self.e_pub, _s(name), pair.e_pub)
                grant = nonce + pair.grant_out.encrypt(nonce, plain, ad)
                parts.append(_blob(_s(name)) + pair.e_pub[:_HINT] + grant)
                count += 1
        parts[1] = struct.pack(">H", count)
        lacking = self._lacking(now)
        parts.append(struct.pack(">H", len(self._missed) + len(lacking)))
        for name, session in lacking:  # grants lost on the way: asked for again
            parts.append(_blob(_s(name)) + struct.pack(">QH", session, 0))
        for (name, session), seqs in list(self._missed.items()):
            # Without its grant, ask for the grant only: copies would be refused like the
            # originals. With it, ask once for what we could not open.
            ask = list(seqs)[-_RESEND_MAX:] if (name, session) in self.rx else []
            parts.append(_blob(_s(name)) + struct.pack(f">QH{len(ask)}Q", session, len(ask), *ask))
            if ask:
                del self._missed[name, session]
        body = b"".join(parts)
        unsigned = self._writer.write(0, self.session, HELLO_TYPE, body, b"")
        proof = self._prove(_s(HELLO_CHANNEL) + b"\0" + unsigned)
        return unsigned[:-2] + struct.pack(">h", len(proof)) + proof

    def _prove(self, data: bytes) -> bytes:
        if self.credentials is not None:
            return self.credentials.identity.sign(data)
        assert self._key is not None
        return hmac.digest(self._key, data, "sha256")

    def _check_proof(self, sender: str, proof: bytes, data: bytes) -> bool:
        if self.credentials is not None:
            return self.credentials.roster.verify(sender, proof, data)
        assert self._key is not None
        return hmac.compare_digest(hmac.digest(self._key, data, "sha256"), proof)

    def open_hello(self, env: envelope_t, data: bytes) -> str | None:
        """Take a hello in; returns a drop reason, or None when it was used (or of no use)."""
        sender: str = env.sender
        body: bytes = env.payload
        if self._me not in body:  # no grant for us, nothing asked of us: of use only if new
            peer = self._peers.get(sender)
            if peer is not None and any(
                p is not None and p.opens and p.e_pub == body[:32]
                for p in (peer.current, peer.candidate)
            ):
                return None  # a hello for others from a peer we share keys with
        try:
            e_pub, grants, wants = parse_hello(body, _HINT, _GRANT_SIZE, _MISSED_MAX)
        except ValueError:
            return "garbage"
        grant = next((g for h, g in grants.get(self.sender, ()) if h == self.e_pub[:_HINT]), None)
        missed = wants.get((self.sender, self.session))
        peer = self._peers.get(sender)
        pair = None
        if peer is not None:
            pair = next((p for p in (peer.current, peer.candidate) if p and p.e_pub == e_pub), None)
        if pair is not None and grant is None and missed is None and pair.opens:
            return None  # a hello for others from a peer we share keys with: nothing to do
        unsigned = data[: len(data) - 2 - env.mac_size] + b"\0\0"
        if not self._check_proof(sender, env.mac, _s(HELLO_CHANNEL) + b"\0" + unsigned):
            return "forged"
        peer = self._peers.setdefault(sender, _Peer())
        if e_pub in peer.retired:
            return "replayed"
        if pair is None:
            try:
                pair = self._pair(sender, e_pub)
            except ValueError:
                return "garbage"
            if peer.candidate is not None and peer.candidate is not peer.current:
                peer.drop(peer.candidate, self.seq)
            peer.candidate = pair
            self._answer()  # it gets a grant from us
        pair.session, pair.heard_at = env.stamp_us, self._clock()
        if missed:  # it asks for what it could not open before it had our grant
            self._resend.append((sender, pair, missed))
        elif missed is not None:  # it lacks our grant
            now = self._clock()
            sent = pair.granted_at
            if not pair.owed and (sent is None or not sent <= now < sent + GRANT_WAIT_S):
                pair.owed = True  # with our next hello, at the pace of the fleet's hellos
                self.want_hello(now)
            # else: our grant left a moment ago (it asked before that reached it)
        if grant is None:
            # Its grant for us comes when it has our key (from our hello) and it owes us one;
            # if it sends us data before we have it, we ask for it then (open_data).
            return None
        ad = _blob(_s(self.fleet), _s(sender), e_pub, _s(self.sender), self.e_pub)
        try:
            plain = pair.grant_in.decrypt(grant[:12], grant[12:], ad)
        except InvalidTag:
            return "forged"
        g, session, floor = _GRANT_PLAIN.unpack(plain)
        if peer.current is not pair:  # proven fresh: it knows our key of this boot
            if peer.current is not None:
                peer.retired.add(peer.current.e_pub)
                peer.drop(peer.current, self.seq)
            peer.current = pair
            if peer.candidate is pair:
                peer.candidate = None
        if (sender, session) not in self.rx:
            # Everything at or below the floor was sealed before this grant: refused.
            rx = self.rx[sender, session] = RxSession(
                sender, ChaCha20Poly1305(g), pair, floor, _WINDOW_MASK, floor
            )
            pair.opens = True
            # What we got and could not open, our next hello asks for again; the originals
            # above the floor are refused from now on (at or below it they are anyway).
            held = self._missed.get((sender, session), deque())
            for seq in held:
                if seq > floor:
                    _admit(rx, seq)
                else:
                    rx.asked.add(seq)
            if held:
                self._answer()
            else:
                self._missed.pop((sender, session), None)
        return None

    # --- data ---------------------------------------------------------------------------------

    def _ad(
        self, channel: str, sender: str, type_name: str, seq: int, session: int, tags: bytes
    ) -> bytes:
        """The associated data of a message: :func:`_ad`, its head cached per channel."""
        key = (channel, sender, type_name)
        head = self._ad_heads.get(key)
        if head is None:
            if len(self._ad_heads) >= _AD_CACHE_MAX:
                self._ad_heads.clear()
            head = self._ad_heads[key] = _ad_head(channel, self.fleet, sender, type_name)
        return head + _SEQ_SESSION.pack(16, seq, session, len(tags)) + tags

    def seal(
        self, channel: str, type_name: str, payload: bytes, only: _Pair | None = None
    ) -> bytes:
        """Encrypt and authenticate one message for every peer (or ``only`` one)."""
        self.seq += 1
        seq = self.seq
        if only is None:
            self._backlog.append((seq, self._clock(), channel, type_name, payload))
        if self.roster_mode:
            pairs = [only] if only is not None else self._recipients()
            tags = b"".join(p.tag_out for p in pairs)
        else:
            pairs, tags = [], (only.tag_out if only is not None else b"")
        ad = self._ad(channel, self.sender, type_name, seq, self.session, tags)
        sealed = self._aead.encrypt(seq.to_bytes(12, "big"), payload, ad)
        cipher, tag = sealed[:-_TAG], sealed[-_TAG:]
        if self.roster_mode:
            digest = hashlib.blake2b(ad + sealed, digest_size=32).digest()
            tags = b"".join(
                p.tag_out + hashlib.blake2b(digest, key=p.mac_out, digest_size=_MAC).digest()
                for p in pairs
            )
        return self._writer.write(seq, self.session, type_name, cipher, tag + tags)

    def _recipients(self) -> list[_Pair]:
        return [
            p
            for peer in self._peers.values()
            for p in {id(q): q for q in (peer.current, peer.candidate) if q}.values()
        ]

    def _resend_backlog(self, resend: list[tuple[str, _Pair, list[int]]], now: float) -> None:
        """Re-send to peers the messages they got from us and could not open (no grant yet).

        The copies are addressed to that peer alone (no other member gets a message twice),
        and the peer refuses the originals from now on. A message that another boot of the
        same member held a grant for is never re-sent: that boot may have opened it, and a
        captured copy shown to a restarted member must not come back through us.
        """
        while self._backlog and now - self._backlog[0][1] > BACKLOG_S:
            self._backlog.popleft()
        for name, pair, missed in resend:
            wanted = set(missed)
            peer = self._peers.get(name)
            for seq, _, channel, type_name, payload in list(self._backlog):
                if seq not in wanted:
                    continue
                if peer is not None and peer.could_open(seq, pair):
                    if name in self._replays or len(self._replays) < _MISSED_MAX:
                        self._replays[name] = self._replays.get(name, 0) + 1
                    continue
                self._outgoing.append((channel, self.seal(channel, type_name, payload, only=pair)))

    def take_replays(self) -> dict[str, int]:
        """Per peer, how many messages it asked for that an earlier boot of it may have opened.

        Such a message reached the restarted peer again: a replay of captured traffic (or a
        copy in flight while it restarted). It is refused there and never sent again; the
        counts are since the last call.
        """
        replays, self._replays = self._replays, {}
        return replays

    def open_data(self, channel: str, env: envelope_t) -> Sealed | str:
        """Check and decrypt a data envelope; a :class:`Sealed` or a drop reason."""
        sender: str = env.sender
        session: int = env.stamp_us
        rx = self.rx.get((sender, session))
        if rx is None:
            missed = self._missed.get((sender, session))
            if missed is None and len(self._missed) < _MISSED_MAX:
                missed = self._missed[sender, session] = deque(maxlen=_MISSED_MAX)
            if missed is not None and 0 < env.seq < 1 << 63:
                missed.append(env.seq)  # our next hello asks for a grant and these again
            # Its grant is on its way if our key left a moment ago (it answers our hello):
            # ask only if it has not come by then.
            peer = self._peers.get(sender)
            sent = None
            if peer is not None:
                sent = max(
                    (
                        p.granted_at
                        for p in (peer.current, peer.candidate)
                        if p is not None and p.granted_at is not None
                    ),
                    default=None,
                )
            now = self._clock()
            self.want_hello(now if sent is None or sent > now else max(now, sent + GRANT_WAIT_S))
            return "no_session"
        mac: bytes = env.mac
        roster = self.credentials is not None
        if len(mac) < _TAG:
            return "forged"
        tag = mac[:_TAG]
        mine = None
        tags = b""
        if len(mac) > _TAG:  # recipient entries (a roster fleet, or a copy re-sent to one peer)
            tail = mac[_TAG:]
            step = _RECIPIENT + _MAC if roster else _RECIPIENT
            if len(tail) % step:
                return "forged"
            ours = rx.pair.tag_in
            heads = []
            for i in range(0, len(tail), step):
                head = tail[i : i + _RECIPIENT]
                heads.append(head)
                if mine is None and head == ours:
                    mine = tail[i : i + step]
            tags = b"".join(heads)
            if mine is None:
                return "not_for_us"
        elif roster:
            return "not_for_us"
        seq: int = env.seq
        if not 0 < seq < 1 << 63:
            return "forged"
        type_name: str = env.type
        ad = self._ad(channel, sender, type_name, seq, session, tags)
        sealed = env.payload + tag
        if roster:
            assert mine is not None
            digest = hashlib.blake2b(ad + sealed, digest_size=32).digest()
            want = hashlib.blake2b(digest, key=rx.pair.mac_in, digest_size=_MAC).digest()
            if not hmac.compare_digest(want, mine[_RECIPIENT:]):
                return "forged"
        try:
            plain = rx.aead.decrypt(seq.to_bytes(12, "big"), sealed, ad)
        except InvalidTag:
            return "forged"
        if seq <= rx.floor and self._sealed_before_grant(rx, session, seq):
            return "no_session"
        if not _admit(rx, seq):
            return "replayed"
        return Sealed(type_name, plain, seq, session)

    def _sealed_before_grant(self, rx: RxSession, session: int, seq: int) -> bool:
        """Ask for a copy of a message sealed before its sender's grant, which came first.

        Its sender seals and publishes a message outside its lock, so a grant it sends
        meanwhile (whose floor counts the message) can overtake it: the message then comes
        after the grant, at or below the floor, and without this would be refused as replayed
        and never re-sent. It is refused like every message at or below the floor, once asked
        for again like those that came before the grant (the sender re-sends a copy only if no
        other boot of ours could have opened it; docs/security.md).

        Returns:
            True if it is asked for (the first time it comes, while the sender may still hold
            it); False if it is a replay.
        """
        key = (rx.sender, session)
        if (
            seq in rx.asked
            or rx.floor - seq >= _BACKLOG_MAX  # the sender keeps no more
            or len(rx.asked) >= _MISSED_MAX
            or (key not in self._missed and len(self._missed) >= _MISSED_MAX)
        ):
            return False
        rx.asked.add(seq)
        self._missed.setdefault(key, deque(maxlen=_MISSED_MAX)).append(seq)
        self._answer()
        return True


def _ad(
    channel: str, fleet: str, sender: str, type_name: str, seq: int, session: int, tags: bytes
) -> bytes:
    """The associated data of a message: what its AEAD tag (and MACs) cover besides it."""
    return _blob(
        b"temoto-v2", _s(channel), _s(fleet), _s(sender), _s(type_name),
        struct.pack(">QQ", seq, session), tags,
    )  # fmt: skip


def _ad_head(channel: str, fleet: str, sender: str, type_name: str) -> bytes:
    """The first parts of :func:`_ad`, the same for every message of a sender on a channel."""
    return _blob(b"temoto-v2", _s(channel), _s(fleet), _s(sender), _s(type_name))


def _admit(rx: RxSession, seq: int) -> bool:
    """The IPsec replay window (RFC 4303 §3.4.3); True if ``seq`` is new."""
    if seq > rx.highest:
        shift = seq - rx.highest
        rx.bitmap = ((rx.bitmap << shift) | 1) & _WINDOW_MASK if shift < _WINDOW else 1
        rx.highest = seq
        return True
    behind = rx.highest - seq
    if behind >= _WINDOW or rx.bitmap >> behind & 1:
        return False
    rx.bitmap |= 1 << behind
    return True
