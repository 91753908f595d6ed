"""The values of one action run: :class:`Inputs` it reads, :class:`Outputs` it writes.

Both are checked against the action's parameter definitions (:mod:`temoto.core.params`); the
engine hands a run its input values with :meth:`Inputs.over` and takes the outputs with
:meth:`Outputs.take`.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, TypeVar

from temoto.core.params import NATIVE_TYPES, Parameter, check_value

__all__ = ["NO_INPUTS", "NO_OUTPUTS", "NO_VALUES", "Inputs", "Outputs"]

T = TypeVar("T")


class Inputs(Mapping[str, Any]):
    """The input values of one run (read-only), with typed getters.

    Args:
        values: Values by full parameter name (``pose::position::x``).
        params: The action's input parameter definitions.
    """

    __slots__ = ("_params", "_values")

    def __init__(self, values: Mapping[str, Any], params: Mapping[str, Parameter]) -> None:
        self._values = dict(values)
        self._params = params

    def __getitem__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            if name in self._params:
                raise KeyError(f"input '{name}' holds no value in this run") from None
            known = ", ".join(self._params) or "none"
            raise KeyError(f"unknown input '{name}' (inputs: {known})") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    @classmethod
    def over(cls, values: dict[str, Any], params: Mapping[str, Parameter]) -> Inputs:
        """A view over a run's values, which are handed over, not copied (framework call).

        Args:
            values: Values by full parameter name; the caller no longer changes them.
            params: The action's input parameter definitions.

        Returns:
            The inputs.
        """
        inputs = cls.__new__(cls)  # no __init__: the values are not copied
        inputs._values = values
        inputs._params = params
        return inputs

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"Inputs({self._values!r})"

    def _typed(self, name: str, kind: type[T], label: str) -> T:
        value = self[name]
        if not isinstance(value, kind):
            raise TypeError(f"input '{name}' is not a {label}: {type(value).__name__}")
        return value

    def get_string(self, name: str) -> str:
        """The value of a ``string`` input.

        Args:
            name: Parameter name.

        Returns:
            The string.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a string.
        """
        return self._typed(name, str, "string")

    def get_number(self, name: str) -> float:
        """The value of a ``number`` input.

        Args:
            name: Parameter name.

        Returns:
            The number.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a number.
        """
        value = self[name]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(f"input '{name}' is not a number: {type(value).__name__}")
        return float(value)

    def get_bool(self, name: str) -> bool:
        """The value of a ``bool`` input.

        Args:
            name: Parameter name.

        Returns:
            The boolean.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a boolean.
        """
        return self._typed(name, bool, "bool")

    def get_strings(self, name: str) -> list[str]:
        """The value of a ``strings`` input (a copy).

        Args:
            name: Parameter name.

        Returns:
            The list.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a list of strings.
        """
        return list(self._typed(name, list, "list"))

    def get_numbers(self, name: str) -> list[float]:
        """The value of a ``numbers`` input (a copy).

        Args:
            name: Parameter name.

        Returns:
            The list.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a list.
        """
        return [float(v) for v in self._typed(name, list, "list")]

    def get_bools(self, name: str) -> list[bool]:
        """The value of a ``bools`` input (a copy).

        Args:
            name: Parameter name.

        Returns:
            The list.

        Raises:
            KeyError: If the input is unknown or holds no value.
            TypeError: If it is not a list.
        """
        return list(self._typed(name, list, "list"))


class Outputs:
    """The output values an action sets during a run; checked against the description.

    Args:
        params: The action's output parameter definitions.
    """

    __slots__ = ("_params", "_values")

    def __init__(self, params: Mapping[str, Parameter]) -> None:
        self._params = params
        self._values: dict[str, Any] = {}

    def __setitem__(self, name: str, value: Any) -> None:
        param = self._params.get(name)
        if param is None:
            known = ", ".join(self._params) or "none"
            raise KeyError(f"unknown output '{name}' (outputs: {known})")
        if param.type in NATIVE_TYPES:
            try:
                value = check_value(param.type, value)
            except TypeError as err:
                raise TypeError(f"output '{name}' ({param.type}): {err}") from None
        self._values[name] = value

    def __getitem__(self, name: str) -> Any:
        return self._values[name]

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __repr__(self) -> str:
        return f"Outputs({self._values!r})"

    def snapshot(self) -> dict[str, Any]:
        """The values set so far.

        Returns:
            A copy, by name.
        """
        return dict(self._values)

    def take(self) -> dict[str, Any]:
        """The values set so far, for the engine (framework call).

        Returns:
            A copy by name, or the shared empty :data:`NO_VALUES` if none was set (the engine
            never mutates what it is given).
        """
        return dict(self._values) if self._values else NO_VALUES


#: The engine's empty value dict, shared; never mutated.
NO_VALUES: dict[str, Any] = {}

#: What an action sees before its first run, and in runs without parameters: no values, no
#: writable outputs (shared, never written).
NO_INPUTS = Inputs({}, {})
NO_OUTPUTS = Outputs({})
