"""Replay of a recorded run in the live view's page: ``temoto view FILE``.

A :class:`Recording` is what the page replays: the graph's drawing, node state changes (and
results) in time, the run's result, and robot readings in time. Loaders turn a file into one,
chosen by the file's suffix (:data:`READERS`):

* ``.jsonl``, ``.json``, ``.trace``, anything else: the JSON lines of ``temoto run --trace``
  (``{"t", "graph", "node", "state"}`` per node change, ``{"graph", "result"}`` at the end;
  the line of a node's run ending carries its ``node_result``);
* ``.mcap``: a ``--record FILE.mcap`` recording (:func:`read_mcap`: its node transitions,
  the run's result and the robot's pose, joint, vehicle and health samples).

A reader is ``(path) -> Recording``. The graph's edges are not in a trace: give the graph file
(``--graph``) to draw them; without it the actions are drawn in the order they first ran.

:class:`ReplayView` serves the page in replay mode (``/api/recording``: the whole recording
at once; the page computes every moment from it as the time slider moves). It is read-only.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from typing import Any, Protocol, final

from temoto._files import read_regular_text
from temoto.errors import ConfigError
from temoto.web.server import Site
from temoto.web.view import graph_picture

__all__ = [
    "READERS",
    "Recording",
    "ReplayView",
    "load_recording",
    "read_mcap",
    "read_trace",
    "register_reader",
]

logger = logging.getLogger(__name__)

#: States a node line of a trace may carry.
_STATES = frozenset(
    {
        "UNINITIALIZED",
        "INITIALIZED",
        "RUNNING",
        "PAUSE_REQUESTED",
        "PAUSED",
        "STOPPING",
        "FINISHED",
        "BYPASSED",
        "ERROR",
    }
)


@dataclass
class Recording:
    """A recorded run, ready for the page.

    Attributes:
        source: Where it came from (the file's path).
        name: The run's (top-level graph's) name.
        events: Node changes ``{"t", "node", "state"}`` (``"result"`` when known), by time;
            ``t`` in seconds from the start of the recording.
        result: The run's result (``on_true``, ...), or None when the recording has none.
        robot: Robot readings ``{"t", ...}`` in the form of
            :func:`temoto.web.robot.robot_state` (``pose``, ``goal``, ``joints``,
            ``vehicle``, ``health``), by time.
        graph: The graph in UMRF JSON form (to draw its edges), or None.
        notes: What the reader wants a person to know (a skipped line, missing edges).
    """

    source: str
    name: str
    events: list[dict[str, Any]] = field(default_factory=list)
    result: str | None = None
    robot: list[dict[str, Any]] = field(default_factory=list)
    graph: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)

    def to_page(self) -> dict[str, Any]:
        """The ``/api/recording`` answer: the drawing plus the timed events and readings.

        Returns:
            ``{"source", "name", "result", "start", "end", "events", "robot", "graph",
            "notes"}``; ``graph`` is :func:`~temoto.web.view.graph_picture`'s drawing.
        """
        times = [e["t"] for e in self.events] + [r["t"] for r in self.robot]
        start = min(times, default=0.0)
        end = max(times, default=0.0)
        doc = self.graph
        notes = list(self.notes)
        if doc is None:
            seen: list[str] = []
            for e in self.events:
                if e["node"] not in seen:
                    seen.append(e["node"])
            doc = {"graph_name": self.name, "actions": [_ref(n) for n in seen]}
            notes.append("edges unknown: give the graph file (--graph) to draw them")
        picture = graph_picture(doc)
        return {
            "source": self.source,
            "name": self.name,
            "result": self.result,
            "start": min(start, 0.0),
            "end": end,
            "events": self.events,
            "robot": self.robot,
            "graph": picture,
            "notes": notes,
        }


def _ref(full_name: str) -> dict[str, Any]:
    """An action entry for a node known only by its full name (``Name_<id>``)."""
    name, _, instance = full_name.rpartition("_")
    if name and instance.isdigit():
        return {"name": name, "instance_id": int(instance)}
    return {"name": full_name, "instance_id": 0}  # drawn as "<name>_0"


def read_trace(path: Path) -> Recording:
    """Read a ``temoto run --trace`` file.

    Args:
        path: The JSON-lines file.

    Returns:
        The recording (events of the top-level graph and its sub-graphs, by time).

    Raises:
        ConfigError: The file cannot be read, a line is not JSON, or it holds no run; the
            message names the file and the line.
    """
    file = str(path)
    try:
        text = read_regular_text(path)
    except OSError as err:
        raise ConfigError(f"cannot read: {err.strerror or err}", file=file) from None
    name = ""
    result: str | None = None
    events: list[dict[str, Any]] = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as err:
            raise ConfigError(f"not JSON ({err.msg})", file=file, path=f"line {number}") from None
        if not isinstance(record, dict):
            raise ConfigError("expected a JSON object", file=file, path=f"line {number}")
        if "result" in record and "node" not in record:
            result = str(record["result"])
            name = str(record.get("graph", name))
            continue
        t, node, state = record.get("t"), record.get("node"), record.get("state")
        if not (
            isinstance(t, int | float)
            and math.isfinite(t)
            and isinstance(node, str)
            and state in _STATES
        ):
            raise ConfigError(
                'expected {"t": seconds, "graph", "node", "state"} or {"graph", "result"}',
                file=file,
                path=f"line {number}",
            )
        event: dict[str, Any] = {"t": float(t), "node": node, "state": state}
        for key in ("node_result", "result"):  # "result": what older traces wrote
            if isinstance(record.get(key), str):
                event["result"] = record[key]
                break
        if not name and isinstance(record.get("graph"), str):
            name = record["graph"]
        events.append(event)
    if not events and result is None:
        raise ConfigError("no trace lines: is this a `temoto run --trace` file?", file=file)
    events.sort(key=lambda e: e["t"])  # stable: lines of one instant keep their order
    return Recording(source=file, name=name or path.stem, events=events, result=result)


def read_mcap(path: Path) -> Recording:
    """Read a ``--record FILE.mcap`` recording (finished, or cut short by SIGKILL).

    The replayed run is the first graph run the recording saw start (with its sub-graphs,
    ``<run>__<Name>__<id>``); its node changes come from ``/temoto/transitions`` and its
    result from ``/temoto/graphs``. The robot readings are those of the first robot with
    samples: ``/<robot>/pose``, ``/<robot>/joint_states``, ``/<robot>/vehicle`` and
    ``/<robot>/health``, one reading per sample (the recorder writes health last in each).
    Times are seconds from the recording's first message (the messages' log times).

    A node's result (``on_true``, ``on_false``, ...) comes with the change that ends its run;
    recordings made before results were recorded show only what states tell (``on_error``,
    ``on_stopped``).

    Args:
        path: The MCAP file.

    Returns:
        The recording.

    Raises:
        ConfigError: The file cannot be read, is not an MCAP recording, or holds no graph
            run (the message names the file).
    """
    from temoto.record import read_messages

    file = str(path)
    messages, complete = read_messages(path)
    t0 = messages[0].log_time_ns if messages else 0
    name = ""
    result: str | None = None
    for m in messages:
        if m.topic != "/temoto/graphs":
            continue
        if not name and m.data.get("event") == "started":
            name = str(m.data.get("graph", ""))
        elif name and m.data.get("event") == "finished" and m.data.get("graph") == name:
            given = m.data.get("result")
            result = given if isinstance(given, str) and given else None
    if not name:  # a recording whose start was not flushed: the first transition's run
        name = next((str(m.data["graph"]) for m in messages if _is_transition(m.data)), "")
    if not name:
        raise ConfigError("no graph run in this recording (nothing to replay)", file=file)
    events: list[dict[str, Any]] = []
    for m in messages:
        if m.topic != "/temoto/transitions" or not _is_transition(m.data):
            continue
        graph = m.data["graph"]
        if graph == name or graph.startswith(name + "__"):
            t = (m.log_time_ns - t0) / 1e9
            event = {"t": t, "node": m.data["node"], "state": m.data["new"]}
            if isinstance(m.data.get("result"), str):
                event["result"] = m.data["result"]
            events.append(event)
    robot, notes = _robot_readings(messages, t0)
    if not complete:
        notes.append("the recording was cut short (no footer): replaying what it holds")
    others = sorted({str(m.data["graph"]) for m in messages if _is_transition(m.data)})
    others = [g for g in others if g != name and not g.startswith(name + "__")]
    if others:
        notes.append(f"other runs recorded, not replayed: {', '.join(others)}")
    return Recording(file, name, events, result, robot, notes=notes)


def _is_transition(data: dict[str, Any]) -> bool:
    return (
        isinstance(data.get("graph"), str)
        and isinstance(data.get("node"), str)
        and data.get("new") in _STATES
    )


#: The recorder's robot topics this replay reads, by their last part.
_ROBOT_PARTS = ("pose", "joint_states", "vehicle", "health")
#: A robot's features, by the part of a reading that shows it.
_FEATURES = (("navigation", "pose"), ("manipulation", "joints"), ("flight", "vehicle"))


def _robot_readings(messages: list[Any], t0: int) -> tuple[list[dict[str, Any]], list[str]]:
    """One robot reading per sample of the first robot with samples (and a note for others)."""
    names: list[str] = []
    for m in messages:
        robot, _, part = m.topic[1:].partition("/")
        if part in _ROBOT_PARTS and robot not in ("temoto", "fleet") and robot not in names:
            names.append(robot)
    if not names:
        return [], []
    robot = names[0]
    notes = [f"robots recorded, not shown: {', '.join(names[1:])}"] if names[1:] else []
    current: dict[str, Any] = {"pose": None, "joints": None, "vehicle": None}
    readings: list[dict[str, Any]] = []
    for m in messages:
        if not m.topic.startswith(f"/{robot}/"):
            continue
        part, data = m.topic[len(robot) + 2 :], m.data
        try:
            if part == "pose":
                pose = data["pose"]
                q = pose["orientation"]
                yaw = 2 * math.atan2(float(q["z"]), float(q["w"]))
                where = pose["position"]
                current["pose"] = {"x": float(where["x"]), "y": float(where["y"]), "yaw": yaw}
            elif part == "joint_states":
                current["joints"] = [
                    {"name": str(n), "position": float(p), "min": None, "max": None}
                    for n, p in zip(data["name"], data["position"], strict=True)
                ]
            elif part == "vehicle":
                current["vehicle"] = {
                    "lat": data["latitude"],
                    "lon": data["longitude"],
                    "alt": data["altitude"],
                    "mode": data["mode"],
                    "armed": data["armed"],
                    "battery_voltage": data.get("battery_voltage"),
                    "battery_remaining": data.get("battery_remaining"),
                    "heartbeat_age": data.get("heartbeat_age"),
                    "status": [],
                }
            elif part == "health":  # the last of a sample: the reading is complete
                ok = bool(data["healthy"])
                health = {"device": robot, "state": "ACTIVE" if ok else "FAULT", "ok": ok}
                readings.append(
                    {
                        "t": (m.log_time_ns - t0) / 1e9,
                        "name": robot,
                        "loaded": True,
                        "features": [
                            feature for feature, part in _FEATURES if current[part] is not None
                        ],
                        "goal": None,
                        "health": [{**health, "message": "" if ok else "unhealthy"}],
                        "healthy": ok,
                        **current,
                    }
                )
        except (KeyError, TypeError, ValueError) as err:  # a message of another shape
            logger.debug("%s: %s message skipped: %s", robot, part, err)
    return readings, notes


#: Readers by file suffix (lower case, with the dot); :func:`load_recording` falls back to
#: :func:`read_trace` for a suffix not listed.
READERS: dict[str, Callable[[Path], Recording]] = {".mcap": read_mcap}


def register_reader(suffix: str, reader: Callable[[Path], Recording]) -> None:
    """Make :func:`load_recording` read files ending in ``suffix`` with ``reader``.

    Args:
        suffix: The suffix with its dot (``.mcap``); case does not matter.
        reader: Turns a path into a :class:`Recording` (raising :class:`ConfigError` for a
            file it cannot read).

    Returns:
        None.

    Raises:
        ValueError: The suffix does not start with a dot.
    """
    if not suffix.startswith("."):
        raise ValueError(f"a suffix starts with a dot, got {suffix!r}")
    READERS[suffix.lower()] = reader


def load_recording(path: str | Path, graph: str | Path | None = None) -> Recording:
    """Read a recorded run, and the graph file that draws its edges if given.

    Args:
        path: The recording (a trace, or a ``.mcap`` recording).
        graph: The run's graph file (optional).

    Returns:
        The recording.

    Raises:
        ConfigError: The file (or the graph file) cannot be read, or no reader knows it.
    """
    from temoto.core.documents import graph_to_dict, load_graph

    file = Path(path)
    suffix = file.suffix.lower()
    reader = READERS.get(suffix)
    if reader is None and suffix == ".mcap":
        raise ConfigError(
            "no MCAP reader is installed in this TeMoto (replay a `--trace` file instead)",
            file=str(file),
        )
    recording = (reader or read_trace)(file)
    if graph is not None:
        recording.graph = graph_to_dict(load_graph(graph))
    return recording


class _Answers(Protocol):
    """What the view needs of the server's request handler: a JSON answer."""

    def send_json(self, status: HTTPStatus, answer: Any) -> None: ...


@final
class ReplayView(Site):
    """Serves a recording in the live view's page, with a time slider (started at once).

    Read-only: every write is refused (it has no token).

    Args:
        recording: What to replay.
        host: Address to listen on (default: this machine only).
        port: Port (0: any free port).

    Raises:
        OSError: If the address cannot be bound.
    """

    mode = "replay"

    def __init__(self, recording: Recording, host: str = "127.0.0.1", port: int = 0) -> None:
        super().__init__(host, port, token="")
        self.recording = recording
        self._answer = recording.to_page()
        self._serve()

    def _get(self, handler: _Answers, path: str) -> bool:
        if path == "/api/recording":
            handler.send_json(HTTPStatus.OK, self._answer)
            return True
        return False
