"""The Visualization Manager: displays loaded on demand, served live (``docs/visualization.md``).

The thesis' fifth resource manager (Table 13). :class:`VisualizationManager` serves
``"display"`` on a registrar: a :class:`~temoto.managers.visualization.messages.DisplayRequest`
names a source (a robot's pose, joints, location ...; an action's log) and the Foxglove schema
it is shown as. Equal requests share one display (the registrar counts the references); a
display exists only while some consumer holds it. While loaded, it publishes its source on
``/display/<name>/<field>`` of the live server
(:class:`~temoto.managers.visualization.foxglove.FoxgloveServer`), advertised on load and
unadvertised on release.

A robot display holds the robot through the registrar (a dependency of the display), so a
fault of the robot reaches the display's consumers as a resource status, hop by hop, like any
dependency's. The robot's messages are made by the recorder's own encoders
(:class:`~temoto.record.Recorder`), so a display carries what ``--record`` records.
"""

from __future__ import annotations

import logging
import math
import os
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final

from temoto.clock import Clock, MonotonicClock
from temoto.core.action import ACTION_LOGGER
from temoto.core.registrar import (
    LoadContext,
    Registrar,
    ResourceInfo,
    ResourceServer,
    Status,
)
from temoto.managers.visualization.decode import decode
from temoto.managers.visualization.messages import DisplayRequest, DisplayResponse
from temoto.record.recorder import (
    Encoded,
    health_messages,
    joints_messages,
    log_level,
    pose_messages,
    vehicle_messages,
)
from temoto.record.schemas import stamp

__all__ = ["Display", "VisualizationManager"]

logger = logging.getLogger(__name__)

_GONE: Final = "the display was lost with its process (request it again)"


def _robot_messages(robot: Any, field: str) -> list[Encoded]:
    """One reading of a robot's ``field``, encoded as ``--record`` encodes it."""
    name = robot.name
    if field in ("pose", "tf"):
        return pose_messages(name, robot.pose())
    if field == "joints":
        return joints_messages(name, robot.joint_positions())
    if field in ("location", "vehicle"):
        return vehicle_messages(name, robot.telemetry())
    if field == "health":
        return health_messages(name, robot.healthy())
    return []


@dataclass(eq=False)
class Display:
    """A loaded display (what :meth:`VisualizationManager.displays` lists).

    Attributes:
        request: What it shows.
        resource_id: Its registrar resource.
        last: Its last message (None before the first).
        count: Messages published so far.
        dropped: Datagrams a decoding display could not decode (and did not publish).
        first_at: ``time.monotonic()`` of its first message (None before it).
    """

    request: DisplayRequest
    resource_id: str
    last: dict[str, Any] | None = None
    count: int = 0
    first_at: float | None = None
    dropped: int = 0
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _stopping: bool = False
    _thread: threading.Thread | None = None
    _undo: Callable[[], None] | None = None
    _wake: int = -1  # the write end of a pipe that wakes a reader thread's select
    _watchers: list[Callable[[dict[str, Any]], None]] = field(default_factory=list)

    def watch(self, watcher: Callable[[dict[str, Any]], None]) -> None:
        """Call ``watcher(message)`` with each message from now on.

        It runs in the publishing thread with the display's lock held: keep it short, and do not
        release the display in it.
        """
        with self._cond:
            self._watchers.append(watcher)

    def wait_for_message(self, timeout: float) -> float:
        """Wait (real seconds) for the display's first message.

        Returns:
            Its ``time.monotonic()``.

        Raises:
            TimeoutError: None came within ``timeout``.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: self.first_at is not None, timeout):
                raise TimeoutError(f"display {self.request.name}: no message in {timeout:g} s")
            assert self.first_at is not None
            return self.first_at


#: Metres a robot moves before its path display takes another pose; the poses it keeps.
PATH_STEP: Final = 0.02
PATH_POSES: Final = 200


class _Path:
    """A robot's path travelled, as a ``foxglove.PosesInFrame`` in the odometry frame.

    A pose each :data:`PATH_STEP` metres, the newest :data:`PATH_POSES`.
    """

    def __init__(self) -> None:
        self.poses: deque[dict[str, Any]] = deque(maxlen=PATH_POSES)
        self._last: tuple[float, float] | None = None

    def sample(self, pose: tuple[float, float, float]) -> dict[str, Any] | None:
        """Take a reading; the message to publish when the path grew (or at first), else None."""
        x, y, yaw = pose
        if self._last is not None and math.hypot(x - self._last[0], y - self._last[1]) < (
            PATH_STEP
        ):
            return None
        self._last = (x, y)
        self.poses.append(_pose(x, y, yaw))
        return {"frame_id": "odom", "poses": list(self.poses)}


def _pose(x: float, y: float, yaw: float) -> dict[str, Any]:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
    }


class _Plan:
    """A robot's planned path, as a ``foxglove.PosesInFrame`` in the odometry frame.

    The drive controller holds a goal and no plan: it turns towards the goal from where the
    base is and drives straight to it (then turns to the goal's yaw, if it has one). So the
    path planned from here is the straight segment from the base's pose to the goal: two
    poses, both facing along the segment, the goal's with its yaw if it has one. No goal: no
    poses. A message when the goal changes or the base moved :data:`PATH_STEP` metres.
    """

    def __init__(self) -> None:
        self._last: tuple[Any, tuple[float, float]] | None = None

    def sample(
        self,
        pose: tuple[float, float, float],
        goal: tuple[float, float, float | None] | None,
    ) -> dict[str, Any] | None:
        """Take a reading; the message to publish when the plan changed (or at first), else None."""
        x, y, yaw = pose
        if self._last is not None:
            last_goal, (lx, ly) = self._last
            moved = math.hypot(x - lx, y - ly) >= PATH_STEP
            if goal == last_goal and (goal is None or not moved):
                return None
        self._last = (goal, (x, y))
        if goal is None:
            return {"frame_id": "odom", "poses": []}
        gx, gy, gyaw = goal
        heading = math.atan2(gy - y, gx - x) if (gx, gy) != (x, y) else yaw
        end = heading if gyaw is None else gyaw
        return {"frame_id": "odom", "poses": [_pose(x, y, heading), _pose(gx, gy, end)]}


class _LogHandler(logging.Handler):
    """Publishes an action logger's records on a log display."""

    def __init__(self, manager: VisualizationManager, display: Display) -> None:
        super().__init__()
        self.manager = manager
        self.display = display

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
        except Exception:
            text = str(record.msg)
        message = {
            "level": log_level(record.levelno),
            "message": text,
            "name": record.name,
            "file": record.pathname,
            "line": record.lineno,
        }
        self.manager._publish(self.display, message)


class VisualizationManager(ResourceServer[DisplayRequest, DisplayResponse]):
    """Serves ``"display"``: one display per distinct request, while it is held.

    Args:
        registrar: The registrar to serve on (a robot display needs a Robot Manager there).
        server: The live server displays publish on (None: displays load and keep their last
            message for :meth:`displays`, published nowhere).
        clock: Paces the robot displays' sampling and stamps messages (default: real time).
        register: Register on ``registrar`` now.
    """

    name: ClassVar[str] = "display"
    request_type = DisplayRequest
    response_type = DisplayResponse

    def __init__(
        self,
        registrar: Registrar,
        server: Any = None,
        *,
        clock: Clock | None = None,
        register: bool = True,
    ) -> None:
        self.registrar = registrar
        self.server = server
        self.clock: Clock = clock or MonotonicClock()
        self._lock = threading.Lock()
        self._displays: dict[str, Display] = {}  # by name
        self._listeners: list[Callable[[str, DisplayResponse], None]] = []
        if register:
            registrar.register(self)

    # ---- what is loaded ------------------------------------------------------------------------

    def displays(self) -> dict[str, Display]:
        """The loaded displays, by name."""
        with self._lock:
            return dict(self._displays)

    def add_listener(self, listener: Callable[[str, DisplayResponse], None]) -> None:
        """Call ``listener("loaded" | "released", response)`` as displays come and go.

        It runs in the thread that loads or releases the display: keep it short.
        """
        self._listeners.append(listener)

    # ---- the server hooks ----------------------------------------------------------------------

    def on_load(self, request: DisplayRequest, ctx: LoadContext) -> DisplayResponse:
        """Take the source (a robot: as a dependency), advertise the topic, start publishing.

        Raises:
            ValueError: Another display already has this name.
            ResourceError: The robot cannot be had.
        """
        with self._lock:
            if request.name in self._displays:
                raise ValueError(f"display name '{request.name}' is in use by another display")
            display = Display(request, ctx.resource_id)
            self._displays[request.name] = display
        try:
            what = self._start(display, ctx)
            if self.server is not None:
                self.server.advertise(request.topic, request.kind)
        except BaseException:
            with self._lock:
                self._displays.pop(request.name, None)
            self._stop(display)  # the registrar releases the source (a dependency)
            if self.server is not None:
                self.server.unadvertise(request.topic)
            raise
        response = DisplayResponse(
            request.name, (request.topic,), request.kind, what, ctx.resource_id
        )
        self._tell("loaded", response)
        logger.info("display %s: showing %s on %s", request.name, what, request.topic)
        return response

    def on_unload(self, request: DisplayRequest, response: DisplayResponse) -> None:
        """Stop publishing and unadvertise (the robot is released after, as a dependency)."""
        with self._lock:
            display = self._displays.get(request.name)
            if display is None or display.resource_id != response.resource_id:
                return  # lost in a restart (on_restore): a display of that name is another one
            del self._displays[request.name]
        self._stop(display)
        if self.server is not None:
            for topic in response.topics:
                self.server.unadvertise(topic)
        self._tell("released", response)
        logger.info("display %s: released", request.name)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart from the catalog: the display's publisher died with its process."""
        return Status.FATAL, _GONE

    def shutdown(self) -> None:
        """Stop every display still loaded (the registrar is closing); unadvertises them."""
        with self._lock:
            displays = list(self._displays.values())
            self._displays.clear()
        for display in displays:
            self._stop(display)
            if self.server is not None:
                self.server.unadvertise(display.request.topic)

    # ---- internals -----------------------------------------------------------------------------

    def _tell(self, event: str, response: DisplayResponse) -> None:
        for listener in list(self._listeners):
            try:
                listener(event, response)
            except Exception:
                logger.exception("display listener failed")

    def _start(self, display: Display, ctx: LoadContext) -> str:
        request = display.request
        if request.source == "robot":
            from temoto.managers.robot.client import RobotManagerClient

            # Called in on_load's thread: the robot is a dependency of the display.
            robot = RobotManagerClient(self.registrar).request(
                request.target, client=f"display/{request.name}"
            )
            drive = self._drive(robot.name) if request.field == "plan" else None
            thread = threading.Thread(
                target=self._sample_loop,
                args=(display, robot, drive),
                name=f"temoto-display-{request.name}",
                daemon=True,
            )
            display._thread = thread
            thread.start()
            return f"robot {robot.name} {request.field}"
        if request.source == "component":
            return self._start_component(display)
        if request.source == "world":
            return self._start_world(display)
        # source "log"
        handler = _LogHandler(self, display)
        log = logging.getLogger(
            f"{ACTION_LOGGER}.{request.target}" if request.target else ACTION_LOGGER
        )
        log.addHandler(handler)
        display._undo = lambda: log.removeHandler(handler)
        return f"log of {log.name}"

    def _drive(self, robot: str) -> Any:
        """The drive controller of a loaded robot (its goal is a plan display's source).

        Raises:
            StateError: The robot has no navigation feature.
        """
        from temoto.errors import StateError
        from temoto.managers.robot.manager import RobotManager

        server = self.registrar.server(RobotManager.name)
        assert isinstance(server, RobotManager)  # RobotManagerClient found it
        drive = server.robot(robot).drive
        if drive is None:
            raise StateError(f"robot '{robot}' has no navigation feature: it has no planned path")
        return drive

    def _start_world(self, display: Display) -> str:
        """A world display: the Context Manager's tree now, and again after every change."""
        from temoto.errors import ContextError, ResourceError, ResourceNotFoundError
        from temoto.managers.context.manager import ContextManager
        from temoto.managers.visualization.scene import scene_update

        try:
            server = self.registrar.server(ContextManager.name)
        except ResourceNotFoundError:
            server = None
        if not isinstance(server, ContextManager):
            raise ResourceError(
                f"display {display.request.name}: a world display needs a Context Manager"
                " on this registrar"
            )
        context = server
        root = display.request.target
        if root:
            context.get(root)  # ContextItemNotFoundError: the load fails, naming the item
        shown: set[str] = set()
        lock = threading.Lock()

        def send(_change: Any = None) -> None:
            nonlocal shown
            with lock:  # one at a time, in order (the load's thread, then the context's)
                ns = int(self.clock.time() * 1e9)
                try:
                    message, shown = scene_update(context, root, shown, ns)
                except ContextError:  # the root was removed: everything shown goes
                    message = {
                        "deletions": [
                            {"timestamp": stamp(ns), "type": 0, "id": name}
                            for name in sorted(shown)
                        ],
                        "entities": [],
                    }
                    shown = set()
                self._publish(display, message)

        display._undo = context.listen(send)
        send()
        return f"world model {root or '(every item)'}"

    def _start_component(self, display: Display) -> str:
        from temoto.managers.component.channels import ChannelReader
        from temoto.managers.component.messages import ComponentRequest

        request = display.request
        # Called in on_load's thread: the component is a dependency of the display.
        component = self.registrar.call(
            "component",
            ComponentRequest(
                type=request.target, name=request.candidate, failover=not request.candidate
            ),
            client=f"display/{request.name}",
        )
        reader = ChannelReader(component.response.output())
        wake_r, wake_w = os.pipe()  # _stop wakes the reader at once (a release is not delayed)

        def undo() -> None:
            display._wake = -1
            display._undo = None
            reader.close()
            os.close(wake_r)
            os.close(wake_w)

        thread = threading.Thread(
            target=self._read_loop,
            args=(display, reader, wake_r, component.resource_id),
            name=f"temoto-display-{request.name}",
            daemon=True,
        )
        display._thread = thread
        display._undo = undo
        display._wake = wake_w
        thread.start()
        response = component.response
        return f"{request.target} {response.name} of {response.robot}"

    def _read_loop(self, display: Display, reader: Any, wake: int, component_id: str) -> None:
        request = display.request
        while not display._stopping:
            try:
                ready, _, _ = select.select([reader, wake], [], [])
                if wake in ready:
                    return
                data = reader.recv(0)
            except OSError as err:
                logger.debug("display %s: channel closed: %s", request.name, err)
                return
            if not data:
                continue
            try:  # the active candidate (a failover changes it in place)
                active = self.registrar.info(component_id).response
                name, robot = str(active.name), str(active.robot)
            except Exception:  # released meanwhile
                name, robot = request.candidate, ""
            if request.kind != "temoto.ComponentData":  # decoded: a scan, an image
                try:
                    message = decode(request.kind, bytes(data), name)
                except ValueError as err:
                    display.dropped += 1
                    logger.debug("display %s: datagram dropped: %s", request.name, err)
                    continue
                self._publish(display, message)
                continue
            message = {
                "type": request.target,
                "component": name,
                "robot": robot,
                "data": bytes(data[:1024]).decode("utf-8", errors="replace"),
                "size": len(data),
            }
            self._publish(display, message)

    def _stop(self, display: Display) -> None:
        with display._cond:
            display._stopping = True
            display._cond.notify_all()
        if display._wake >= 0:
            os.write(display._wake, b"x")
        thread = display._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(5.0)
        if display._undo is not None:
            display._undo()

    def _sample_loop(self, display: Display, robot: Any, drive: Any = None) -> None:
        request = display.request
        clock = self.clock
        period = 1.0 / request.rate_hz
        next_at = clock.monotonic()
        cond = display._cond
        path = _Path() if request.field == "path" else None
        plan = _Plan() if drive is not None else None
        while not display._stopping:
            try:
                if plan is not None:
                    message = plan.sample(drive.pose(), drive.goal())
                    messages = [] if message is None else [("", request.kind, message)]
                elif path is not None:
                    message = path.sample(robot.pose())
                    messages = [] if message is None else [("", request.kind, message)]
                else:
                    messages = _robot_messages(robot, request.field)
            except Exception as err:  # a device in fault: its status reaches the consumers
                logger.debug("display %s: no sample: %s", request.name, err)
                messages = []
            for _topic, schema, message in messages:
                if schema == request.kind:
                    self._publish(display, message)
            next_at += period
            now = clock.monotonic()
            if next_at < now - period:  # fell behind: do not catch up
                next_at = now + period
            with cond:
                while not display._stopping:
                    remaining = next_at - clock.monotonic()
                    if remaining <= 0:
                        break
                    clock.wait(cond, remaining)

    def _publish(self, display: Display, message: dict[str, Any]) -> None:
        # Under the display's condition: once _stop has set _stopping, nothing is in flight
        # (a late message would advertise the topic again after its release).
        with display._cond:
            if display._stopping:
                return
            ns = int(self.clock.time() * 1e9)
            message.setdefault("timestamp", stamp(ns))
            display.last = message
            display.count += 1
            if display.first_at is None:
                display.first_at = time.monotonic()
                display._cond.notify_all()
            for watcher in display._watchers:
                try:
                    watcher(message)
                except Exception:
                    logger.exception("display %s: watcher failed", display.request.name)
            if self.server is not None:
                try:
                    self.server.publish(display.request.topic, display.request.kind, message, ns)
                except ValueError as err:  # a NaN: that message only
                    logger.debug("display %s: message not sent: %s", display.request.name, err)
