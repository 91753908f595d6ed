"""The operator's commands from Foxglove: start, pause, resume and stop a graph, by token.

``docs/visualization.md``, "Operator commands". Off by default: ``--foxglove-commands`` adds
four services to the live Foxglove server, ``/temoto/start``, ``/temoto/pause``,
``/temoto/resume`` and ``/temoto/stop``, called from Foxglove's *Service Call* panel with a
JSON request ``{"token": "...", "graph": "..."}`` (``graph``: an indexed graph's name for a
start, a run's name for the others). A call whose ``token`` is not the server's is refused
before anything else is looked at; the others go through
:func:`temoto.web.server.operator_command`, the live view's own controls, so a command does
and answers the same from the page and from Foxglove. A refused call is a service call failure
whose message says why (the live view's error text); an accepted one answers the live view's
JSON (``{"run": ..., "done": ...}``).

The protocol has no authentication of its own: the token is the only gate, and anyone who can
read the traffic can read it (keep the server on localhost, or tunnel it).
"""

from __future__ import annotations

import hmac
import json
import logging
from http import HTTPStatus
from typing import TYPE_CHECKING, Any, Final

from temoto.web.server import COMMANDS, operator_command

if TYPE_CHECKING:
    from temoto.core.engine import ActionEngine
    from temoto.managers.visualization.foxglove import FoxgloveServer

__all__ = ["SERVICE_PREFIX", "add_operator_commands"]

logger = logging.getLogger(__name__)

#: The services' names: ``/temoto/<command>``.
SERVICE_PREFIX: Final = "/temoto/"

_REQUEST_SCHEMA: Final = {
    "title": "temoto.OperatorCommand",
    "description": "An operator's command: the server's token and the graph (start) or run",
    "type": "object",
    "properties": {"token": {"type": "string"}, "graph": {"type": "string"}},
    "required": ["token", "graph"],
}
_RESPONSE_SCHEMA: Final = {
    "title": "temoto.OperatorAnswer",
    "description": "The run a command started or acted on, and what was done",
    "type": "object",
    "properties": {"run": {"type": "string"}, "done": {"type": "string"}},
}


class CommandRefused(Exception):
    """A refused command; the SDK sends its text to the client as the call's failure."""


def _handler(engine: ActionEngine, verb: str, token: str) -> Any:
    """The service handler of one command (runs on an SDK thread)."""

    def handle(request: Any) -> bytes:
        try:
            body = json.loads(bytes(request.payload) or b"{}")
        except ValueError:
            body = None
        if not isinstance(body, dict):
            raise CommandRefused("the request must be a JSON object")
        given = body.get("token")
        if (
            not token
            or not isinstance(given, str)
            or not hmac.compare_digest(given.encode(), token.encode())
        ):
            logger.warning("foxglove: %s refused: wrong or missing token", verb)
            raise CommandRefused(f"{verb} refused: the request's token is not the server's")
        status, answer = operator_command(engine, verb, body.get("graph"))
        if status != HTTPStatus.OK:
            raise CommandRefused(f"{verb}: {answer['error']}")
        return json.dumps(answer).encode()

    return handle


def add_operator_commands(server: FoxgloveServer, engine: ActionEngine, token: str) -> list[str]:
    """Advertise the four operator commands on ``server``, for ``engine``, behind ``token``.

    Args:
        server: A server made with ``services=True``.
        engine: The engine the commands act on.
        token: The token every call must carry (``""``: every call is refused).

    Returns:
        The services' names.

    Raises:
        RuntimeError: The server does not declare services.
    """
    services = [
        (SERVICE_PREFIX + verb, _REQUEST_SCHEMA, _RESPONSE_SCHEMA, _handler(engine, verb, token))
        for verb in COMMANDS
    ]
    server.add_json_services(services)
    return [name for name, *_ in services]
