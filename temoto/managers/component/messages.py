"""Requests and responses of the ``"component"`` and ``"pipeline"`` servers (registrar values).

Frozen dataclasses whose fields are JSON-serialisable; mappings given to the constructors become
sorted ``(key, value)`` tuples (so equal requests are equal values and share one resource), and
lists read back from JSON become tuples.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from temoto.managers.component.channels import check_channel

__all__ = ["ComponentRequest", "ComponentResponse", "PipelineRequest", "PipelineResponse"]

Pairs = tuple[tuple[str, str], ...]


def _pairs(value: Any, what: str, *, channels: bool = False) -> Pairs:
    if isinstance(value, Mapping):
        items: Iterable[Any] = value.items()
    elif isinstance(value, list | tuple):
        items = value
    else:
        raise TypeError(f"{what} must be a mapping or pairs, not {type(value).__name__}")
    out: dict[str, str] = {}
    for item in items:
        if not isinstance(item, list | tuple) or len(item) != 2:
            raise TypeError(f"{what}: {item!r} is not a (name, value) pair")
        key, val = item
        if not isinstance(key, str) or not isinstance(val, str):
            raise TypeError(f"{what}: names and values must be str, got {item!r}")
        if key in out:
            raise ValueError(f"{what}: '{key}' is given twice")
        out[key] = check_channel(val) if channels else val
    return tuple(sorted(out.items()))


def _text(value: Any, what: str) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{what} must be a str, not {type(value).__name__}")
    return value


def _flag(value: Any, what: str) -> bool:
    if not isinstance(value, bool):
        raise TypeError(f"{what} must be a bool, not {type(value).__name__}")
    return value


@dataclass(frozen=True)
class ComponentRequest:
    """Ask for a component of a type (the ``"component"`` server).

    Attributes:
        type: The component type (``range_sensor``, ``camera``, ``detector``).
        name: Only this candidate (by description name); "" = any of the type.
        outputs: Output name -> channel the consumer listens on (a mapping is accepted);
            outputs left out get a channel the manager allocates (in the response).
        inputs: Input name -> channel to read (algorithms: every input must be bound).
        parameters: Parameter values for the component's program.
        local_only: Only candidates of this robot.
        failover: When the active candidate fails, substitute the next one (else FATAL).

    Raises:
        TypeError: A field of the wrong type.
        ValueError: An empty type, a bad channel, a name given twice.
    """

    type: str
    name: str = ""
    outputs: Pairs = ()
    inputs: Pairs = ()
    parameters: Pairs = ()
    local_only: bool = False
    failover: bool = True

    def __post_init__(self) -> None:
        if not _text(self.type, "type"):
            raise ValueError("a component request needs a type")
        _text(self.name, "name")
        object.__setattr__(self, "outputs", _pairs(self.outputs, "outputs", channels=True))
        object.__setattr__(self, "inputs", _pairs(self.inputs, "inputs", channels=True))
        object.__setattr__(self, "parameters", _pairs(self.parameters, "parameters"))
        _flag(self.local_only, "local_only")
        _flag(self.failover, "failover")


@dataclass(frozen=True)
class ComponentResponse:
    """The active candidate of a component resource (updated in place on failover).

    Attributes:
        resource_id: The component resource's id (on the robot that serves it).
        name: The active candidate's description name.
        type: The component type.
        robot: The robot running it.
        outputs: Output name -> channel (every output of the active candidate).
        inputs: Input name -> channel.
        pid: Its process id (on ``robot``).
        reliability: The candidate's reliability when it was chosen.
        switches: How many failovers this resource has made.
        failed: ``robot/name`` of the candidates that failed for this resource.
    """

    resource_id: str
    name: str
    type: str
    robot: str
    outputs: Pairs = ()
    inputs: Pairs = ()
    pid: int = 0
    reliability: float = 0.0
    switches: int = 0
    failed: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "outputs", _pairs(self.outputs, "outputs"))
        object.__setattr__(self, "inputs", _pairs(self.inputs, "inputs"))
        object.__setattr__(self, "failed", tuple(self.failed))

    def output(self, name: str = "") -> str:
        """The channel of an output (default: the only or first one).

        Args:
            name: The output's name, or "".

        Returns:
            The channel.

        Raises:
            KeyError: No such output.
        """
        table = dict(self.outputs)
        if not name:
            if not self.outputs:
                raise KeyError(f"component '{self.name}' has no outputs")
            return self.outputs[0][1]
        return table[name]


@dataclass(frozen=True)
class PipelineRequest:
    """Ask for a pipeline built from a template (the ``"pipeline"`` server).

    Attributes:
        template: The template's name.
        outputs: Pipeline output name -> channel the consumer listens on.
        local_only: Only components of this robot.
        failover: Segments fail over to substitutes (else a failed segment fails the pipeline).

    Raises:
        TypeError: A field of the wrong type.
        ValueError: An empty template, a bad channel.
    """

    template: str
    outputs: Pairs = ()
    local_only: bool = False
    failover: bool = True

    def __post_init__(self) -> None:
        if not _text(self.template, "template"):
            raise ValueError("a pipeline request needs a template")
        object.__setattr__(self, "outputs", _pairs(self.outputs, "outputs", channels=True))
        _flag(self.local_only, "local_only")
        _flag(self.failover, "failover")


@dataclass(frozen=True)
class PipelineResponse:
    """A loaded pipeline.

    Attributes:
        template: The template's name.
        outputs: Pipeline output name -> channel.
        segments: Segment name -> its component resource id (look the current candidate up
            with ``registrar.info(id).response``).
        links: ``"segment.output"`` -> channel, for every link inside the pipeline.
    """

    template: str
    outputs: Pairs = ()
    segments: Pairs = ()
    links: Pairs = ()

    def __post_init__(self) -> None:
        for what in ("outputs", "segments", "links"):
            value = getattr(self, what)
            object.__setattr__(self, what, tuple((str(k), str(v)) for k, v in value))

    def output(self, name: str = "") -> str:
        """The channel of a pipeline output (default: the first).

        Args:
            name: The output's name, or "".

        Returns:
            The channel.

        Raises:
            KeyError: No such output.
        """
        if not name:
            if not self.outputs:
                raise KeyError(f"pipeline '{self.template}' has no outputs")
            return self.outputs[0][1]
        return dict(self.outputs)[name]
