"""Zenoh transport: the fleet's channels as key expressions on a Zenoh session.

Where LCM's multicast stops at the network segment, Zenoh carries the same envelopes through
routers, across subnets and over TCP (docs/zenoh.md says when to pick which). A channel
``C`` becomes the key expression ``<prefix>/C`` (``/`` inside a channel becomes ``~``, so every
channel is one chunk and channel names need no rules beyond :func:`~temoto.transport.base.\
check_channel`'s); the bytes travel unchanged, so the authenticated envelopes of
:mod:`temoto.transport.auth` and everything above them work as over LCM.

A transport declares **one** Zenoh subscriber, on ``<prefix>/**``, when its first subscription
is made, and sorts what arrives by key expression. One subscriber because Zenoh keeps the order
of one sender's messages within a subscriber: with a subscriber per channel, messages of one
sender on two channels could be handled in another order than sent, which LCM never does. The
price is LCM's: every member receives every channel under its prefix.

The subscriber delivers into a Zenoh ring channel (:data:`RECEIVE_CHANNEL_CAPACITY`), and one
thread of ours, ``temoto-zenoh``, takes the messages from it (waiting in Zenoh's ``recv``, which
releases the GIL, as LCM's thread waits in ``handle_timeout``), moves everything that has
arrived into the queues of the subscriptions of its channel (bounded when ``queue_capacity`` is
given: the oldest is dropped), and hands them to the handlers in arrival order: handlers never
run on the publisher's thread (a ``put`` delivers to this session's own subscriber on the
caller's thread), as with LCM. A message thus crosses one thread hand-off in the receiver, as
over LCM: a Python callback would be run by zenoh-python on a thread of its own (or, with
``indirect=False``, on Zenoh's network thread, waiting there for the GIL: a third of the
throughput, and Zenoh dropped messages of a flood), and then be handed to ours, which cost about
0.04 ms a message on loopback (bench/README.md, "Over Zenoh, second part").

Subscribing never races the receive thread (LCM's binding can: :mod:`temoto.transport.lcm`):
a subscription of ours is an entry in the transport's own lists, changed under the lock that
thread dispatches under, and the one Zenoh subscriber is declared under it before that thread
first reads from it.

The URL (:func:`parse_zenoh_url`)::

    zenoh:                                  peer, finds peers by multicast scouting (one LAN)
    zenoh:tcp/10.0.0.1:7447[,tcp/...]       client of the router(s) at these endpoints
    zenoh:tcp/10.0.0.1:7447?mode=peer       peer that also connects to these endpoints
    zenoh:/etc/temoto/zenoh.json5           a Zenoh configuration file, used as it is
    ...?listen=tcp/0.0.0.0:7448             also listen there (several: comma-separated)
    ...?prefix=site1/fleet                  key expressions under this prefix (default temoto)
    ...?timeout=5                           a client tries its routers this long (seconds)

The ``eclipse-zenoh`` wheel (the ``zenoh`` extra) is imported when a transport is created,
never when this module is imported.
"""

from __future__ import annotations

import collections
import json
import logging
import re
import threading
import urllib.parse
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, final

from temoto.errors import TransportError
from temoto.transport.base import Handler, QueuedSubscription, Transport

if TYPE_CHECKING:
    from types import ModuleType

__all__ = [
    "DEFAULT_CONNECT_TIMEOUT_S",
    "DEFAULT_PREFIX",
    "DEFAULT_ROUTER_LISTEN",
    "INSTALL_HINT",
    "RECEIVE_CHANNEL_CAPACITY",
    "ZENOH_SCHEME",
    "ZenohSubscription",
    "ZenohTransport",
    "ZenohUrl",
    "channel_key",
    "config_endpoints",
    "import_zenoh",
    "open_router",
    "parse_zenoh_url",
]

#: URL scheme of :class:`ZenohTransport`.
ZENOH_SCHEME: Final = "zenoh:"

#: The key expression prefix of the fleet's channels unless the URL gives ``prefix=``.
DEFAULT_PREFIX: Final = "temoto"

#: Seconds a client keeps trying to reach its routers when it opens, unless ``timeout=`` says.
#: Robots may start before their router, and on a lossy link the first attempt may be lost.
DEFAULT_CONNECT_TIMEOUT_S: Final = 5.0

#: The most messages that wait in a transport's Zenoh channel while a handler runs; the thread
#: moves them to the subscriptions' own queues before every handler call. When more arrive
#: during one handler call the oldest are dropped (by Zenoh, uncounted). Zenoh allocates the
#: channel as it fills, not up front.
RECEIVE_CHANNEL_CAPACITY: Final = 65_536

#: What to install for the Zenoh transport and ``temoto router``.
INSTALL_HINT: Final = "pip install 'temoto[zenoh]' (the eclipse-zenoh package)"

logger = logging.getLogger(__name__)

_MODES: Final = ("peer", "client")
_RETRY: Final = '{"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}'
_CONFIG_SUFFIXES: Final = (".json5", ".json", ".yaml", ".yml")
# Zenoh endpoints are <protocol>/<address>[#<config>] (tcp, udp, quic, tls, ws, unixsock-stream).
_ENDPOINT_RE: Final = re.compile(r"[a-z][a-z0-9-]*/[^\s,?&#]+(#[^\s,?&]*)?")
# A prefix is one or more key-expression chunks without wildcards or special characters.
_PREFIX_RE: Final = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")


def import_zenoh() -> ModuleType:
    """Import the ``zenoh`` module of the ``eclipse-zenoh`` wheel.

    Returns:
        The module.

    Raises:
        TransportError: If it is not installed, naming the pip command that installs it.
    """
    try:
        import zenoh
    except ImportError as err:
        raise TransportError(f"the Zenoh transport needs eclipse-zenoh: {INSTALL_HINT}") from err
    return zenoh


def channel_key(prefix: str, channel: str) -> str:
    """The key expression a channel travels on.

    Args:
        prefix: The fleet's key prefix.
        channel: A checked channel name.

    Returns:
        ``<prefix>/<channel>``, with every ``/`` of the channel replaced by ``~`` (a character
        no channel may contain, so the mapping is one to one).
    """
    return f"{prefix}/{channel.replace('/', '~')}"


@dataclass(frozen=True)
class ZenohUrl:
    """A parsed ``zenoh:`` URL (see :func:`parse_zenoh_url`).

    Attributes:
        mode: ``"peer"`` or ``"client"``; None when a configuration file decides.
        connect: Endpoints to connect to (routers, or peers).
        listen: Endpoints to listen on.
        prefix: The key expression prefix of the channels.
        config_file: A Zenoh configuration file, or None.
        connect_timeout_s: Seconds a client keeps trying to reach its routers when it opens
            (0: one attempt).
    """

    mode: str | None
    connect: tuple[str, ...]
    listen: tuple[str, ...]
    prefix: str
    config_file: str | None
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S

    def config(self, zenoh: Any) -> Any:
        """Build the ``zenoh.Config`` for this URL.

        Args:
            zenoh: The imported ``zenoh`` module.

        Returns:
            The configuration.

        Raises:
            TransportError: If the configuration file cannot be read or an endpoint is
                refused.
        """
        try:
            if self.config_file is not None:
                conf = zenoh.Config.from_file(self.config_file)
            else:
                conf = zenoh.Config()
                conf.insert_json5("mode", json.dumps(self.mode))
                if self.mode == "client":
                    # A client talks to the routers it was given, not to whatever answers on
                    # the multicast scouting group; it tries them for a while, every 0.1 s at
                    # first, then less often (up to every second).
                    conf.insert_json5("scouting/multicast/enabled", "false")
                    conf.insert_json5(
                        "connect/timeout_ms", str(round(self.connect_timeout_s * 1000))
                    )
                    conf.insert_json5("connect/retry", _RETRY)
            if self.connect:
                conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
            if self.listen:
                conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        except zenoh.ZError as err:
            what = self.config_file or "the URL's endpoints"
            raise TransportError(f"Zenoh configuration: {what}: {_reason(err)}") from err
        return conf


def parse_zenoh_url(url: str) -> ZenohUrl:
    """Parse a ``zenoh:`` fleet URL.

    Args:
        url: ``zenoh:[ENDPOINT[,ENDPOINT...]][?mode=peer|client][&listen=ENDPOINT[,...]]
            [&prefix=KEY][&timeout=SECONDS]``, or ``zenoh:FILE`` for a Zenoh configuration
            file (a name ending in ``.json5``, ``.json``, ``.yaml`` or ``.yml``; only ``prefix``
            and ``listen`` may follow). Without endpoints the mode is peer (multicast scouting
            finds the others), with them client (the endpoints are routers); ``mode=peer``
            makes a peer that also connects to them. ``timeout`` is how long a client keeps
            trying to reach its routers when it opens (default
            :data:`DEFAULT_CONNECT_TIMEOUT_S`; 0: once).

    Returns:
        The parsed URL.

    Raises:
        ValueError: If the URL is malformed, naming the part at fault.
    """
    if not url.startswith(ZENOH_SCHEME):
        raise ValueError(f"{url!r} is not a zenoh: URL")
    body, _, query = url[len(ZENOH_SCHEME) :].partition("?")
    params: dict[str, str] = {}
    for item in query.split("&") if query else ():
        name, eq, value = item.partition("=")
        if not eq or name not in ("mode", "listen", "prefix", "timeout"):
            raise ValueError(
                f"{url!r}: unknown parameter {item!r} (expected mode=, listen=, prefix= or"
                " timeout=)"
            )
        if name in params:
            raise ValueError(f"{url!r}: {name}= given twice")
        params[name] = urllib.parse.unquote(value)
    prefix = params.get("prefix", DEFAULT_PREFIX)
    if not _PREFIX_RE.fullmatch(prefix):
        raise ValueError(
            f"{url!r}: prefix {prefix!r} must be key-expression chunks of A-Z a-z 0-9 _ . -"
            " joined by /"
        )
    listen = _endpoints(url, "listen", params["listen"]) if "listen" in params else ()
    timeout = DEFAULT_CONNECT_TIMEOUT_S
    if "timeout" in params:
        try:
            timeout = float(params["timeout"])
        except ValueError:
            timeout = -1.0
        if not 0 <= timeout <= 3600:
            raise ValueError(
                f"{url!r}: timeout must be 0 to 3600 seconds, not {params['timeout']!r}"
            )
    if body.endswith(_CONFIG_SUFFIXES):
        for name in ("mode", "timeout"):
            if name in params:
                raise ValueError(f"{url!r}: with a configuration file, the file sets the {name}")
        return ZenohUrl(None, (), listen, prefix, body)
    connect = _endpoints(url, "endpoint", body) if body else ()
    mode = params.get("mode", "client" if connect else "peer")
    if mode not in _MODES:
        raise ValueError(f"{url!r}: mode must be peer or client, not {mode!r}")
    if mode == "client" and not connect:
        raise ValueError(f"{url!r}: a client needs the endpoint of a router (zenoh:tcp/HOST:7447)")
    return ZenohUrl(mode, connect, listen, prefix, None, timeout)


def _endpoints(url: str, what: str, text: str) -> tuple[str, ...]:
    items = tuple(text.split(","))
    for item in items:
        if not _ENDPOINT_RE.fullmatch(item):
            raise ValueError(f"{url!r}: {what} {item!r} is not a Zenoh endpoint like tcp/HOST:PORT")
    return items


def config_endpoints(path: str, which: str) -> list[str]:
    """The endpoints a Zenoh configuration file names.

    Args:
        path: The configuration file.
        which: ``"listen"`` or ``"connect"``.

    Returns:
        Its ``<which>/endpoints`` (those of every mode, when given per mode); empty when the
        file cannot be read or names none.
    """
    try:
        zenoh = import_zenoh()
    except TransportError:
        return []
    try:
        return _endpoints_of(zenoh.Config.from_file(path), which)
    except (zenoh.ZError, ValueError, TypeError):
        return []


def _endpoints_of(conf: Any, which: str) -> list[str]:
    endpoints = json.loads(conf.get_json(f"{which}/endpoints"))
    if isinstance(endpoints, dict):  # endpoints per mode of the session
        endpoints = [e for listed in endpoints.values() for e in listed]
    return [str(e) for e in endpoints or ()]


def _open_hint(conf: Any) -> str:
    """What to check when a session with this configuration could not open."""
    try:
        mode = json.loads(conf.get_json("mode"))
        endpoints = _endpoints_of(conf, "connect")
    except (ValueError, TypeError, AttributeError):  # a configuration Zenoh took but we cannot read
        return ""
    hints = []
    if mode == "client":
        hints.append("is a router running there? `temoto router` starts one")
    if any(str(e).startswith(("tls/", "quic/")) for e in endpoints):
        hints.append(
            "for TLS, transport/link/tls/root_ca_certificate must be the CA that signed the"
            " router's certificate, which must name the endpoint's host; for mutual TLS also"
            " enable_mtls and this robot's connect_certificate and connect_private_key"
            " (docs/zenoh.md)"
        )
    return f" ({'; '.join(hints)})" if hints else ""


def _reason(err: BaseException) -> str:
    """A Zenoh error's message without the Rust source location it ends with."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(err)).strip()


@final
class ZenohSubscription(QueuedSubscription):
    """A subscription of a :class:`ZenohTransport`, with its own bounded queue.

    Attributes:
        channel: The channel name.
        key: The key expression it listens on.
        queue_capacity: The most messages that wait for the handler (None: no limit).
    """

    def __init__(
        self,
        transport: ZenohTransport,
        channel: str,
        key: str,
        handler: Handler,
        queue_capacity: int | None,
    ) -> None:
        super().__init__(channel, handler, queue_capacity)
        self.key = key
        self._transport = transport

    def _on_unsubscribe(self) -> None:
        self._transport._remove(self)


@final
class ZenohTransport(Transport):
    """A transport over a Zenoh session (peer or client; see :func:`parse_zenoh_url`).

    Args:
        url: A ``zenoh:`` URL.

    Attributes:
        url: The URL it was opened with.
        prefix: The key expression prefix of its channels.

    Raises:
        ValueError: If the URL is malformed.
        TransportError: If eclipse-zenoh is missing, or the session cannot be opened (no
            router at a client's endpoints, an address in use, a bad configuration file).
    """

    def __init__(self, url: str = ZENOH_SCHEME) -> None:
        parsed = parse_zenoh_url(url)
        super().__init__()
        self.url = url
        self.prefix = parsed.prefix
        zenoh = import_zenoh()
        conf = parsed.config(zenoh)
        try:
            self._session: Any = zenoh.open(conf)
        except zenoh.ZError as err:
            raise TransportError(
                f"Zenoh cannot open {url!r}: {_reason(err)}{_open_hint(conf)}"
            ) from err
        self._zerror: type[Exception] = zenoh.ZError
        self._ring: Any = zenoh.handlers.RingChannel
        self._cond = threading.Condition()
        # Guarded by _cond: the live subscriptions by key expression, the Zenoh subscriber
        # once declared, and one token per message waiting in a subscription's queue, in
        # arrival order (a full queue drops its oldest message and keeps its token count, as
        # InProcessTransport does). Only the thread fills the queues.
        self._by_key: dict[str, list[ZenohSubscription]] = {}
        self._zsub: Any = None
        self._ready: collections.deque[ZenohSubscription] = collections.deque()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="temoto-zenoh", daemon=True)
        self._thread.start()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<ZenohTransport {self.url!r} {state}>"

    def peers(self) -> list[str]:
        """The Zenoh ids of the routers and peers this session is connected to.

        Returns:
            Their ids as hex strings (routers first); empty when closed or alone.
        """
        if self.closed:
            return []
        try:
            info = self._session.info
            return [str(z) for z in (*info.routers_zid(), *info.peers_zid())]
        except self._zerror:
            return []

    # --- Transport hooks ----------------------------------------------------------------------

    def _publish(self, channel: str, data: bytes) -> None:
        try:
            self._session.put(channel_key(self.prefix, channel), data)
        except self._zerror as err:
            if self.closed:
                raise TransportError("ZenohTransport is closed") from err
            raise TransportError(f"Zenoh put on {channel!r} failed: {_reason(err)}") from err

    def _subscribe(
        self, channel: str, handler: Handler, queue_capacity: int | None
    ) -> ZenohSubscription:
        key = channel_key(self.prefix, channel)
        sub = ZenohSubscription(self, channel, key, handler, queue_capacity)
        with self._cond:
            if self._stopping:
                raise TransportError("ZenohTransport is closed")
            if self._zsub is None:
                wildcard = f"{self.prefix}/**"
                try:
                    self._zsub = self._session.declare_subscriber(
                        wildcard, self._ring(RECEIVE_CHANNEL_CAPACITY)
                    )
                except self._zerror as err:
                    raise TransportError(
                        f"Zenoh subscribe to {wildcard!r} failed: {_reason(err)}"
                    ) from err
                self._cond.notify_all()  # the thread starts receiving
            self._by_key.setdefault(key, []).append(sub)
        return sub

    def _close(self) -> None:
        with self._cond:
            self._stopping = True
            subs = [sub for subs in self._by_key.values() for sub in subs]
            self._by_key.clear()
            self._ready.clear()
            zsub, self._zsub = self._zsub, None
            self._cond.notify_all()
        for sub in subs:
            sub.detach()
        try:
            if zsub is not None:
                zsub.undeclare()  # closes its channel: the thread's recv() returns
        except self._zerror as err:
            logger.warning("undeclaring the Zenoh subscriber: %s", _reason(err))
        if threading.current_thread() is not self._thread:
            self._thread.join()
        try:
            self._session.close()
        except self._zerror as err:
            # Nothing to recover: the session is gone either way.
            logger.warning("closing the Zenoh session: %s", _reason(err))

    # --- internals ----------------------------------------------------------------------------

    def _take(self, samples: list[Any]) -> None:
        """Queue messages for the subscriptions of their channels, in arrival order."""
        with self._cond:
            if self._stopping:
                return
            for sample in samples:
                subs = self._by_key.get(str(sample.key_expr))
                if subs:
                    data = sample.payload.to_bytes()
                    for sub in subs:
                        sub.offer(data, self._ready)
            self._cond.notify_all()  # whoever watches the queues

    def _remove(self, sub: ZenohSubscription) -> None:
        with self._cond:
            subs = self._by_key.get(sub.key)
            if subs is not None and sub in subs:
                subs.remove(sub)
                if not subs:
                    del self._by_key[sub.key]
            sub.discard_pending()  # its tokens stay in _ready; the thread skips them

    def _run(self) -> None:
        with self._cond:
            while self._zsub is None and not self._stopping:
                self._cond.wait()
            if self._zsub is None:
                return
            channel = self._zsub.handler
        try:
            while self._step(channel):
                pass
        except self._zerror:
            if not self._stopping:  # not closed by us: the session ended under us
                logger.error("the Zenoh subscriber of %r closed; receiving stopped", self.url)

    def _step(self, channel: Any) -> bool:
        """Take what Zenoh has (waiting for it when nothing is queued), hand one message on.

        Returns:
            False once the transport is closing.

        Raises:
            zenoh.ZError: When the channel has closed (the subscriber was undeclared).
        """
        with self._cond:
            idle = not self._ready
        # waits in Zenoh without the GIL when idle; then everything that has come meets the
        # queues' bounds before the next handler runs
        arrived = [channel.recv()] if idle else []
        while (sample := channel.try_recv()) is not None:
            arrived.append(sample)
        if arrived:
            self._take(arrived)
        with self._cond:
            if self._stopping:
                return False
            if not self._ready:
                return True
            sub = self._ready.popleft()
            data = sub.take()
            if data is None:
                return True
        self._deliver(sub, sub.channel, data)
        return True


#: Where ``temoto router`` listens unless told otherwise: Zenoh's own router port, every address.
DEFAULT_ROUTER_LISTEN: Final = ("tcp/0.0.0.0:7447",)


def open_router(
    listen: tuple[str, ...] = DEFAULT_ROUTER_LISTEN,
    *,
    connect: tuple[str, ...] = (),
    config_file: str | None = None,
) -> Any:
    """Open a Zenoh session in router mode in this process (what ``temoto router`` runs).

    Clients (``zenoh:tcp/HOST:PORT``) and peers reach each other through it; it forwards
    messages without opening them, so the fleet's HMAC envelopes stay end to end.

    Args:
        listen: Endpoints to listen on.
        connect: Endpoints of other routers to connect to (a chain of routers).
        config_file: A Zenoh configuration file to start from (its mode is overridden to
            router; ``listen`` and ``connect`` are added when not empty).

    Returns:
        The ``zenoh.Session``; ``close()`` it to stop routing.

    Raises:
        ValueError: If an endpoint is malformed.
        TransportError: If eclipse-zenoh is missing or the router cannot start (an address
            in use, a bad configuration file).
    """
    for what, items in (("listen", listen), ("connect", connect)):
        for item in items:
            if not _ENDPOINT_RE.fullmatch(item):
                raise ValueError(f"{what} {item!r} is not a Zenoh endpoint like tcp/HOST:PORT")
    zenoh = import_zenoh()
    try:
        conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        conf.insert_json5("mode", '"router"')
        if listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except zenoh.ZError as err:
        raise TransportError(
            f"Zenoh router configuration {config_file or ''}: {_reason(err)}"
        ) from err
    try:
        return zenoh.open(conf)
    except zenoh.ZError as err:
        where = ", ".join(listen) or "its configured endpoints"
        raise TransportError(f"Zenoh router cannot listen on {where}: {_reason(err)}") from err
