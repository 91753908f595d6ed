"""Task sources: tasks given in words, turned into UMRF graphs (thesis §8, source-agnostic tasking).

A :class:`TaskSource` turns text into a UMRF graph document; the engine validates and runs it
like any other graph, so where a task comes from (a person typing, a speech recogniser, a
language model, a mission planner) does not matter to the rest of TeMoto. The shipped source,
:class:`RuleBasedTaskSource`, works offline: it splits a sentence into steps and matches each
step against a few phrasings of the robot actions it knows. A source backed by a language model
plugs into the same interface (its ``graph`` returns the document the model wrote, and the
engine's validation catches what it got wrong).

Example::

    source = RuleBasedTaskSource(places={"workshop": (2.0, 0.5), "lobby": (-1.0, 1.0)})
    doc = source.graph("go to the workshop, pick up the object, then go to the lobby")
    engine.run(doc)   # NavigateTo -> MoveJoints (pick) -> NavigateTo
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final, Protocol, runtime_checkable

from temoto.errors import TaskParseError

__all__ = ["RuleBasedTaskSource", "Step", "TaskSource"]


@runtime_checkable
class TaskSource(Protocol):
    """Something that turns a task in words into a UMRF graph document."""

    name: str

    def graph(self, text: str, *, graph_name: str = "task") -> dict[str, Any]:
        """The UMRF graph document (JSON-ready) that does what ``text`` says.

        Raises:
            TaskParseError: The text cannot be understood (the message says which part).
        """
        ...


@dataclass(frozen=True, slots=True)
class Step:
    """One understood step: the action and its input values.

    Attributes:
        text: The words it came from.
        action: The action's name (``NavigateTo``, ``MoveJoints``, ...).
        inputs: Its input values by name.
    """

    text: str
    action: str
    inputs: Mapping[str, Any]


# Splits "a, b and then c; d" into steps (commas, "then", "and", "and then", semicolons, ".").
_SPLIT: Final = re.compile(
    r"\s*(?:,\s*(?:and\s+)?(?:then\s+)?|;\s*|\.\s+|\s+and\s+then\s+|\s+then\s+|\s+and\s+)\s*"
)
_ARTICLE: Final = r"(?:the\s+|a\s+|an\s+)?"
_GO: Final = re.compile(
    rf"^(?:go|drive|navigate|move|head|return|come)\s+(?:back\s+)?to\s+{_ARTICLE}(?P<place>.+)$"
)
_PICK: Final = re.compile(rf"^(?:pick\s+up|grab|take|fetch|lift)\s+{_ARTICLE}(?P<thing>.+)$")
_PLACE: Final = re.compile(
    rf"^(?:put\s+down|place|drop|release|set\s+down)\s+{_ARTICLE}(?P<thing>.+)$"
)
_PLACE_IT: Final = re.compile(r"^(?:put|set|lay)\s+(?:it|them|(?:the\s+)?\w+)\s+down$")
_POSE: Final = re.compile(
    r"^(?:move|put|bring)\s+(?:the\s+)?arm\s+(?:to\s+)?(?:the\s+)?(?P<pose>\w+)(?:\s+pose)?$"
)
_TAKEOFF: Final = re.compile(r"^take\s*off(?:\s+to\s+(?P<alt>[0-9.]+)\s*m(?:eters|etres)?)?$")
_LAND: Final = re.compile(r"^land$")


class RuleBasedTaskSource:
    """An offline task source for the built-in robot actions.

    Phrasings it understands (case does not matter; steps are separated by commas, "then",
    "and", semicolons or full stops):

    * "go to / drive to / navigate to / head to / return to [the] PLACE" → ``NavigateTo``
      the place's coordinates;
    * "pick up / grab / take / fetch [the] THING" → ``MoveJoints`` to the pick pose;
    * "put down / place / drop [the] THING", "put it down" → ``MoveJoints`` to the place
      pose;
    * "move the arm to POSE" → ``MoveJoints`` to that pose;
    * "take off [to N m]", "land" → ``TakeOff``, ``Land``.

    Args:
        places: Named places and their (x, y) in the robot's odometry frame.
        pick_pose: The arm pose that picks something up.
        place_pose: The arm pose that puts it down.
        robot: The ``robot`` input of every step (empty: the engine's robot).
        takeoff_altitude: Metres, when "take off" names none.

    Raises:
        ValueError: A place name is empty or its coordinates are not two numbers.
    """

    name = "rule-based"

    def __init__(
        self,
        places: Mapping[str, tuple[float, float]],
        *,
        pick_pose: str = "reach",
        place_pose: str = "stow",
        robot: str = "",
        takeoff_altitude: float = 5.0,
    ) -> None:
        self.places: dict[str, tuple[float, float]] = {}
        for place, xy in places.items():
            if not place.strip() or len(xy) != 2:
                raise ValueError(f"a place needs a name and (x, y): {place!r}: {xy!r}")
            self.places[place.strip().lower()] = (float(xy[0]), float(xy[1]))
        self.pick_pose = pick_pose
        self.place_pose = place_pose
        self.robot = robot
        self.takeoff_altitude = takeoff_altitude

    def steps(self, text: str) -> list[Step]:
        """Understand ``text`` step by step.

        Args:
            text: The task.

        Returns:
            The steps, in order.

        Raises:
            TaskParseError: A step matches no phrasing, or names an unknown place; the message
                quotes the step and lists what is known.
        """
        cleaned = text.strip().lower().rstrip(".!")
        if not cleaned:
            raise TaskParseError("the task is empty")
        steps: list[Step] = []
        for part in (p.strip() for p in _SPLIT.split(cleaned)):
            if not part:
                continue
            steps.append(self._step(part))
        return steps

    def graph(self, text: str, *, graph_name: str = "task") -> dict[str, Any]:
        """A sequential UMRF graph of the steps of ``text``.

        Args:
            text: The task.
            graph_name: The graph's name.

        Returns:
            The UMRF graph document.

        Raises:
            TaskParseError: The text cannot be understood.
        """
        steps = self.steps(text)
        counts: dict[str, int] = {}
        names: list[tuple[str, int]] = []
        for step in steps:
            iid = counts.get(step.action, 0)
            counts[step.action] = iid + 1
            names.append((step.action, iid))
        actions: list[dict[str, Any]] = []
        for i, (step, (action, iid)) in enumerate(zip(steps, names, strict=True)):
            inputs = dict(step.inputs)
            if self.robot:
                inputs["robot"] = self.robot
            umrf: dict[str, Any] = {
                "name": action,
                "instance_id": iid,
                "type": "sync",
                "description": step.text,
                "input_parameters": {
                    key: {"pvf_type": _pvf_type(value), "pvf_value": value}
                    for key, value in inputs.items()
                },
            }
            if i > 0:
                prev = names[i - 1]
                umrf["parents"] = [{"name": prev[0], "instance_id": prev[1]}]
            if i + 1 < len(names):
                nxt = names[i + 1]
                umrf["children"] = [{"name": nxt[0], "instance_id": nxt[1]}]
            actions.append(umrf)
        first, last = names[0], names[-1]
        return {
            "graph_name": graph_name,
            "graph_description": f"{self.name} task: {text.strip()}",
            "graph_entry": [{"name": first[0], "instance_id": first[1]}],
            "graph_exit": [{"name": last[0], "instance_id": last[1]}],
            "actions": actions,
        }

    def _step(self, part: str) -> Step:
        if m := _TAKEOFF.match(part):
            alt = float(m["alt"]) if m["alt"] else self.takeoff_altitude
            return Step(part, "TakeOff", {"altitude": alt})
        if _LAND.match(part):
            return Step(part, "Land", {})
        if m := _GO.match(part):
            place = m["place"].strip()
            xy = self.places.get(place)
            if xy is None:
                known = ", ".join(sorted(self.places)) or "none"
                raise TaskParseError(f"{part!r}: unknown place {place!r} (known places: {known})")
            return Step(part, "NavigateTo", {"x": xy[0], "y": xy[1]})
        if _PICK.match(part):
            return Step(part, "MoveJoints", {"pose": self.pick_pose})
        if _PLACE.match(part) or _PLACE_IT.match(part):
            return Step(part, "MoveJoints", {"pose": self.place_pose})
        if m := _POSE.match(part):
            return Step(part, "MoveJoints", {"pose": m["pose"]})
        raise TaskParseError(
            f"{part!r}: not understood (say: go to PLACE, pick up THING, put down THING,"
            " move the arm to POSE, take off, land)"
        )


def _pvf_type(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int | float):
        return "number"
    return "string"
