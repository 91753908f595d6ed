"""Actions declared in Python: :func:`action`, :class:`Param`, :func:`catalog`.

Part of :mod:`temoto.build` (its docstring is the overview).
"""

from __future__ import annotations

import inspect
import keyword
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol, TypeAlias, TypeVar, overload

from temoto.core.action import Action
from temoto.core.catalog import ActionCatalog
from temoto.core.params import NATIVE_TYPES, NO_VALUE, Parameter, check_value
from temoto.core.umrf import Umrf, parse_umrf

__all__ = ["ActionDecorator", "Param", "ParamDecl", "action", "catalog", "description_of"]

#: Python types accepted as parameter types, and their ``pvf_type``.
_PY_TYPES: dict[object, str] = {
    str: "string",
    float: "number",
    int: "number",
    bool: "bool",
    list[str]: "strings",
    list[float]: "numbers",
    list[int]: "numbers",
    list[bool]: "bools",
}


@dataclass(frozen=True, slots=True)
class Param:
    """A parameter declared with more than its type.

    Attributes:
        type: A ``pvf_type`` name (``"string"``, ``"number"``, ``"bool"``, ``"strings"``,
            ``"numbers"``, ``"bools"``, or any other name for a value that only Python code
            passes on) or a Python type (``str``, ``float``, ``int``, ``bool``, ``list[str]``,
            ``list[float]``, ``list[bool]``).
        default: A literal value (``pvf_value``); every node gets it unless given another.
        required: ``pvf_required``: an input without a value holds its node back.
        updatable: ``pvf_updatable``: parents may overwrite a literal.
        allowed: ``pvf_allowed_values``: the only values the input accepts (empty: any).
    """

    type: str | type | Any
    default: Any = NO_VALUE
    required: bool = True
    updatable: bool = True
    allowed: Sequence[Any] = ()

    def umrf(self) -> dict[str, Any]:
        """The parameter in UMRF JSON (``{"pvf_type": ...}``).

        Returns:
            A JSON-ready dict.

        Raises:
            TypeError: The type is neither a ``pvf_type`` name nor a Python type listed above.
        """
        out: dict[str, Any] = {"pvf_type": _pvf_type(self.type)}
        if self.default is not NO_VALUE:
            out["pvf_value"] = self.default
        if not self.required:
            out["pvf_required"] = False
        if not self.updatable:
            out["pvf_updatable"] = False
        if self.allowed:
            out["pvf_allowed_values"] = list(self.allowed)
        return out

    def parameter(self, name: str) -> Parameter:
        """The declared parameter as the graph model holds it.

        Args:
            name: Its full name.

        Returns:
            The parameter.

        Raises:
            TypeError: The type is unknown, or the default or an allowed value does not fit it.
        """
        pvf_type = _pvf_type(self.type)
        value, allowed = self.default, tuple(self.allowed)
        if pvf_type in NATIVE_TYPES:
            single = pvf_type if pvf_type in ("string", "number", "bool") else pvf_type[:-1]
            try:
                if value is not NO_VALUE:
                    value = check_value(pvf_type, value)
                allowed = tuple(check_value(single, v) for v in allowed)
            except TypeError as err:
                raise TypeError(f"parameter '{name}' ({pvf_type}): {err}") from None
        return Parameter(name, pvf_type, value, self.required, self.updatable, allowed)


#: How one parameter may be declared: a type (``str``, ``"number"``) or a :class:`Param`.
ParamDecl: TypeAlias = "str | type | Param | Any"


def _pvf_type(spec: object) -> str:
    if isinstance(spec, str):
        if not spec:
            raise TypeError("a parameter type may not be empty")
        return spec
    found = _PY_TYPES.get(spec)
    if found is None:
        known = "str, float, int, bool, list[str], list[float], list[bool]"
        raise TypeError(f"{spec!r} is not a parameter type: use a pvf_type name or one of {known}")
    return found


def _tree(specs: Mapping[str, ParamDecl] | None) -> dict[str, Any]:
    """A parameter tree in UMRF JSON from declared parameters (``a::b`` names nest)."""
    root: dict[str, Any] = {}
    for name, spec in (specs or {}).items():
        if not isinstance(name, str) or not name:
            raise TypeError(f"parameter names are non-empty strings, got {name!r}")
        declared = spec if isinstance(spec, Param) else Param(spec)
        *spaces, leaf = name.split("::")
        place = root
        for space in spaces:
            place = place.setdefault(space, {})
        place[leaf] = declared.umrf()
    return root


_A = TypeVar("_A", bound="type[Action]")


class ActionDecorator(Protocol):
    """What ``@action(...)`` with arguments returns: the decorator proper."""

    @overload
    def __call__(self, obj: _A, /) -> _A: ...
    @overload
    def __call__(self, obj: Callable[..., Any], /) -> type[Action]: ...


@overload
def action(
    target: _A,
    /,
    *,
    name: str | None = None,
    inputs: Mapping[str, ParamDecl] | None = None,
    outputs: Mapping[str, ParamDecl] | None = None,
    type: str = "sync",
    blocking: bool | None = None,
) -> _A: ...
@overload
def action(
    target: Callable[..., Any],
    /,
    *,
    name: str | None = None,
    inputs: Mapping[str, ParamDecl] | None = None,
    outputs: Mapping[str, ParamDecl] | None = None,
    type: str = "sync",
    blocking: bool | None = None,
) -> type[Action]: ...
@overload
def action(
    target: None = None,
    /,
    *,
    name: str | None = None,
    inputs: Mapping[str, ParamDecl] | None = None,
    outputs: Mapping[str, ParamDecl] | None = None,
    type: str = "sync",
    blocking: bool | None = None,
) -> ActionDecorator: ...


def action(
    target: Any = None,
    /,
    *,
    name: str | None = None,
    inputs: Mapping[str, ParamDecl] | None = None,
    outputs: Mapping[str, ParamDecl] | None = None,
    type: str = "sync",  # noqa: A002 - the UMRF key's name
    blocking: bool | None = None,
) -> Any:
    """Declare an action's name, type, inputs and outputs where it is written.

    On an :class:`~temoto.core.action.Action` subclass, it attaches the description (read with
    :func:`description_of`) and returns the class. On a function, it returns a new Action
    subclass whose ``on_run`` calls the function with the run's input values as keyword
    arguments (inputs without a value are left out, so the function's defaults apply). The
    function returns True or False (the result), or a mapping of output values (the result is
    then ``on_true``); anything else is a ``TypeError``, so the node ends ``on_error``. Write a
    class when the action must wait, stop, pause or acquire resources.

    Usable bare (``@action``) or with arguments (``@action(inputs={"x": float})``).

    Args:
        target: The class or function (given by the bare decorator form).
        name: The action's name (default: the class's name, or the function's name in
            CamelCase: ``shout_twice`` becomes ``ShoutTwice``).
        inputs: Input parameters by name: a type (``str``, ``"number"``) or a :class:`Param`.
        outputs: Output parameters, likewise.
        type: ``sync``, ``async`` or ``spontaneous`` (re-run until stopped).
        blocking: Set the class's ``blocking`` (False: ``on_run`` never waits and runs
            inline); default: a class keeps its own, a function action is blocking.

    Returns:
        The class, or a decorator that returns it.

    Raises:
        TypeError: ``target`` is neither an Action subclass nor a function, or a parameter
            type is unknown.
        temoto.errors.UmrfError: The description is not valid UMRF (the message names the key).
    """

    def decorate(obj: Any) -> Any:
        return _describe(obj, name, inputs, outputs, type, blocking)

    return decorate if target is None else decorate(target)


def _describe(
    obj: Any,
    name: str | None,
    inputs: Mapping[str, ParamDecl] | None,
    outputs: Mapping[str, ParamDecl] | None,
    kind: str,
    blocking: bool | None,
) -> type[Action]:
    """What :func:`action` does to the class or function it decorates."""
    cls: type[Action]
    if inspect.isclass(obj):
        if not issubclass(obj, Action):
            raise TypeError(f"@action: {obj.__qualname__} is not a subclass of temoto.Action")
        cls = obj
    elif inspect.isfunction(obj):
        cls = _function_action(obj, name or _camel(obj.__name__))
    else:
        raise TypeError(f"@action decorates an Action subclass or a function, not {obj!r}")
    doc: dict[str, Any] = {"name": name or cls.__name__, "type": kind}
    if cls.__doc__ and cls.__doc__.strip():
        doc["description"] = inspect.cleandoc(cls.__doc__).split("\n\n")[0]
    tree_in, tree_out = _tree(inputs), _tree(outputs)
    if tree_in:
        doc["input_parameters"] = tree_in
    if tree_out:
        doc["output_parameters"] = tree_out
    file = obj.__code__.co_filename if inspect.isfunction(obj) else None
    cls.umrf = parse_umrf(doc, file=file)  # type: ignore[attr-defined]
    if blocking is not None:
        cls.blocking = blocking
    return cls


def _camel(snake: str) -> str:
    """``shout_twice`` → ``ShoutTwice``; a name already CamelCase is kept."""
    return "".join(part[:1].upper() + part[1:] for part in snake.split("_") if part)


class _FunctionAction(Action):
    """An action whose ``on_run`` calls a plain function (made by :func:`action`)."""

    function: ClassVar[Callable[..., Any]]

    def on_run(self) -> bool:
        """Call the function with the input values; set its outputs; return its result.

        Returns:
            The function's bool, or True when it returned a mapping of outputs.

        Raises:
            TypeError: The function returned something else.
        """
        returned = type(self).function(**self.inputs)
        if isinstance(returned, bool):
            return returned
        if isinstance(returned, Mapping):
            for key, value in returned.items():
                self.outputs[key] = value
            return True
        raise TypeError(
            f"{self.name}: the function returned {type(returned).__name__}; return True or"
            " False, or a dict of output values"
        )


def _function_action(function: Callable[..., Any], name: str) -> type[Action]:
    if not name.isidentifier() or keyword.iskeyword(name):
        raise TypeError(f"@action: {name!r} is not a valid action name; pass name=")
    namespace = {
        "function": staticmethod(function),
        "__module__": function.__module__,
        "__qualname__": name,
        "__doc__": function.__doc__,
    }
    return type(name, (_FunctionAction,), namespace)


def description_of(cls: type[Action]) -> Umrf:
    """The description :func:`action` attached to a class.

    Args:
        cls: A decorated Action subclass.

    Returns:
        Its description (name, type, parameters).

    Raises:
        TypeError: ``cls`` was not decorated with :func:`action`.
    """
    found = getattr(cls, "__dict__", {}).get("umrf")  # its own: a subclass is another action
    if not isinstance(found, Umrf):
        what = getattr(cls, "__qualname__", repr(cls))
        raise TypeError(f"{what} has no description: decorate it with @temoto.action(...)")
    return found


def catalog(
    *actions: type[Action], paths: Iterable[str | Path] = (), entry_points: bool = False
) -> ActionCatalog:
    """An action catalog of decorated actions (and, optionally, folders of actions).

    Args:
        actions: Classes decorated with :func:`action` (or made by it from functions).
        paths: Folders of ``*.umrf.json`` actions to add, as ``--actions`` does.
        entry_points: Also index the installed action packages (entry point group
            ``temoto.action_packages``).

    Returns:
        The catalog, for ``ActionEngine(actions=...)`` or a graph's ``catalog=``.

    Raises:
        TypeError: An action is not decorated.
    """
    out = ActionCatalog(paths, use_entry_points=entry_points)
    for cls in actions:
        out.register(cls, description_of(cls))
    return out
