"""The live view's HTTP server: a page, a JSON API, a Server-Sent Events stream, controls.

:class:`LiveView` serves one engine on localhost from a :class:`~http.server.ThreadingHTTPServer`
on a named thread. Endpoints (see ``docs/live-view.md``):

* ``GET /``: the page (inline CSS and JavaScript, nothing fetched from elsewhere);
* ``GET /api/graphs``: every run with its state and result;
* ``GET /api/graphs/<run>``: one run (URL-encoded name): nodes, edges, layout, logs,
  resources, timeline;
* ``GET /api/indexed``: the graphs the engine can start by name;
* ``GET /api/robot``: the Robot Manager's robot (:mod:`temoto.web.robot`), or null;
* ``GET /api/displays``: the Visualization Manager's loaded displays with their newest
  messages (:mod:`temoto.web.displays`), one panel each on the page;
* ``GET /api/events``: a ``text/event-stream`` of engine events (:mod:`temoto.web.events`);
* ``POST /api/start`` (``{"graph": name}``), ``POST /api/graphs/<run>/pause|resume|stop``:
  the controls. A write needs the view's token in the ``X-TeMoto-Token`` header (never a
  cookie, so another site cannot make a browser send it), a same-origin ``Origin`` when the
  browser sends one, and a JSON body; anything else is refused with 403.

Threads: ``temoto-web`` accepts connections; each request runs on its own ``temoto-web-<n>``
thread (an event stream for as long as its client stays); ``temoto-web-robot`` samples the
robot. Streams are bounded (``max_clients``), sockets time out, and :meth:`LiveView.close`
ends the streams, stops the server and joins every one of these threads.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import ipaddress
import itertools
import json
import logging
import secrets
import socket
import threading
from functools import cache
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Any, final
from urllib.parse import unquote, urlsplit

from temoto._closing import Closing
from temoto.errors import ConfigError, GraphNotFoundError, TemotoError
from temoto.web import _page
from temoto.web.displays import DisplayWatch
from temoto.web.events import EventHub
from temoto.web.robot import RobotWatch
from temoto.web.view import edge_status, graph_picture, graph_view, graphs_list, to_json

if TYPE_CHECKING:
    from temoto.core.engine import ActionEngine

__all__ = ["COMMANDS", "LiveView", "Site", "operator_command"]

logger = logging.getLogger(__name__)

_GRAPH_PREFIX = "/api/graphs/"
_CONTROLS = ("pause", "resume", "stop")

#: Header that carries the write token.
TOKEN_HEADER = "X-TeMoto-Token"

#: Largest request body a write may have.
MAX_BODY = 4096


@cache
def _page_bytes(mode: str) -> tuple[bytes, str]:
    """The page in a mode (``live``/``replay``) and its Content-Security-Policy (by hash)."""

    def digest(text: str) -> str:
        return base64.b64encode(hashlib.sha256(text.encode()).digest()).decode()

    policy = (
        "default-src 'none'; "
        f"script-src 'sha256-{digest(_page.js())}'; "
        f"style-src 'sha256-{digest(_page.css())}'; "
        "connect-src 'self'; img-src data:; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'"
    )
    return _page.page(mode).encode(), policy


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


#: The states of a run that has ended.
_ENDED_STATES = frozenset({"FINISHED", "STOPPED", "ERROR", "HALTED"})


def _state_of(result: str | None) -> str:
    """An ended run's state from its result (as the engine's ``_end_run`` sets it)."""
    return {"on_stopped": "STOPPED", "on_error": "ERROR", "on_halted": "HALTED"}.get(
        result or "", "FINISHED"
    )


def _ended_state(picture: dict[str, Any] | None, result: str | None) -> str:
    """An earlier run's state: its picture's if that was taken after its end."""
    state = picture.get("state") if picture is not None else None
    return state if state in _ENDED_STATES else _state_of(result)


#: The operator's commands: ``start`` names an indexed graph, the others a run.
COMMANDS = ("start", *_CONTROLS)


def operator_command(engine: ActionEngine, verb: str, target: Any) -> tuple[HTTPStatus, Any]:
    """Carry out one operator command, with the checks of the live view's controls.

    The one place the page's buttons and the Foxglove server's services
    (:mod:`temoto.managers.visualization.commands`) start, pause, resume and stop graphs;
    the caller has checked the token.

    Args:
        engine: The engine.
        verb: ``start`` (``target``: an indexed graph's name), ``pause``, ``resume`` or
            ``stop`` (``target``: a run's name).
        target: The graph or run (anything but a non-empty string is refused).

    Returns:
        The HTTP status and the JSON answer: ``{"run": name}`` for a start,
        ``{"run": name, "done": verb}`` for the others, ``{"error": why}`` when refused
        (400: no name; 404: no such graph or run; 409: not in a state for it).
    """
    if verb not in COMMANDS:
        return HTTPStatus.BAD_REQUEST, {"error": f"unknown command {verb!r}"}
    if not isinstance(target, str) or not target:
        why = "name a graph" if verb == "start" else "name a run"
        return HTTPStatus.BAD_REQUEST, {"error": why}
    try:
        if verb == "start":
            run = engine.start(target)
            logger.info("operator: started %s", run)
            return HTTPStatus.OK, {"run": run}
        if verb == "pause":
            engine.pause(target)
        elif verb == "resume":
            engine.resume(target)
        else:
            with contextlib.suppress(TimeoutError):  # answer now; the page sees it end
                engine.stop(target, timeout=0.0)
    except GraphNotFoundError as err:
        return HTTPStatus.NOT_FOUND, {"error": str(err)}
    except TemotoError as err:  # not RUNNING, already active, a bad graph, ...
        return HTTPStatus.CONFLICT, {"error": f"{type(err).__name__}: {err}"}
    logger.info("operator: %s %s", verb, target)
    return HTTPStatus.OK, {"run": target, "done": verb}


class _Server(ThreadingHTTPServer):
    """A threading HTTP server whose request threads are named ``temoto-web-<n>``."""

    # server_close() joins the request threads (ThreadingMixIn keeps them when this is true)
    block_on_close = True
    daemon_threads = True

    def __init__(self, address: tuple[str, int], site: Site) -> None:
        self.site = site
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
    #: The methods answered (``OPTIONS`` and a 405 name them in ``Allow``).
    allowed = "GET, HEAD, POST, OPTIONS"

    def version_string(self) -> str:
        """The Server header: the name alone (the base class adds a space and sys_version)."""
        return self.server_version

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """Every error as JSON (``{"error": ...}``), as the API's own; never an HTML page."""
        try:
            status = HTTPStatus(code)
        except ValueError:
            status = HTTPStatus.INTERNAL_SERVER_ERROR
        self.close_connection = True
        self.send_json(status, {"error": message or status.phrase})

    def do_HEAD(self) -> None:
        """A GET's headers without its body (an event stream: its headers, then the end)."""
        self.do_GET()

    def do_OPTIONS(self) -> None:
        """The methods the server answers (no CORS: another origin gets nothing more)."""
        self.send_response(HTTPStatus.NO_CONTENT)
        self.send_header("Allow", self.allowed)
        self.send_header("Content-Length", "0")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()

    def _not_allowed(self) -> None:
        self.close_connection = True
        self.send_response(HTTPStatus.METHOD_NOT_ALLOWED)
        self.send_header("Allow", self.allowed)
        body = to_json({"error": f"{self.command} is not allowed"}).encode()
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_PUT(self) -> None:
        self._not_allowed()

    def do_DELETE(self) -> None:
        self._not_allowed()

    def do_PATCH(self) -> None:
        self._not_allowed()

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base's name
        logger.debug("%s %s", self.address_string(), format % args)

    def do_GET(self) -> None:
        site = self.server.site
        if not site._host_allowed(self.headers.get("Host", "")):
            self.send_json(HTTPStatus.MISDIRECTED_REQUEST, {"error": "unexpected Host header"})
            return
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            body, policy = _page_bytes(site.mode)
            self.send(HTTPStatus.OK, "text/html; charset=utf-8", body, policy)
        elif not site._get(self, path):
            self.send_json(HTTPStatus.NOT_FOUND, {"error": "not found"})

    def do_POST(self) -> None:
        site = self.server.site
        refusal = site._write_refusal(self.headers)
        if refusal is not None:
            status, why = refusal
            self.close_connection = True
            self.send_json(status, {"error": why})
            return
        try:
            length = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_BODY:
            self.close_connection = True
            self.send_json(HTTPStatus.BAD_REQUEST, {"error": "bad Content-Length"})
            return
        raw = self.rfile.read(length) if length else b"{}"
        try:
            body = json.loads(raw)
        except ValueError:
            body = None
        if not isinstance(body, dict):
            self.send_json(HTTPStatus.BAD_REQUEST, {"error": "the body must be a JSON object"})
            return
        path = urlsplit(self.path).path
        if not site._post(self, path, body):
            self.send_json(HTTPStatus.NOT_FOUND, {"error": "not found"})

    def send(
        self, status: HTTPStatus, kind: str, body: bytes, policy: str = "default-src 'none'"
    ) -> None:
        """Send a whole answer (never cached, never sniffed)."""
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", policy)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def send_json(self, status: HTTPStatus, answer: Any) -> None:
        """Send a JSON answer."""
        self.send(status, "application/json", to_json(answer).encode())

    def stream(self, hub: EventHub, heartbeat_s: float) -> None:
        """Serve an event stream until the client leaves or the hub closes."""
        sub = hub.subscribe()
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
            if self.command == "HEAD":
                return
            # "hello" tells a (re)connected page to fetch fresh snapshots
            self.wfile.write(b'retry: 1000\ndata: {"kind": "hello"}\n\n')
            while True:
                batch = sub.get(heartbeat_s)
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


class Site(Closing):
    """The part every page server shares: the socket, its thread, Host and write checks.

    Subclasses (:class:`LiveView`, :class:`~temoto.web.replay.ReplayView`) answer paths in
    :meth:`_get` and :meth:`_post`.

    Args:
        host: Address to listen on. On a loopback address, requests must also name a
            loopback host with this port (no DNS rebinding).
        port: Port to listen on (0: any free port).
        token: The write token (None: a new random one; ``""``: writes are refused).

    Raises:
        ConfigError: If the address cannot be bound (a port out of range, or one in use);
            the message names the address and why, in one line.
    """

    #: The page's mode (``live`` or ``replay``).
    mode = "live"

    def __init__(self, host: str, port: int, token: str | None) -> None:
        self.host = host
        self.token: str = secrets.token_urlsafe(24) if token is None else token
        server_class = _Server6 if ":" in host else _Server
        try:
            self._httpd = server_class((host, port), self)
        except (OSError, OverflowError) as err:  # out of range: OverflowError; in use: OSError
            why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
            raise ConfigError(f"live view: cannot listen on {host}:{port}: {why}") from None
        self.port: int = self._httpd.server_address[1]
        self._loopback = _is_loopback(host)
        self._closed = False
        self._thread = threading.Thread(
            target=self._httpd.serve_forever,
            kwargs={"poll_interval": 0.1},
            name="temoto-web",
        )

    def _serve(self) -> None:
        self._thread.start()

    @property
    def base_url(self) -> str:
        """The page's address without the token, e.g. ``http://127.0.0.1:8765/``."""
        host = self.host
        if host in ("", "0.0.0.0"):
            host = "127.0.0.1"
        elif host == "::":
            host = "::1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The address to open: :attr:`base_url` with ``?token=`` (what the commands print).

        Whoever opens it may use the controls; the page moves the token out of the address
        bar into the tab's session storage.
        """
        return f"{self.base_url}?token={self.token}" if self.token else self.base_url

    def _host_allowed(self, header: str) -> bool:
        if not self._loopback:
            return True
        host, _, port = header.rpartition(":") if not header.endswith("]") else (header, "", "")
        host = host.strip("[]")
        return _is_loopback(host) and port == str(self.port)

    def _write_refusal(self, headers: Any) -> tuple[HTTPStatus, str] | None:
        """Why a write request is refused, or None: token, Host, Origin, content type."""
        host = headers.get("Host", "")
        if not self._host_allowed(host):
            return HTTPStatus.MISDIRECTED_REQUEST, "unexpected Host header"
        origin = headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != host:
            return HTTPStatus.FORBIDDEN, "cross-origin write refused"
        given = headers.get(TOKEN_HEADER, "")
        if not self.token or not hmac.compare_digest(given.encode(), self.token.encode()):
            return HTTPStatus.FORBIDDEN, f"a write needs the view's token in {TOKEN_HEADER}"
        kind = headers.get("Content-Type", "").split(";")[0].strip().lower()
        if kind != "application/json":
            return HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "a write's body must be application/json"
        return None

    def _get(self, handler: _Handler, path: str) -> bool:
        """Answer a GET of ``path``; False: not found."""
        return False

    def _post(self, handler: _Handler, path: str, body: dict[str, Any]) -> bool:
        """Answer an authorised POST of ``path``; False: not found."""
        return False

    def _close_server(self) -> None:
        self._httpd.shutdown()
        self._thread.join()
        self._httpd.server_close()  # closes the socket, joins the request threads

    def close(self) -> None:
        """Stop serving and join every thread. Idempotent.

        Returns:
            None.
        """
        if self._closed:
            return
        self._closed = True
        self._close_server()


@final
class LiveView(Site):
    """Serves a live picture of an engine's graph runs to a browser (started at once).

    Args:
        engine: The engine to show; the view adds an instrument to it. When the engine has a
            registrar with a Robot Manager, the page also shows the robot.
        host: Address to listen on. The default serves this machine only; on a loopback
            address, requests must also name a loopback host (no DNS rebinding).
        port: Port to listen on (0: any free port; see :attr:`url`).
        max_clients: Event streams (open pages) served at once; more get HTTP 503.
        heartbeat_s: Seconds between keep-alive comments on an idle event stream (how soon a
            vanished client is noticed).
        token: The write token the controls need (None: a new random one, shown in
            :attr:`url`; ``""``: read-only, every write refused).
        robot_period_s: Real seconds between readings of the robot.

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
        token: str | None = None,
        robot_period_s: float = 0.2,
    ) -> None:
        super().__init__(host, port, token)
        self.engine = engine
        self.heartbeat_s = heartbeat_s
        self._hub = EventHub(max_clients=max_clients)
        engine.add_instrument(self._hub)
        registrar = engine.registrar
        self._robot = RobotWatch(registrar, robot_period_s) if registrar is not None else None
        self._displays = DisplayWatch(registrar) if registrar is not None else None
        # the last picture of each ended run (its timeline's start, the answer), so that an
        # earlier run of a name used again is still drawn as it ended
        self._pictures_lock = threading.Lock()
        self._pictures: dict[str, tuple[float | None, dict[str, Any]]] = {}
        self._earlier: dict[str, dict[str, Any]] = {}  # by "<run> #<k>"
        self._serve()
        logger.info("live view at %s", self.base_url)

    @property
    def clients(self) -> int:
        """Event streams open now."""
        return self._hub.subscribers

    def _get(self, handler: _Handler, path: str) -> bool:
        engine = self.engine
        if path == "/api/graphs":
            handler.send_json(HTTPStatus.OK, self._graphs_list())
        elif path.startswith(_GRAPH_PREFIX) and len(path) > len(_GRAPH_PREFIX):
            name = unquote(path[len(_GRAPH_PREFIX) :])
            try:
                answer = self._graph_view(name)
            except GraphNotFoundError:
                earlier = self._earlier_view(name)
                if earlier is None:
                    error = {"error": f"no graph run named {name!r}"}
                    handler.send_json(HTTPStatus.NOT_FOUND, error)
                    return True
                answer = earlier
            handler.send_json(HTTPStatus.OK, answer)
        elif path == "/api/indexed":
            names = sorted(g.name for g in engine.indexed_graphs())
            handler.send_json(HTTPStatus.OK, {"graphs": names})
        elif path == "/api/robot":
            state = self._robot.state() if self._robot is not None else None
            handler.send_json(HTTPStatus.OK, {"robot": state})
        elif path == "/api/displays":
            shown = self._displays.state() if self._displays is not None else []
            handler.send_json(HTTPStatus.OK, {"displays": shown})
        elif path == "/api/events":
            handler.stream(self._hub, self.heartbeat_s)
        else:
            return False
        return True

    def _graph_view(self, name: str) -> dict[str, Any]:
        """A run's picture; the last one served is kept (see :meth:`_graphs_list`)."""
        self._take_earlier()
        timeline = self._hub.timeline(name)
        answer = graph_view(self.engine, name, timeline)
        with self._pictures_lock:
            self._pictures[name] = (timeline["start"] if timeline else None, answer)
        return answer

    def _take_earlier(self) -> list[dict[str, Any]]:
        """Take in the runs the hub archived: each takes the picture kept of it (if any).

        Called before a picture is replaced, so that the earlier run keeps its own.
        """
        earlier = self._hub.earlier_runs()
        with self._pictures_lock:
            for entry in earlier:
                if entry["name"] in self._earlier:
                    continue
                kept = self._pictures.get(entry["run"])
                start = entry["timeline"]["start"]
                picture = kept[1] if kept is not None and kept[0] == start else None
                self._earlier[entry["name"]] = {**entry, "picture": picture}
            kept_names = {e["name"] for e in earlier}
            for gone in [k for k in self._earlier if k not in kept_names]:
                del self._earlier[gone]  # the hub keeps a bounded number
        return earlier

    def _graphs_list(self) -> dict[str, Any]:
        """The engine's runs, each earlier run of a name used again just before that name's.

        The engine forgets an ended run when its name is used again; the hub keeps its
        timeline (:meth:`EventHub.earlier_runs`) and the view its last picture.
        """
        answer = graphs_list(self.engine)
        earlier = self._take_earlier()
        for run in answer["graphs"]:  # the picture of an ended run, once
            if run["state"] in _ENDED_STATES:
                line = self._hub.timeline(run["name"])
                with self._pictures_lock:
                    kept = self._pictures.get(run["name"])
                if (
                    kept is None
                    or kept[1]["state"] not in _ENDED_STATES
                    or (line is not None and kept[0] != line["start"])
                ):
                    with contextlib.suppress(GraphNotFoundError):
                        self._graph_view(run["name"])
        listed = answer["graphs"]
        for entry in earlier:
            with self._pictures_lock:
                picture = self._earlier.get(entry["name"], {}).get("picture")
            row = {
                "name": entry["name"],
                "state": _ended_state(picture, entry["result"]),
                "result": entry["result"],
                "earlier": True,
            }
            at = next((i for i, r in enumerate(listed) if r["name"] == entry["run"]), None)
            listed.insert(len(listed) if at is None else at, row)
        return answer

    def _earlier_view(self, name: str) -> dict[str, Any] | None:
        """The picture of an earlier run of a name used again (None: no such run)."""
        self._take_earlier()
        with self._pictures_lock:
            entry = self._earlier.get(name)
        if entry is None:
            return None
        line = entry["timeline"]
        picture = entry["picture"]
        last: dict[str, str] = {}
        for span in line["spans"]:
            last[span["node"]] = span["state"]
        if picture is not None:  # its drawing as a page last saw it, its states as it ended
            nodes = [
                {**n, "state": last.get(n["id"], n["state"])} if n["kind"] == "action" else n
                for n in picture["nodes"]
            ]
            states = {n["id"]: n["state"] for n in nodes}
            edges = [
                {**e, "status": edge_status(states.get(e["from"]), states.get(e["to"]), e)}
                for e in picture["edges"]
            ]
            picture = {**picture, "nodes": nodes, "edges": edges}
            if line["spans"]:  # each node's result is its newest span's
                results = {sp["node"]: sp["result"] for sp in line["spans"]}
                for n in nodes:
                    if n["id"] in results:
                        n["result"] = results[n["id"]]
        else:  # not seen by a page: drawn from its timeline, without edges
            actions = []
            for node, state in last.items():
                base, _, number = node.rpartition("_")
                actions.append(
                    {
                        "name": base or node,
                        "instance_id": int(number) if number.isdigit() else 0,
                        "state": state,
                    }
                )
            picture = graph_picture({"actions": actions}, None, line)
            picture["errors"] = []
        return {
            **picture,
            "name": name,
            "state": _ended_state(picture, entry["result"]),
            "result": entry["result"],
            "timeline": line,
            "earlier": True,
        }

    def _post(self, handler: _Handler, path: str, body: dict[str, Any]) -> bool:
        if path == "/api/start":
            status, answer = operator_command(self.engine, "start", body.get("graph"))
            handler.send_json(status, answer)
            return True
        name, _, verb = path[len(_GRAPH_PREFIX) :].rpartition("/")
        if not path.startswith(_GRAPH_PREFIX) or not name or verb not in _CONTROLS:
            return False
        status, answer = operator_command(self.engine, verb, unquote(name))
        handler.send_json(status, answer)
        return True

    def close(self) -> None:
        """End the event streams, stop serving and join every thread. Idempotent.

        The engine keeps the view's instrument, which does nothing from now on.

        Returns:
            None.
        """
        if self._closed:
            return
        self._closed = True
        self._hub.close()
        if self._robot is not None:
            self._robot.close()
        if self._displays is not None:
            self._displays.close()
        self._close_server()
