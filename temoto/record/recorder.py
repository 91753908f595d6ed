"""The recorder behind ``--record FILE.mcap`` (``docs/recording.md``).

A :class:`Recorder` is an engine :class:`~temoto.core.instrument.Instrument` (graph runs and
node transitions) that also takes the action logs (a logging handler), samples a robot's
telemetry at a fixed rate on the robot's clock, and hears the fleet's envelopes on a
transport. Every source only queues a message; one writer thread writes them to the MCAP file
and flushes it (closing the chunk in progress) at least once a second, so a process killed
with SIGKILL leaves a file whose last second at most is missing. :meth:`Recorder.close`
writes the summary and the footer: the file is then complete.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any, Final, cast

from mcap.writer import Writer

from temoto.clock import Clock, MonotonicClock
from temoto.core.action import ACTION_LOGGER
from temoto.core.instrument import Instrument
from temoto.core.states import NodeState, Result
from temoto.errors import ConfigError
from temoto.record.schemas import schema_bytes, stamp

__all__ = [
    "FLUSH_PERIOD_S",
    "TELEMETRY_RATE_HZ",
    "TOPICS",
    "Encoded",
    "Recorder",
    "health_messages",
    "joints_messages",
    "log_level",
    "pose_messages",
    "vehicle_messages",
]

logger = logging.getLogger(__name__)

#: How often a robot's telemetry is sampled (per second of the robot's clock).
TELEMETRY_RATE_HZ: Final = 10.0
#: Real seconds between flushes of the file (what a SIGKILL may lose at most).
FLUSH_PERIOD_S: Final = 1.0
#: The most acknowledgement channels (``TEMOTO_ACK_<actor>``) one recording subscribes to.
MAX_ACK_CHANNELS: Final = 1024
#: The recorder's own topics and their schemas (``{robot}``: the robot's name; ``{channel}``:
#: a fleet channel).
TOPICS: Final[dict[str, str]] = {
    "/temoto/graphs": "temoto.GraphEvent",
    "/temoto/transitions": "temoto.NodeTransition",
    "/temoto/log": "foxglove.Log",
    "/{robot}/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransform",
    "/{robot}/joint_states": "temoto.JointStates",
    "/{robot}/location": "foxglove.LocationFix",
    "/{robot}/vehicle": "temoto.VehicleState",
    "/{robot}/health": "temoto.RobotHealth",
    "/fleet/{channel}": "temoto.FleetMessage",
}

_LEVELS: Final = ((logging.CRITICAL, 5), (logging.ERROR, 4), (logging.WARNING, 3))
_STOP: Final = object()
#: A queued message: topic, schema, stamp (ns since the epoch), message.
_Item = tuple[str, str, int, dict[str, Any]]


#: An encoded message: topic, schema, message (what :meth:`Recorder.put` takes).
Encoded = tuple[str, str, dict[str, Any]]


def log_level(levelno: int) -> int:
    """A logging level as a ``foxglove.LogLevel``."""
    for at_least, level in _LEVELS:
        if levelno >= at_least:
            return level
    return 2 if levelno >= logging.INFO else 1


def pose_messages(robot: str, pose: tuple[float, float, float]) -> list[Encoded]:
    """A robot's pose ``(x, y, yaw)`` as its ``/{robot}/pose`` and ``/tf`` messages."""
    x, y, yaw = pose
    position = {"x": x, "y": y, "z": 0.0}
    orientation = {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}
    return [
        (
            f"/{robot}/pose",
            "foxglove.PoseInFrame",
            {"frame_id": "odom", "pose": {"position": position, "orientation": orientation}},
        ),
        (
            "/tf",
            "foxglove.FrameTransform",
            {
                "parent_frame_id": "odom",
                "child_frame_id": f"{robot}/base_link",
                "translation": dict(position),
                "rotation": dict(orientation),
            },
        ),
    ]


def joints_messages(robot: str, positions: dict[str, float]) -> list[Encoded]:
    """A robot's joint positions as its ``/{robot}/joint_states`` message."""
    message = {
        "name": list(positions),
        "position": list(positions.values()),
        "velocity": [],
        "effort": [],
    }
    return [(f"/{robot}/joint_states", "temoto.JointStates", message)]


def vehicle_messages(robot: str, telemetry: Any) -> list[Encoded]:
    """A vehicle's telemetry as its ``/{robot}/location`` and ``/{robot}/vehicle`` messages.

    None (no telemetry yet) gives none.
    """
    if telemetry is None:
        return []
    where = telemetry.position
    roll, pitch, yaw = telemetry.attitude
    return [
        (
            f"/{robot}/location",
            "foxglove.LocationFix",
            {
                "frame_id": f"{robot}/base_link",
                "latitude": where.lat,
                "longitude": where.lon,
                "altitude": where.alt,
                "position_covariance": [0.0] * 9,
                "position_covariance_type": 0,
            },
        ),
        (
            f"/{robot}/vehicle",
            "temoto.VehicleState",
            {
                "armed": bool(telemetry.armed),
                "mode": str(telemetry.mode),
                "latitude": where.lat,
                "longitude": where.lon,
                "altitude": where.alt,
                "roll": roll,
                "pitch": pitch,
                "yaw": yaw,
                "battery_voltage": telemetry.battery_voltage,
                "battery_remaining": int(telemetry.battery_remaining),
                "heartbeat_age": telemetry.heartbeat_age,
            },
        ),
    ]


def health_messages(robot: str, healthy: bool) -> list[Encoded]:
    """A robot's health as its ``/{robot}/health`` message."""
    return [(f"/{robot}/health", "temoto.RobotHealth", {"robot": robot, "healthy": bool(healthy)})]


class _LogHandler(logging.Handler):
    """Queues every record it handles as a ``foxglove.Log`` message."""

    def __init__(self, recorder: Recorder, *, skip: str = "", level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self.recorder = recorder
        self.skip = skip

    def emit(self, record: logging.LogRecord) -> None:
        if self.skip and (record.name == self.skip or record.name.startswith(self.skip + ".")):
            return  # recorded by the other handler
        try:
            message = record.getMessage()
        except Exception:
            message = str(record.msg)
        self.recorder.log(
            log_level(record.levelno), message, record.name, record.pathname, record.lineno
        )


class _Forward(logging.Handler):
    """Hands a record to the parent logger's handlers (what propagation would have done)."""

    def __init__(self, parent: logging.Logger, level: int) -> None:
        super().__init__(level)
        self.parent = parent

    def emit(self, record: logging.LogRecord) -> None:
        self.parent.handle(record)


class Recorder(Instrument):
    """Writes graph runs, node transitions, logs, telemetry and fleet traffic to an MCAP file.

    Add it to an engine (``engine.add_instrument`` or ``instruments=[...]``), then
    :meth:`capture_logs`, :meth:`sample` a robot and :meth:`listen` to a transport as wanted;
    :meth:`close` (or leaving the ``with`` block) finishes the file. Every method is
    thread-safe; the engine hooks only queue a message.

    Args:
        path: The file to write (replaced if it exists).
        clock: Stamps every message (``clock.time()``) and paces the sampling (default: real
            time).
        metadata: Written as the recording's ``temoto`` metadata record (strings).
        flush_period_s: Real seconds between flushes (each closes the chunk in progress):
            what a SIGKILL may lose at most (0: after every message).

    Raises:
        ConfigError: The file cannot be written (the message names it).
        ValueError: ``flush_period_s`` is negative.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        clock: Clock | None = None,
        metadata: dict[str, str] | None = None,
        flush_period_s: float = FLUSH_PERIOD_S,
    ) -> None:
        if not (math.isfinite(flush_period_s) and flush_period_s >= 0):
            raise ValueError(f"a flush period must be finite and >= 0: {flush_period_s!r}")
        self.flush_period_s = flush_period_s
        self.path = Path(path)
        self.clock: Clock = clock or MonotonicClock()
        try:
            self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 - closed by close()
        except OSError as err:
            raise ConfigError(f"{self.path}: cannot record: {err.strerror or err}") from None
        self._writer = Writer(self._file)
        self._writer.start(profile="", library="temoto")
        meta = {"telemetry_rate_hz": f"{TELEMETRY_RATE_HZ:g}", **(metadata or {})}
        self._writer.add_metadata("temoto", meta)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._counts: dict[str, int] = {}
        self._queue: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._results: dict[tuple[str, str], str] = {}  # node results awaiting their transition
        self._results_lock = threading.Lock()
        self._closed = False
        self._close_lock = threading.Lock()
        self._broken = False
        self._write_lock = threading.Lock()  # the writer thread's, and close()'s at the end
        self._sample_cond = threading.Condition()
        self._samples = 0
        self._samplers: list[threading.Thread] = []
        self._stopping = False
        self._subscriptions: list[Any] = []
        self._transport: Any = None  # the transport of listen(), for the acknowledgement channels
        self._ack_channels: set[str] = set()  # TEMOTO_ACK_<actor> channels subscribed to
        self._undo_logs: list[Callable[[], None]] = []
        self._thread = threading.Thread(target=self._drain, name="temoto-record", daemon=True)
        self._thread.start()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- what is recorded ----------------------------------------------------------------------

    def put(self, topic: str, schema: str, message: dict[str, Any]) -> None:
        """Queue one message (stamped now) for ``topic``; its channel is made on first use.

        Args:
            topic: The MCAP topic.
            schema: A schema name of :data:`temoto.record.schemas.SCHEMAS`.
            message: The message; a ``timestamp`` field is added if it has none.
        """
        if self._closed:
            return
        ns = int(self.clock.time() * 1e9)
        message.setdefault("timestamp", stamp(ns))
        self._queue.put((topic, schema, ns, message))

    def graph_started(self, graph: str, t: float) -> None:
        """Record a run's start on ``/temoto/graphs``."""
        event = {"t": t, "graph": graph, "event": "started", "result": ""}
        self.put("/temoto/graphs", "temoto.GraphEvent", event)

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        """Keep a node's result for the transition that ends its run (which carries it)."""
        with self._results_lock:
            self._results[(graph, node)] = result.value

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Record a transition on ``/temoto/transitions`` (with ``result`` when it ends a run)."""
        with self._results_lock:
            result = self._results.pop((graph, node), None)
        transition = {"t": t, "graph": graph, "node": node, "old": old.value, "new": new.value}
        if result is not None:
            transition["result"] = result
        self.put("/temoto/transitions", "temoto.NodeTransition", transition)

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Record a run's end (and its result) on ``/temoto/graphs``."""
        event = {"t": t, "graph": graph, "event": "finished", "result": result.value}
        self.put("/temoto/graphs", "temoto.GraphEvent", event)

    def action_failed(self, graph: str, node: str, error: BaseException) -> None:
        """Record an action's exception as an ERROR on ``/temoto/log``."""
        self.log(4, f"{node} failed: {type(error).__name__}: {error}", f"{graph}/{node}")

    def log(self, level: int, message: str, name: str, file: str = "", line: int = 0) -> None:
        """Record a ``foxglove.Log`` message on ``/temoto/log``.

        Args:
            level: A ``foxglove.LogLevel`` (1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL).
            message: The text.
            name: Who logs (a logger's or a node's name).
            file: The source file, if known.
            line: Its line, if known.
        """
        record = {"level": level, "message": message, "name": name, "file": file, "line": line}
        self.put("/temoto/log", "foxglove.Log", record)

    def capture_logs(self) -> None:
        """Record the actions' logs (INFO and up) and every other ``temoto`` WARNING and up.

        The actions' INFO records are made for the recording, but the console shows what it
        showed before: ``temoto.action`` no longer propagates, and a handler passes its parent
        the records at the level it had. :meth:`close` restores it all.
        """
        actions = logging.getLogger(ACTION_LOGGER)
        parent = logging.getLogger("temoto")
        shown = actions.getEffectiveLevel()
        level, propagate = actions.level, actions.propagate
        mine = _LogHandler(self)
        forward = _Forward(parent, shown)
        others = _LogHandler(self, skip=ACTION_LOGGER, level=logging.WARNING)
        actions.setLevel(min(shown, logging.INFO))
        actions.addHandler(mine)
        actions.addHandler(forward)
        actions.propagate = False
        parent.addHandler(others)

        def undo() -> None:
            actions.removeHandler(mine)
            actions.removeHandler(forward)
            parent.removeHandler(others)
            actions.setLevel(level)
            actions.propagate = propagate

        self._undo_logs.append(undo)

    def sample(self, robot: Any, rate_hz: float = TELEMETRY_RATE_HZ) -> None:
        """Sample a robot's telemetry ``rate_hz`` times a second of the recorder's clock.

        Each sample records what the robot has: with navigation, its odometry pose
        (``/{robot}/pose``, frame ``odom``) and the ``odom`` → ``{robot}/base_link`` transform
        (``/tf``); with manipulation, the arm's joint positions (``/{robot}/joint_states``);
        with flight, the vehicle's position (``/{robot}/location``) and state
        (``/{robot}/vehicle``); always, whether every device works (``/{robot}/health``).
        A reading that fails (a device in fault) is skipped.

        Args:
            robot: A :class:`~temoto.managers.robot.client.RobotHandle` (or anything with its
                ``name``, ``features``, ``healthy()``, ``pose()``, ``joint_positions()`` and
                ``telemetry()``).
            rate_hz: Samples per second (> 0).

        Raises:
            ValueError: ``rate_hz`` is not positive.
        """
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"a sampling rate must be positive: {rate_hz!r}")
        thread = threading.Thread(
            target=self._sample_loop,
            args=(robot, 1.0 / rate_hz),
            name=f"temoto-record-{robot.name}",
            daemon=True,
        )
        self._samplers.append(thread)
        thread.start()

    def listen(self, transport: Any, actors: Sequence[str] = ()) -> None:
        """Record the envelope of every fleet message heard on ``transport``.

        One topic per fleet channel (``/fleet/TEMOTO_RIS`` ...): the channel, sender, inner
        type, sequence number, sender's stamp and size of each envelope, as heard (neither
        authenticated nor decoded; ``docs/recording.md`` says how to keep the raw traffic).

        The acknowledgements of shared runs travel on one channel per notifying actor
        (``TEMOTO_ACK_<actor>``, :func:`temoto.fleet.actors.ack_channel`): those of
        ``actors`` are recorded from the start, and those of every actor named by a handshake
        heard on ``TEMOTO_HANDSHAKE`` from then on (a handshake precedes every notification
        of its run), at most :data:`MAX_ACK_CHANNELS`.

        Args:
            transport: A :class:`~temoto.transport.base.Transport` (open).
            actors: Actors whose acknowledgement channels are recorded at once (e.g. this
                instance's own).
        """
        self._transport = transport
        for channel in _fleet_channels():
            self._subscriptions.append(transport.subscribe(channel, self._on_fleet))
        for actor in actors:
            self._listen_acks(actor)

    def _listen_acks(self, actor: str) -> None:
        """Record the acknowledgement channel of ``actor`` too (once)."""
        from temoto.fleet.actors import ack_channel

        if not actor:
            return
        channel = ack_channel(actor)
        with self._close_lock:  # close() unsubscribes everything under it
            if (
                self._closed
                or self._transport is None
                or channel in self._ack_channels
                or len(self._ack_channels) >= MAX_ACK_CHANNELS
            ):
                return
            self._ack_channels.add(channel)
            try:
                self._subscriptions.append(self._transport.subscribe(channel, self._on_fleet))
            except Exception:  # the transport was closed meanwhile
                logger.debug("cannot record %s", channel, exc_info=True)

    def stop_sampling(self) -> None:
        """Stop every :meth:`sample` thread (e.g. before the robot is released); idempotent."""
        with self._sample_cond:
            self._stopping = True
            self._sample_cond.notify_all()
        for thread in self._samplers:
            if thread is not threading.current_thread():
                thread.join(5.0)

    @property
    def samples(self) -> int:
        """How many telemetry samples were taken so far."""
        with self._sample_cond:
            return self._samples

    def wait_for_samples(self, count: int, timeout: float) -> bool:
        """Wait (real time) until at least ``count`` samples were taken.

        Args:
            count: The number.
            timeout: Real seconds.

        Returns:
            Whether they were.
        """
        with self._sample_cond:
            return self._sample_cond.wait_for(lambda: self._samples >= count, timeout)

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, by topic."""
        return dict(self._counts)

    # ---- the end -------------------------------------------------------------------------------

    def close(self, timeout: float = 5.0) -> None:
        """Stop recording and finish the file (summary and footer); idempotent, thread-safe.

        A second caller waits until the first has finished the file.

        Args:
            timeout: Real seconds to wait for the writer to write what is queued.
        """
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            self.stop_sampling()
            for sub in self._subscriptions:
                try:
                    sub.unsubscribe()
                except Exception:
                    logger.debug("unsubscribing %r failed", sub, exc_info=True)
            for undo in self._undo_logs:
                undo()
            self._queue.put(_STOP)
            self._thread.join(timeout)
            with self._write_lock:
                try:
                    if not self._broken:
                        self._writer.finish()  # type: ignore[no-untyped-call]
                except Exception as err:
                    logger.error("%s: finishing the recording failed: %s", self.path, err)
                finally:
                    self._broken = True  # a late writer thread writes nothing more
                    self._file.close()

    # ---- internals -----------------------------------------------------------------------------

    def _drain(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=max(self.flush_period_s, 0.05))
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            now = time.monotonic()
            flush = now - last_flush >= self.flush_period_s
            if flush:
                last_flush = now
            with self._write_lock:
                if self._broken:
                    continue
                if item is not None:
                    self._write(*cast("_Item", item))
                if flush:
                    try:
                        self._writer.flush()  # type: ignore[no-untyped-call]
                    except Exception as err:
                        self._fail(err)

    def _write(self, topic: str, schema: str, ns: int, message: dict[str, Any]) -> None:
        try:
            channel = self._channels.get(topic)
            if channel is None:
                schema_id = self._schemas.get(schema)
                if schema_id is None:
                    schema_id = self._writer.register_schema(
                        schema, "jsonschema", schema_bytes(schema)
                    )
                    self._schemas[schema] = schema_id
                channel = self._writer.register_channel(topic, "json", schema_id)
                self._channels[topic] = channel
            data = json.dumps(message, ensure_ascii=False, allow_nan=False, default=str)
            count = self._counts.get(topic, 0)
            self._writer.add_message(channel, ns, data.encode(), ns, count)
            self._counts[topic] = count + 1
        except ValueError as err:  # a NaN or an infinity: that message only
            logger.debug("%s: message on %s not recorded: %s", self.path, topic, err)
        except Exception as err:
            self._fail(err)

    def _fail(self, err: BaseException) -> None:
        self._broken = True
        logger.error("%s: recording stopped: %s", self.path, err)

    def _sample_loop(self, robot: Any, period: float) -> None:
        clock = self.clock
        next_at = clock.monotonic()
        while True:
            with self._sample_cond:
                while not self._stopping:
                    remaining = next_at - clock.monotonic()
                    if remaining <= 0:
                        break
                    clock.wait(self._sample_cond, remaining)
                if self._stopping:
                    return
            self._sample_once(robot)
            with self._sample_cond:
                self._samples += 1
                self._sample_cond.notify_all()
            next_at += period
            now = clock.monotonic()
            if next_at < now - period:  # fell behind (a slow reading): do not catch up
                next_at = now + period

    def _sample_once(self, robot: Any) -> None:
        name = robot.name
        features = robot.features
        readings: list[tuple[str, Callable[[], list[Encoded]]]] = []
        if "navigation" in features:
            readings.append(("pose", lambda: pose_messages(name, robot.pose())))
        if "manipulation" in features:
            readings.append(("joints", lambda: joints_messages(name, robot.joint_positions())))
        if "flight" in features:
            readings.append(("vehicle", lambda: vehicle_messages(name, robot.telemetry())))
        readings.append(("health", lambda: health_messages(name, robot.healthy())))
        for what, read in readings:
            try:
                messages = read()
            except Exception as err:  # a device in fault, a driver shut down: skip it
                logger.debug("robot %s: no %s sample: %s", name, what, err)
                continue
            for topic, schema, message in messages:
                self.put(topic, schema, message)

    def _on_fleet(self, channel: str, data: bytes) -> None:
        from temoto.lcm_types import envelope_t

        message: dict[str, Any] = {"channel": channel, "size": len(data)}
        try:
            env = envelope_t.decode(data)
            signed = int(env.mac_size) > 0
            # The envelope's stamp field is the sender's clock on an insecure fleet only; a
            # keyed fleet's envelopes carry the sender's session id there (the same on every
            # message): it is `session`, and `stamp_us` is 0.
            message.update(
                sender=str(env.sender),
                type=str(env.type),
                seq=int(env.seq),
                stamp_us=0 if signed else int(env.stamp_us),
                session=int(env.stamp_us) if signed else 0,
                signed=signed,
            )
        except Exception:
            message.update(sender="", type="", seq=0, stamp_us=0, session=0, signed=False)
        self.put(f"/fleet/{channel}", "temoto.FleetMessage", message)
        if message["type"] == "handshake_t" and channel == "TEMOTO_HANDSHAKE":
            # A keyed fleet encrypts the payload (docs/security.md): every participant sends
            # handshakes, so its name as a sender is enough; an insecure one names them all.
            actors = [message["sender"], *_handshake_actors(env.payload)]
            for actor in dict.fromkeys(a for a in actors if a):
                self._listen_acks(actor)


def _handshake_actors(payload: bytes) -> list[str]:
    """The sender and the participants a handshake_t names (none if it does not decode)."""
    from temoto.errors import DecodeError
    from temoto.transport import codec

    try:
        msg = codec.decode("handshake_t", bytes(payload))
        names = json.loads(msg.actors) if msg.actors else []
    except (DecodeError, ValueError, RecursionError):
        return []
    if not isinstance(names, list):
        return []
    return [str(msg.actor), *(n for n in names if isinstance(n, str))]


def _fleet_channels() -> tuple[str, ...]:
    """Every channel the fleet services use."""
    from temoto.fleet.actors import HANDSHAKE_CHANNEL, NOTIFY_CHANNEL
    from temoto.fleet.control import COMMAND_CHANNEL, FEEDBACK_CHANNEL, REPLY_CHANNEL
    from temoto.fleet.resource_types import RESOURCE_CHANNEL
    from temoto.fleet.ris import RIS_CHANNEL
    from temoto.managers.context.manager import CONTEXT_CHANNEL

    return (
        HANDSHAKE_CHANNEL,
        NOTIFY_CHANNEL,
        COMMAND_CHANNEL,
        REPLY_CHANNEL,
        FEEDBACK_CHANNEL,
        RIS_CHANNEL,
        RESOURCE_CHANNEL,
        CONTEXT_CHANNEL,
    )
