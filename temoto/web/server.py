"""The live view's HTTP server: a page, a JSON API and a Server-Sent Events stream.

:class:`LiveView` serves one engine on localhost from a :class:`~http.server.ThreadingHTTPServer`
on a named thread. Endpoints (all ``GET``; see ``docs/live-view.md``):

* ``/``: the page (inline CSS and JavaScript, nothing fetched from elsewhere);
* ``/api/graphs``: every run with its state and result;
* ``/api/graphs/<run>``: one run (URL-encoded name): nodes, edges, layout, logs, resources;
* ``/api/events``: a ``text/event-stream`` of engine events (:mod:`temoto.web.events`).

Threads: ``temoto-web`` accepts connections; each request runs on its own ``temoto-web-<n>``
thread (an event stream for as long as its client stays). Streams are bounded
(``max_clients``), sockets time out, and :meth:`LiveView.close` ends the streams, stops the
server and joins every one of these threads.
"""

from __future__ import annotations

import base64
import hashlib
import ipaddress
import itertools
import logging
import socket
import threading
from functools import cache
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Any, final
from urllib.parse import unquote, urlsplit

from temoto._closing import Closing
from temoto.errors import ConfigError, GraphNotFoundError
from temoto.web import _page
from temoto.web.events import EventHub
from temoto.web.view import graph_view, graphs_list, to_json

if TYPE_CHECKING:
    from temoto.core.engine import ActionEngine

__all__ = ["LiveView"]

logger = logging.getLogger(__name__)

_GRAPH_PREFIX = "/api/graphs/"


@cache
def _page_bytes() -> tuple[bytes, str]:
    """The page and its Content-Security-Policy (the inline script and style, by hash)."""

    def digest(text: str) -> str:
        return base64.b64encode(hashlib.sha256(text.encode()).digest()).decode()

    policy = (
        "default-src 'none'; "
        f"script-src 'sha256-{digest(_page.JS)}'; "
        f"style-src 'sha256-{digest(_page.CSS)}'; "
        "connect-src 'self'; img-src data:; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'"
    )
    return _page.page().encode(), policy


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Server(ThreadingHTTPServer):
    """A threading HTTP server whose request threads are named ``temoto-web-<n>``."""

    # server_close() joins the request threads (ThreadingMixIn keeps them when this is true)
    block_on_close = True
    daemon_threads = True

    def __init__(self, address: tuple[str, int], view: LiveView) -> None:
        self.view = view
        self._numbers = itertools.count(1)
        super().__init__(address, _Handler)

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        threading.current_thread().name = f"temoto-web-{next(self._numbers)}"
        super().process_request_thread(request, client_address)


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    #: Seconds a client may stay silent, or leave a write unread, before it is dropped.
    timeout = 10.0
    server_version = "TeMotoLiveView"
    sys_version = ""

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        logger.debug("%s %s", self.address_string(), format % args)

    def do_GET(self) -> None:
        view = self.server.view
        if not view._host_allowed(self.headers.get("Host", "")):
            self._send_json(HTTPStatus.MISDIRECTED_REQUEST, {"error": "unexpected Host header"})
            return
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            body, policy = _page_bytes()
            self._send(HTTPStatus.OK, "text/html; charset=utf-8", body, policy)
        elif path == "/api/graphs":
            self._send_json(HTTPStatus.OK, graphs_list(view.engine))
        elif path.startswith(_GRAPH_PREFIX) and len(path) > len(_GRAPH_PREFIX):
            name = unquote(path[len(_GRAPH_PREFIX) :])
            try:
                answer = graph_view(view.engine, name)
            except GraphNotFoundError:
                self._send_json(HTTPStatus.NOT_FOUND, {"error": f"no graph run named {name!r}"})
                return
            self._send_json(HTTPStatus.OK, answer)
        elif path == "/api/events":
            self._stream(view)
        else:
            self._send_json(HTTPStatus.NOT_FOUND, {"error": "not found"})

    def _send(
        self, status: HTTPStatus, kind: str, body: bytes, policy: str = "default-src 'none'"
    ) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", policy)
        self.end_headers()
        self.wfile.write(body)

    def _send_json(self, status: HTTPStatus, answer: Any) -> None:
        self._send(status, "application/json", to_json(answer).encode())

    def _stream(self, view: LiveView) -> None:
        sub = view._hub.subscribe()
        if sub is None:
            self.send_response(HTTPStatus.SERVICE_UNAVAILABLE)
            self.send_header("Retry-After", "5")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        self.close_connection = True
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            # "hello" tells a (re)connected page to fetch fresh snapshots
            self.wfile.write(b'retry: 1000\ndata: {"kind": "hello"}\n\n')
            while True:
                batch = sub.get(view.heartbeat_s)
                if batch.closed:
                    break
                chunks = [f"id: {e['seq']}\ndata: {to_json(e)}\n\n" for e in batch.events]
                if batch.resync:
                    chunks.append('data: {"kind": "resync"}\n\n')
                self.wfile.write("".join(chunks).encode() if chunks else b": keep-alive\n\n")
        except OSError:  # the client went away (reset, broken pipe, timeout)
            pass
        finally:
            sub.cancel()


@final
class LiveView(Closing):
    """Serves a live picture of an engine's graph runs to a browser (started at once).

    Args:
        engine: The engine to show; the view adds an instrument to it.
        host: Address to listen on. The default serves this machine only; on a loopback
            address, requests must also name a loopback host (no DNS rebinding).
        port: Port to listen on (0: any free port; see :attr:`url`).
        max_clients: Event streams (open pages) served at once; more get HTTP 503.
        heartbeat_s: Seconds between keep-alive comments on an idle event stream (how soon a
            vanished client is noticed).

    Raises:
        ConfigError: If the address cannot be bound (a port out of range, or one in use);
            the message names the address and why, in one line.
    """

    def __init__(
        self,
        engine: ActionEngine,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        max_clients: int = 8,
        heartbeat_s: float = 10.0,
    ) -> None:
        self.engine = engine
        self.heartbeat_s = heartbeat_s
        self._hub = EventHub(max_clients=max_clients)
        server_class = _Server6 if ":" in host else _Server
        try:
            self._httpd = server_class((host, port), self)
        except (OSError, OverflowError) as err:  # out of range: OverflowError; in use: OSError
            why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
            raise ConfigError(f"live view: cannot listen on {host}:{port}: {why}") from None
        self.host = host
        self.port: int = self._httpd.server_address[1]
        self._loopback = _is_loopback(host)
        self._closed = False
        engine.add_instrument(self._hub)
        self._thread = threading.Thread(
            target=self._httpd.serve_forever,
            kwargs={"poll_interval": 0.1},
            name="temoto-web",
        )
        self._thread.start()
        logger.info("live view at %s", self.url)

    @property
    def url(self) -> str:
        """The page's address, e.g. ``http://127.0.0.1:8765/``."""
        host = self.host
        if host in ("", "0.0.0.0"):
            host = "127.0.0.1"
        elif host == "::":
            host = "::1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

    @property
    def clients(self) -> int:
        """Event streams open now."""
        return self._hub.subscribers

    def _host_allowed(self, header: str) -> bool:
        if not self._loopback:
            return True
        host, _, port = header.rpartition(":") if not header.endswith("]") else (header, "", "")
        host = host.strip("[]")
        return _is_loopback(host) and port == str(self.port)

    def close(self) -> None:
        """End the event streams, stop serving and join every thread. Idempotent.

        The engine keeps the view's instrument, which does nothing from now on.

        Returns:
            None.

        Raises:
            Nothing.
        """
        if self._closed:
            return
        self._closed = True
        self._hub.close()
        self._httpd.shutdown()
        self._thread.join()
        self._httpd.server_close()  # closes the socket, joins the request threads
