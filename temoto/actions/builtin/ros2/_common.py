"""What the ROS 2 actions share: the bridge connection and JSON parameters."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

from temoto.core.action import Action
from temoto.errors import ConfigError, ResourceError, ResourceLoadError, StopRequested
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.manager import Ros2BridgeRequest, Ros2BridgeResponse

__all__ = ["GONE_WAIT_S", "acquire", "connect", "json_object", "request", "timeout_of"]

#: Real seconds to wait for the resource failure that explains a lost bridge connection.
GONE_WAIT_S = 2.0


def connect(action: Action) -> BridgeClient:
    """Hold the registrar's ROS 2 bridge (``"ros2"``) for the run, and connect to it.

    Args:
        action: The action.

    Returns:
        A client; close it when the action is done.

    Raises:
        ConfigError: The ``ros2`` extra is not installed (one line naming it; from the load).
        ResourceError: No bridge could be started.
    """
    domain = int(action.inputs.get("domain_id", -1))
    resource = acquire(action, "ros2", Ros2BridgeRequest(domain))
    response = resource.response
    if not isinstance(response, Ros2BridgeResponse):
        raise ConfigError(f"the 'ros2' server answered {type(response).__name__}, not a bridge")
    return BridgeClient(response.socket)


def acquire(action: Action, server: str, request: Any) -> Any:
    """``action.acquire``, with a load failure's own one line instead of the registrar's.

    The registrar wraps a failed load in "server S could not load <request JSON>: ...", once per
    level (the bridge's process under the bridge); the innermost cause is the line a user needs
    (the missing extra, the wrong RMW, the missing interpreter).

    Args:
        action: The action.
        server: The server.
        request: The request.

    Returns:
        The reference.

    Raises:
        ConfigError: The innermost cause was a user error (one line).
        ResourceError: The load failed otherwise (its innermost cause's line).
    """
    try:
        return action.acquire(server, request)
    except ResourceLoadError as exc:
        cause: BaseException = exc
        while isinstance(cause, ResourceLoadError) and cause.__cause__ is not None:
            cause = cause.__cause__
        if cause is exc:
            raise
        kind = (
            ConfigError
            if isinstance(cause, (ConfigError, ValueError, TypeError))
            else ResourceError
        )
        raise kind(str(cause)) from exc


def json_object(action: Action, name: str) -> dict[str, Any]:
    """An input parameter holding a JSON object (absent or empty: ``{}``).

    Args:
        action: The action.
        name: The parameter's name.

    Returns:
        The object.

    Raises:
        ConfigError: The parameter is not a JSON object (one line naming it).
    """
    text = action.inputs.get(name, "")
    if isinstance(text, dict):
        return text
    if not str(text).strip():
        return {}
    try:
        value = json.loads(str(text))
    except ValueError as exc:
        raise ConfigError(f"{action.name}: parameter {name!r} is not JSON: {exc}") from None
    if not isinstance(value, dict):
        raise ConfigError(
            f"{action.name}: parameter {name!r} must be a JSON object, not {type(value).__name__}"
        )
    return value


def timeout_of(action: Action, default: float) -> float:
    """The ``timeout`` parameter (seconds), or ``default``.

    Args:
        action: The action.
        default: The default.

    Returns:
        Seconds (0: none).
    """
    return float(action.inputs.get("timeout", default))


def request(action: Action, bridge: BridgeClient, op: str, /, **fields: Any) -> dict[str, Any]:
    """A bridge request on behalf of an action: cancelled when the action is asked to stop.

    Args:
        action: The action.
        bridge: Its connection.
        op: The operation.
        **fields: The request's fields (and ``on_event``/``started`` for the client).

    Returns:
        The reply's result.

    Raises:
        StopRequested: The action was asked to stop (the request was cancelled).
        BridgeError: The request failed (the bridge's one line).
    """
    try:
        result = bridge.request(op, stop=lambda: action.stop_requested, **fields)
    except BridgeError as exc:
        if action.stop_requested:
            raise StopRequested(action.name) from None
        if exc.gone:
            # The bridge's process exited: its FATAL (how it exited) follows within milliseconds
            # from the Process Manager; fail with that rather than with the closed socket.
            deadline = time.monotonic() + GONE_WAIT_S
            while time.monotonic() < deadline:
                action.check_resources()  # raises ResourceBrokenError once it arrived
                threading.Event().wait(0.02)
        raise
    if action.stop_requested:
        raise StopRequested(action.name)
    return result
