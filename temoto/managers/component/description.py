"""Component descriptions and pipeline templates, and their files (YAML or JSON).

A description file holds a list of ``components`` and a list of ``templates``::

    components:
      - name: lidar_3d_front          # unique per robot
        type: range_sensor             # what a request asks for
        executable: "{python}"         # {python}: this interpreter; {here}: this file's folder
        args: ["-S", "-I", "{here}/sim_sensor.py", "--output", "{output:scan}",
               "--name", "{name}", "--rate", "{param:rate}"]
        outputs: [scan]                # channels the manager binds ({output:NAME})
        inputs: []                     # channels it reads ({input:NAME}); algorithms
        parameters: {rate: "100"}      # defaults; null = required ({param:NAME})
        priority: 3                    # user-defined order, higher first (thesis demo 1)
        robot: ""                      # the robot hosting it; "" = the manager's own
        reliability: 0.8               # initial reliability
        env: {}                        # extra environment variables
    templates:
      - name: tracking
        segments:                      # name -> component type and input links
          camera: {type: camera}
          detector: {type: detector, inputs: {image: camera.image}}
          tracker: {type: tracker, inputs: {detections: detector.detections}}
        outputs: {tracks: tracker.tracks}   # the pipeline's outputs

Placeholders in ``executable`` and ``args``: ``{python}`` and ``{here}`` are filled when the
file is read; ``{name}``, ``{type}``, ``{robot}``, ``{output:X}``, ``{input:X}`` and
``{param:X}`` when the component is started. Anything else in braces is an error.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from temoto.errors import ConfigError, PipelineError

__all__ = [
    "ComponentDescription",
    "PipelineTemplate",
    "Segment",
    "load_descriptions",
    "parse_descriptions",
]

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_\-]*\Z")
_PLACEHOLDER = re.compile(r"\{([a-z]+)(?::([A-Za-z_][A-Za-z0-9_\-]*))?\}")
_AT_START = frozenset({"name", "type", "robot"})
_WITH_ARG = frozenset({"output", "input", "param"})

_COMPONENT_KEYS = frozenset(
    {
        "name",
        "type",
        "executable",
        "args",
        "outputs",
        "inputs",
        "parameters",
        "priority",
        "robot",
        "reliability",
        "env",
        "description",
    }
)


def _pairs(value: Mapping[str, str] | Iterable[tuple[str, str]]) -> tuple[tuple[str, str], ...]:
    items = value.items() if isinstance(value, Mapping) else value
    return tuple(sorted((str(k), str(v)) for k, v in items))


@dataclass(frozen=True)
class ComponentDescription:
    """One component: a program that senses or processes, and how to start it.

    Attributes:
        name: Unique per robot (a candidate's identity, with ``robot``).
        type: What requests ask for (``range_sensor``, ``camera``, ``detector``).
        executable: The program (``{python}`` already replaced).
        args: Its arguments, with start-time placeholders.
        outputs: Output names (the manager binds each to a channel).
        inputs: Input names (algorithms: each must be bound to a channel).
        parameters: Defaults as ``(name, value)`` pairs; ``None`` = required.
        priority: Higher is tried first.
        robot: Hosting robot; "" = the manager's own.
        reliability: Initial reliability in [0, 1].
        env: Extra environment variables as sorted pairs.
        description: Free text.
        source: The file it came from ("" if made in code).
    """

    name: str
    type: str
    executable: str
    args: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    inputs: tuple[str, ...] = ()
    parameters: tuple[tuple[str, str | None], ...] = ()
    priority: int = 0
    robot: str = ""
    reliability: float = 0.8
    env: tuple[tuple[str, str], ...] = ()
    description: str = ""
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = self.source or None
        for what in ("name", "type"):
            value = getattr(self, what)
            if not isinstance(value, str) or _NAME.match(value) is None:
                raise ConfigError(f"{what} must be an identifier, got {value!r}", file=where)
        if not isinstance(self.executable, str) or not self.executable:
            raise ConfigError(f"component '{self.name}': executable is empty", file=where)
        if not isinstance(self.robot, str):
            raise ConfigError(f"component '{self.name}': robot must be a str", file=where)
        if isinstance(self.priority, bool) or not isinstance(self.priority, int):
            raise ConfigError(f"component '{self.name}': priority must be an int", file=where)
        rel = self.reliability
        if isinstance(rel, bool) or not isinstance(rel, int | float) or not 0.0 <= rel <= 1.0:
            raise ConfigError(
                f"component '{self.name}': reliability must be a number in [0, 1]", file=where
            )
        object.__setattr__(self, "reliability", float(rel))
        object.__setattr__(self, "args", tuple(str(a) for a in self.args))
        for what in ("outputs", "inputs"):
            names = tuple(getattr(self, what))
            for n in names:
                if not isinstance(n, str) or _NAME.match(n) is None:
                    raise ConfigError(
                        f"component '{self.name}': {what} name {n!r} is not an identifier",
                        file=where,
                    )
            if len(set(names)) != len(names):
                raise ConfigError(f"component '{self.name}': duplicate {what}", file=where)
            object.__setattr__(self, what, names)
        params = dict(self.parameters)
        object.__setattr__(
            self,
            "parameters",
            tuple(sorted((str(k), None if v is None else str(v)) for k, v in params.items())),
        )
        object.__setattr__(self, "env", _pairs(self.env))
        known = {
            "output": set(self.outputs),
            "input": set(self.inputs),
            "param": set(params),
        }
        for text in (self.executable, *self.args):
            for m in _PLACEHOLDER.finditer(text):
                kind, arg = m.group(1), m.group(2)
                if arg is None and kind in _AT_START:
                    continue
                if arg is not None and kind in _WITH_ARG:
                    if arg not in known[kind]:
                        raise ConfigError(
                            f"component '{self.name}': {m.group(0)} names no declared {kind}",
                            file=where,
                        )
                    continue
                raise ConfigError(
                    f"component '{self.name}': unknown placeholder {m.group(0)}", file=where
                )

    def argv(
        self,
        robot: str,
        outputs: Mapping[str, str],
        inputs: Mapping[str, str],
        parameters: Mapping[str, str],
    ) -> tuple[str, list[str]]:
        """The executable and arguments with every placeholder filled.

        Args:
            robot: The hosting robot's name.
            outputs: Output name -> channel (every output).
            inputs: Input name -> channel (every input).
            parameters: Parameter values given by the request (defaults fill the rest).

        Returns:
            ``(executable, args)``.

        Raises:
            ValueError: A required parameter or an input is missing, or an unknown parameter.
        """
        unknown = set(parameters) - {k for k, _ in self.parameters}
        if unknown:
            raise ValueError(
                f"component '{self.name}' has no parameter(s) {', '.join(sorted(unknown))}"
            )
        values = {k: v for k, v in self.parameters if v is not None} | dict(parameters)
        missing = [k for k, _ in self.parameters if k not in values]
        if missing:
            raise ValueError(f"component '{self.name}' needs parameter(s) {', '.join(missing)}")
        unbound = [n for n in self.inputs if n not in inputs]
        if unbound:
            raise ValueError(
                f"component '{self.name}' needs its input(s) {', '.join(unbound)} bound to channels"
            )
        table = {
            "output": outputs,
            "input": inputs,
            "param": values,
            "": {"name": self.name, "type": self.type, "robot": robot},
        }

        def fill(m: re.Match[str]) -> str:
            kind, arg = m.group(1), m.group(2)
            if arg is None:
                return str(table[""][kind])
            return str(table[kind][arg])

        return _PLACEHOLDER.sub(fill, self.executable), [
            _PLACEHOLDER.sub(fill, a) for a in self.args
        ]


@dataclass(frozen=True)
class Segment:
    """One step of a pipeline template.

    Attributes:
        name: The segment's name in the template.
        type: The component type it needs.
        inputs: ``(input name, "segment.output")`` pairs.
        parameters: ``(name, value)`` pairs passed to the component.
    """

    name: str
    type: str
    inputs: tuple[tuple[str, str], ...] = ()
    parameters: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class PipelineTemplate:
    """Components composed into a pipeline (a directed acyclic graph of segments).

    Attributes:
        name: The template's name (what pipeline requests ask for).
        segments: The segments, in the order written.
        outputs: ``(pipeline output, "segment.output")`` pairs.
        source: The file it came from.

    Raises:
        PipelineError: A link names an unknown segment, or the links form a cycle.
    """

    name: str
    segments: tuple[Segment, ...]
    outputs: tuple[tuple[str, str], ...] = ()
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        self.order()  # validates

    def segment(self, name: str) -> Segment:
        """A segment by name (KeyError if none)."""
        for seg in self.segments:
            if seg.name == name:
                return seg
        raise KeyError(name)

    def order(self) -> list[Segment]:
        """The segments in start order: every producer before its consumers.

        Returns:
            The segments, topologically sorted (ties in written order).

        Raises:
            PipelineError: An unknown segment in a link, or a cycle (named in the message).
        """
        where = self.source or None
        by_name: dict[str, Segment] = {}
        for seg in self.segments:
            if seg.name in by_name:
                raise PipelineError(
                    f"template '{self.name}': segment '{seg.name}' is defined twice", file=where
                )
            by_name[seg.name] = seg
        if not by_name:
            raise PipelineError(f"template '{self.name}' has no segments", file=where)
        deps: dict[str, list[str]] = {}
        for seg in self.segments:
            deps[seg.name] = []
            for inp, link in seg.inputs:
                deps[seg.name].append(self._producer(link, f"segment '{seg.name}' input '{inp}'"))
        for out, link in self.outputs:
            self._producer(link, f"output '{out}'")
        used = [link for seg in self.segments for _, link in seg.inputs]
        used += [link for _, link in self.outputs]
        twice = sorted({link for link in used if used.count(link) > 1})
        if twice:
            raise PipelineError(
                f"template '{self.name}': {', '.join(twice)} feeds more than one input or output"
                " (a channel has one listener; add a tee component)",
                file=where,
            )
        done: list[Segment] = []
        state: dict[str, int] = {}  # 1: on the path, 2: done
        path: list[str] = []

        def visit(name: str) -> None:
            if state.get(name) == 2:
                return
            if state.get(name) == 1:
                cycle = [*path[path.index(name) :], name]
                raise PipelineError(
                    f"template '{self.name}' has a cycle: {' -> '.join(cycle)}", file=where
                )
            state[name] = 1
            path.append(name)
            for dep in deps[name]:
                visit(dep)
            path.pop()
            state[name] = 2
            done.append(by_name[name])

        for seg in self.segments:
            visit(seg.name)
        return done

    def _producer(self, link: str, what: str) -> str:
        seg, dot, _out = link.partition(".")
        if not dot or not _out or seg not in {s.name for s in self.segments}:
            raise PipelineError(
                f"template '{self.name}': {what} links to {link!r}, not <segment>.<output>"
                " of a segment of this template",
                file=self.source or None,
            )
        return seg


def parse_descriptions(
    doc: Any, *, source: str = "", here: str | Path | None = None
) -> tuple[list[ComponentDescription], list[PipelineTemplate]]:
    """Components and templates from a parsed description document.

    Args:
        doc: A mapping with optional ``components`` and ``templates`` lists.
        source: The file name (for messages).
        here: The folder ``{here}`` stands for (default: the source's folder).

    Returns:
        The components and templates.

    Raises:
        ConfigError: Malformed components (the file and key path in the message).
        PipelineError: A malformed or cyclic template.
    """
    where = source or None
    folder = str(Path(here) if here is not None else Path(source or ".").resolve().parent)
    if not isinstance(doc, Mapping):
        raise ConfigError("a description file must hold a mapping", file=where)
    extra = set(doc) - {"components", "templates"}
    if extra:
        raise ConfigError(f"unknown key(s) {', '.join(sorted(map(str, extra)))}", file=where)
    components: list[ComponentDescription] = []
    for i, raw in enumerate(_list(doc.get("components"), "components", where)):
        path = f"components[{i}]"
        if not isinstance(raw, Mapping):
            raise ConfigError("must be a mapping", file=where, path=path)
        unknown = set(raw) - _COMPONENT_KEYS
        if unknown:
            raise ConfigError(
                f"unknown key(s) {', '.join(sorted(map(str, unknown)))}", file=where, path=path
            )
        for key in ("name", "type", "executable"):
            if key not in raw:
                raise ConfigError(f"'{key}' is missing", file=where, path=path)

        def expand(text: Any) -> str:
            return str(text).replace("{python}", sys.executable).replace("{here}", folder)

        try:
            components.append(
                ComponentDescription(
                    name=raw["name"],
                    type=raw["type"],
                    executable=expand(raw["executable"]),
                    args=tuple(expand(a) for a in _list(raw.get("args"), f"{path}.args", where)),
                    outputs=tuple(_list(raw.get("outputs"), f"{path}.outputs", where)),
                    inputs=tuple(_list(raw.get("inputs"), f"{path}.inputs", where)),
                    parameters=tuple(
                        _map(raw.get("parameters"), f"{path}.parameters", where).items()
                    ),
                    priority=raw.get("priority", 0),
                    robot=raw.get("robot", "") or "",
                    reliability=raw.get("reliability", 0.8),
                    env=_pairs(_map(raw.get("env"), f"{path}.env", where)),
                    description=str(raw.get("description", "")),
                    source=source,
                )
            )
        except ConfigError as err:
            raise ConfigError(err.reason, file=where, path=path) from None
    templates: list[PipelineTemplate] = []
    for i, raw in enumerate(_list(doc.get("templates"), "templates", where)):
        path = f"templates[{i}]"
        if not isinstance(raw, Mapping) or "name" not in raw or "segments" not in raw:
            raise PipelineError("a template needs 'name' and 'segments'", file=where, path=path)
        segments = []
        for seg_name, seg in _map(raw["segments"], f"{path}.segments", where).items():
            if not isinstance(seg, Mapping) or "type" not in seg:
                raise PipelineError(
                    f"segment '{seg_name}' needs a 'type'", file=where, path=f"{path}.segments"
                )
            segments.append(
                Segment(
                    str(seg_name),
                    str(seg["type"]),
                    _pairs(_map(seg.get("inputs"), f"{path}.segments.{seg_name}.inputs", where)),
                    _pairs(
                        _map(seg.get("parameters"), f"{path}.segments.{seg_name}.parameters", where)
                    ),
                )
            )
        try:
            templates.append(
                PipelineTemplate(
                    str(raw["name"]),
                    tuple(segments),
                    _pairs(_map(raw.get("outputs"), f"{path}.outputs", where)),
                    source=source,
                )
            )
        except PipelineError as err:
            raise PipelineError(err.reason, file=where, path=path) from None
    return components, templates


def load_descriptions(
    path: str | Path,
) -> tuple[list[ComponentDescription], list[PipelineTemplate]]:
    """Read a description file (``.yaml``/``.yml``, or ``.json``).

    Args:
        path: The file.

    Returns:
        Its components and templates.

    Raises:
        ConfigError: It cannot be read or parsed, or is malformed.
        PipelineError: A template is malformed or cyclic.
    """
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
        doc = json.loads(text) if file.suffix == ".json" else yaml.safe_load(text)
    except (OSError, ValueError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot read: {err}", file=str(file)) from err
    return parse_descriptions(doc or {}, source=str(file))


def _list(value: Any, path: str, where: str | None) -> Sequence[Any]:
    if value is None:
        return []
    if not isinstance(value, list | tuple):
        raise ConfigError("must be a list", file=where, path=path)
    return value


def _map(value: Any, path: str, where: str | None) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError("must be a mapping", file=where, path=path)
    return {str(k): v for k, v in value.items()}
