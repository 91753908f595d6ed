"""The ``"ros2_lifecycle"`` resource server: a ROS 2 lifecycle node held ACTIVE while requested.

A :class:`Ros2LifecycleRequest` names a managed (lifecycle) node. Loading it configures and
activates the node through its ``lifecycle_msgs`` services (``<node>/get_state``,
``<node>/get_available_transitions``, ``<node>/change_state``), over a bridge held as a
dependency (``"ros2"``); every transition is first checked against the node's available ones,
since an invalid transition sent to a Jazzy ``LifecycleNode`` kills it. Equal requests share the
node (reference counted by the registrar); releasing the last one deactivates it and cleans it
up, back to the state it was found in.

While it is held, a watcher thread (``temoto-ros2-lifecycle``) asks the node's state every
:attr:`Ros2LifecycleManager.check_period` seconds: a node that leaves ACTIVE on its own, or does
not answer (it is gone), is reported FATAL, which reaches the consumers as a resource failure.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Final

from temoto.core.registrar import LoadContext, Registrar, ResourceServer, Status
from temoto.core.registrar.messages import StatusUpdate
from temoto.errors import ResourceError
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.manager import Ros2BridgeRequest, program_request

__all__ = ["Ros2LifecycleManager", "Ros2LifecycleRequest", "Ros2LifecycleResponse"]

logger = logging.getLogger(__name__)

# lifecycle_msgs/msg/State and Transition ids (ROS 2 design: "Managed nodes").
UNCONFIGURED: Final = 1
INACTIVE: Final = 2
ACTIVE: Final = 3
CONFIGURE: Final = 1
CLEANUP: Final = 2
ACTIVATE: Final = 3
DEACTIVATE: Final = 4
_NAMES: Final = {
    CONFIGURE: "configure",
    CLEANUP: "cleanup",
    ACTIVATE: "activate",
    DEACTIVATE: "deactivate",
}


@dataclass(frozen=True)
class Ros2LifecycleRequest:
    """A lifecycle node to hold ACTIVE. Equal requests share it.

    Attributes:
        node: The node's name (``/ns/name`` or ``name``).
        timeout: Seconds each service call may take (discovery included).
        domain_id: The bridge's ``ROS_DOMAIN_ID``, or -1 for the environment's.
        program: The node's program, started first and stopped after the node is brought
            down (a Python node file run with the interpreter that has rclpy, or an executable,
            and its arguments); empty: the node runs already.
    """

    node: str
    timeout: float = 10.0
    domain_id: int = -1
    program: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.node, str) or not self.node.strip("/"):
            raise ValueError(f"a lifecycle node needs a name, not {self.node!r}")
        if not self.timeout > 0:
            raise ValueError(f"timeout must be > 0, not {self.timeout!r}")
        object.__setattr__(self, "program", tuple(str(a) for a in self.program))

    @property
    def path(self) -> str:
        """The node's fully qualified name."""
        return "/" + self.node.strip("/")


@dataclass(frozen=True)
class Ros2LifecycleResponse:
    """A held lifecycle node.

    Attributes:
        node: Its fully qualified name.
        initial_state: The state id it was found in (restored on release).
        token: Identifies this load (equal requests after a failure load anew).
    """

    node: str
    initial_state: int
    token: str


@dataclass
class _Held:
    client: BridgeClient
    refs: list[str]  # the bridge's and the program's references, released last to first
    stop: threading.Event
    watcher: threading.Thread | None = None


class Ros2LifecycleManager(ResourceServer[Ros2LifecycleRequest, Ros2LifecycleResponse]):
    """Serves ``"ros2_lifecycle"`` through the registrar's ``"ros2"`` server.

    Args:
        registrar: The registrar (with a :class:`~temoto.ros2.manager.Ros2Manager` on it).
        check_period: Seconds between the watcher's state checks.
    """

    name: ClassVar[str] = "ros2_lifecycle"
    request_type: ClassVar[type] = Ros2LifecycleRequest
    response_type: ClassVar[type] = Ros2LifecycleResponse

    def __init__(self, registrar: Registrar, *, check_period: float = 0.5) -> None:
        self.registrar = registrar
        self.check_period = check_period
        self._held: dict[str, _Held] = {}
        self._lock = threading.Lock()
        registrar.register(self)

    # ---------------------------------------------------------------------------- service calls

    @staticmethod
    def _call(
        client: BridgeClient,
        req: Ros2LifecycleRequest,
        service: str,
        kind: str,
        body: dict[str, Any],
    ) -> dict[str, Any]:
        result = client.request(
            "call_service",
            service=f"{req.path}/{service}",
            type=f"lifecycle_msgs/srv/{kind}",
            request=body,
            timeout=req.timeout,
        )
        response = result.get("response")
        return response if isinstance(response, dict) else {}

    def _state(self, client: BridgeClient, req: Ros2LifecycleRequest) -> tuple[int, str]:
        state = self._call(client, req, "get_state", "GetState", {}).get("current_state", {})
        return int(state.get("id", 0)), str(state.get("label", "?"))

    def _transition(self, client: BridgeClient, req: Ros2LifecycleRequest, transition: int) -> None:
        available = self._call(
            client, req, "get_available_transitions", "GetAvailableTransitions", {}
        ).get("available_transitions", [])
        ids = {int(t.get("transition", {}).get("id", -1)) for t in available}
        name = _NAMES.get(transition, str(transition))
        if transition not in ids:
            raise ResourceError(
                f"lifecycle node {req.path}: {name} is not an available transition now"
            )
        done = self._call(
            client, req, "change_state", "ChangeState", {"transition": {"id": transition}}
        )
        if not done.get("success"):
            raise ResourceError(f"lifecycle node {req.path}: {name} failed")
        logger.info("lifecycle node %s: %s", req.path, name)

    # ------------------------------------------------------------------------------- the server

    def on_load(self, request: Ros2LifecycleRequest, ctx: LoadContext) -> Ros2LifecycleResponse:
        """Configure and activate the node.

        Args:
            request: The request.
            ctx: The load's context.

        Returns:
            The node, and the state it was in.

        Raises:
            ResourceError: The node does not answer, or a transition is refused or fails.
        """
        token = uuid.uuid4().hex
        resource_id = ctx.resource_id

        def passed_on(what: str) -> Callable[[StatusUpdate], None]:
            def on_status(update: StatusUpdate) -> None:
                if update.status is Status.FATAL:
                    with contextlib.suppress(ResourceError):
                        self.registrar.send_status(
                            resource_id,
                            Status.FATAL,
                            f"lifecycle node {request.path}: {what} failed: {update.message}",
                        )

            return on_status

        # Not dependencies: the registrar releases dependencies before on_unload, and the node
        # is brought down through the bridge there (before its program is stopped); their
        # failures are passed on to the holders.
        refs: list[str] = []

        def hold(server: str, req: Any, what: str) -> Any:
            res = self.registrar.call(
                server,
                req,
                client=f"{self.registrar.name}/ros2_lifecycle/{token}",
                holder="",
                on_status=passed_on(what),
            )
            refs.append(res.id)
            return res

        try:
            if request.program:
                hold(
                    "process",
                    program_request(request.program, domain_id=request.domain_id),
                    "its program",
                )
            bridge = hold("ros2", Ros2BridgeRequest(request.domain_id), "the ROS 2 bridge")
            client = BridgeClient(bridge.response.socket)
        except BaseException:
            self._release(refs)
            raise
        try:
            initial, label = self._state(client, request)
            if initial not in (UNCONFIGURED, INACTIVE, ACTIVE):
                raise ResourceError(
                    f"lifecycle node {request.path} is {label}: not unconfigured, inactive, active"
                )
            if initial == UNCONFIGURED:
                self._transition(client, request, CONFIGURE)
            if initial != ACTIVE:
                self._transition(client, request, ACTIVATE)
        except BaseException as exc:
            client.close()
            self._release(refs)
            if isinstance(exc, BridgeError):
                raise ResourceError(f"lifecycle node {request.path}: {exc}") from None
            raise
        response = Ros2LifecycleResponse(request.path, initial, token)
        held = _Held(client, refs, threading.Event())
        held.watcher = threading.Thread(
            target=self._watch,
            args=(request, resource_id, held),
            name="temoto-ros2-lifecycle",
        )
        with self._lock:
            self._held[response.token] = held
        held.watcher.start()
        return response

    def _watch(self, request: Ros2LifecycleRequest, resource_id: str, held: _Held) -> None:
        while not held.stop.wait(self.check_period):
            try:
                state, label = self._state(held.client, request)
            except BridgeError as exc:
                if held.stop.is_set():
                    return
                message = f"lifecycle node {request.path} does not answer: {exc}"
            else:
                if state == ACTIVE:
                    continue
                message = f"lifecycle node {request.path} left ACTIVE on its own (now {label})"
            logger.warning("%s", message)
            with contextlib.suppress(ResourceError):
                self.registrar.send_status(resource_id, Status.FATAL, message)
            return

    def on_unload(self, request: Ros2LifecycleRequest, response: Ros2LifecycleResponse) -> None:
        """Deactivate and clean the node up, back to the state it was found in.

        Args:
            request: The request.
            response: The held node.
        """
        with self._lock:
            held = self._held.pop(response.token, None)
        if held is None:
            return
        held.stop.set()
        if held.watcher is not None:
            held.watcher.join()
        try:
            state, _label = self._state(held.client, request)
            if state == ACTIVE and response.initial_state != ACTIVE:
                self._transition(held.client, request, DEACTIVATE)
                state = INACTIVE
            if state == INACTIVE and response.initial_state == UNCONFIGURED:
                self._transition(held.client, request, CLEANUP)
        except (BridgeError, ResourceError) as exc:
            logger.warning("lifecycle node %s: not brought back down: %s", request.path, exc)
        finally:
            held.client.close()
            self._release(held.refs)

    def _release(self, refs: list[str]) -> None:
        for ref in reversed(refs):
            with contextlib.suppress(ResourceError):
                self.registrar.release(ref)
