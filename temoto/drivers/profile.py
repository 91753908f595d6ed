"""Reading hardware profiles: one typed reader for the profile and every driver's entry.

A hardware profile (:mod:`temoto.config`) is checked in two places: the profile itself (robot,
devices, features) and each device's entry, which its driver reads. Both use
:class:`ProfileReader`, so every problem is reported the same way: a
:class:`~temoto.errors.ProfileError` whose message is ``<file>: <key path>: <what is wrong>``
(``sim_rover.yaml: devices.base.nodes[1].node_id: duplicate node id 1 (nodes[0])``), and the
robot command exits with status 2.

A driver declares the keys of its entry as data, a mapping of key → :class:`Field` built by the
field kinds below, with defaults and ranges::

    profile_fields = {
        "link": custom(read_link, hint="e.g. serial:/dev/ttyUSB0"),
        "poll_rate": number(50.0, low=0, high=1000, unit="Hz"),
        "timeout_polls": integer(3, low=1),
    }

and :meth:`~temoto.drivers.base.Driver.from_profile` reads the entry with them: unknown keys
are refused (naming the known ones), a missing required key says what to write, a value of the
wrong kind or out of range says what it must be and what it was. A driver that needs more
(lists of motors, links, checks across keys) reads those parts with the reader's own methods,
so their messages have the same form.

=================  =========================================================================
field kind         what it accepts
=================  =========================================================================
:func:`number`     an int or float (not a bool), finite, within an optional range
:func:`integer`    an int (not a bool), within an optional range
:func:`text`       a string (non-empty unless told otherwise)
:func:`name`       a name: a letter, then letters, digits, ``_ . -``; at most 63
:func:`flag`       ``true`` or ``false``
:func:`choice`     one of a fixed set of strings
:func:`custom`     anything a function of the driver's accepts (it raises through the reader)
=================  =========================================================================
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Generic, NoReturn, Self, TypeVar, overload

from temoto.errors import ProfileError

__all__ = [
    "REQUIRED",
    "Field",
    "ProfileReader",
    "choice",
    "custom",
    "flag",
    "integer",
    "name",
    "number",
    "text",
]

T = TypeVar("T")

#: A name in a profile (robot, device, joint, pose): a letter, then letters, digits, ``_ . -``.
NAME_PATTERN: Final = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,62}$")


class _Required:
    """The marker of a field without a default (see :data:`REQUIRED`)."""

    def __repr__(self) -> str:
        return "REQUIRED"


#: The ``default`` of a field that must be present.
REQUIRED: Final = _Required()

#: Reads a present value: ``(reader, value, key path) -> checked value``; raises through the
#: reader (:meth:`ProfileReader.fail`).
Reader = Callable[["ProfileReader", Any, str], T]


@dataclass(frozen=True, slots=True)
class Field(Generic[T]):
    """One key of a profile entry: how its value is read, and what it is when absent.

    Build fields with the field kinds (:func:`number`, :func:`integer`, ...), not directly.

    Attributes:
        read: Checks and converts a present value (``None`` counts as absent).
        default: The value when the key is absent, or :data:`REQUIRED`.
        hint: For a missing required key: what to write (``e.g. udpin:127.0.0.1:14550``).
        init: Whether the value is an argument of the driver's constructor (``driver``,
            ``safe_state`` and ``sim`` are not).
    """

    read: Reader[T]
    default: T | _Required = REQUIRED
    hint: str = ""
    init: bool = True


def _range_text(
    low: float | None, high: float | None, low_open: bool, unit: str, integral: bool
) -> str:
    """How a range reads in a message: ``a positive number``, ``an integer 0..63``, ..."""
    suffix = f" {unit}" if unit else ""
    if integral:
        if low is not None and high is not None:
            return f"an integer {low:g}..{high:g}{suffix}"
        if low is not None:
            return f"an integer >= {low:g}{suffix}"
        if high is not None:
            return f"an integer <= {high:g}{suffix}"
        return "an integer"
    if low is not None and high is not None:
        return f"a number in {'(' if low_open else '['}{low:g}, {high:g}]{suffix}"
    if low == 0 and low_open:
        return f"a positive number{suffix}"
    if low is not None:
        return f"a number {'>' if low_open else '>='} {low:g}{suffix}"
    if high is not None:
        return f"a number <= {high:g}{suffix}"
    return f"a finite number{suffix}"


@overload
def number(
    default: float | _Required = REQUIRED,
    *,
    low: float | None = 0.0,
    high: float | None = None,
    low_open: bool = True,
    unit: str = "",
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[float]: ...


@overload
def number(
    default: None,
    *,
    low: float | None = 0.0,
    high: float | None = None,
    low_open: bool = True,
    unit: str = "",
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[float | None]: ...


def number(
    default: float | _Required | None = REQUIRED,
    *,
    low: float | None = 0.0,
    high: float | None = None,
    low_open: bool = True,
    unit: str = "",
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[Any]:
    """A finite number (an int or float, never a bool), read as a float.

    By default it must be positive (``low=0`` excluded); pass ``low=None`` for any finite
    number, ``low_open=False`` to allow ``low`` itself.

    Args:
        default: When absent (:data:`REQUIRED`: it must be there; None: it stays None).
        low: The smallest value, or None.
        high: The largest value (included), or None.
        low_open: Whether ``low`` itself is refused.
        unit: Named after the range in messages (``Hz``).
        describe: What the value must be, for messages, instead of the range's own text
            (``0 (not used) or positive``).
        hint: For a missing required key.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    what = describe or _range_text(low, high, low_open, unit, integral=False)

    def read(reader: ProfileReader, value: Any, path: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            reader.fail(path, f"must be {what}, got {value!r}")
        bad = not math.isfinite(value)
        bad = bad or (low is not None and (value <= low if low_open else value < low))
        bad = bad or (high is not None and value > high)
        if bad:
            reader.fail(path, f"must be {what}, got {value!r}")
        return float(value)

    return Field(read, default, hint, init)


@overload
def integer(
    default: int | _Required = REQUIRED,
    *,
    low: int | None = None,
    high: int | None = None,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[int]: ...


@overload
def integer(
    default: None,
    *,
    low: int | None = None,
    high: int | None = None,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[int | None]: ...


def integer(
    default: int | _Required | None = REQUIRED,
    *,
    low: int | None = None,
    high: int | None = None,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[Any]:
    """An integer (an int, never a bool or a float), within ``low..high`` (both included).

    Args:
        default: When absent (:data:`REQUIRED`: it must be there; None: it stays None).
        low: The smallest value, or None.
        high: The largest value, or None.
        describe: What the value must be, for messages, instead of the range's own text.
        hint: For a missing required key.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    what = describe or _range_text(low, high, False, "", integral=True)

    def read(reader: ProfileReader, value: Any, path: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            reader.fail(path, f"must be {what}, got {value!r}")
        if (low is not None and value < low) or (high is not None and value > high):
            reader.fail(path, f"must be {what}, got {value!r}")
        return value

    return Field(read, default, hint, init)


@overload
def text(
    default: str | _Required = REQUIRED,
    *,
    empty: bool = False,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[str]: ...


@overload
def text(
    default: None,
    *,
    empty: bool = False,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[str | None]: ...


def text(
    default: str | _Required | None = REQUIRED,
    *,
    empty: bool = False,
    describe: str = "",
    hint: str = "",
    init: bool = True,
) -> Field[Any]:
    """A string.

    Args:
        default: When absent (:data:`REQUIRED`: it must be there).
        empty: Whether ``""`` is accepted.
        describe: What it must be, for messages (default ``text`` or ``non-empty text``).
        hint: For a missing required key.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    what = describe or ("text" if empty else "non-empty text")

    def read(reader: ProfileReader, value: Any, path: str) -> str:
        if not isinstance(value, str) or (not empty and not value):
            reader.fail(path, f"must be {what}, got {value!r}")
        return value

    return Field(read, default, hint, init)


def name(default: str | _Required = REQUIRED, *, hint: str = "", init: bool = True) -> Field[str]:
    """A name (:data:`NAME_PATTERN`): a letter, then letters, digits, ``_ . -``; at most 63.

    Args:
        default: When absent (:data:`REQUIRED`: it must be there).
        hint: For a missing required key.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    return Field(lambda reader, value, path: reader.name(value, path), default, hint, init)


def flag(default: bool | _Required = REQUIRED, *, init: bool = True) -> Field[bool]:
    """``true`` or ``false`` (a YAML boolean; ``yes`` in quotes or 1 is refused).

    Args:
        default: When absent.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """

    def read(reader: ProfileReader, value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            reader.fail(path, f"must be true or false, got {value!r}")
        return value

    return Field(read, default, "", init)


def choice(
    options: Iterable[str], default: str | _Required = REQUIRED, *, init: bool = True
) -> Field[str]:
    """One of a fixed set of strings.

    Args:
        options: The accepted values, in the order messages list them.
        default: When absent.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    known = tuple(options)

    def read(reader: ProfileReader, value: Any, path: str) -> str:
        if value not in known:
            reader.fail(path, f"must be one of {', '.join(known)}, got {value!r}")
        return str(value)

    return Field(read, default, "", init)


def custom(
    read: Reader[T], default: T | _Required = REQUIRED, *, hint: str = "", init: bool = True
) -> Field[T]:
    """A value that a function of the driver reads (a link, a list of motors, a mapping).

    Args:
        read: ``(reader, value, key path) -> value``; raises with :meth:`ProfileReader.fail`.
        default: When absent (not passed through ``read``).
        hint: For a missing required key.
        init: Whether it is a constructor argument.

    Returns:
        The field.
    """
    return Field(read, default, hint, init)


class ProfileReader:
    """Checks a part of a profile document; every error names the file and the key path.

    Args:
        where: The key path of the part read (``devices.base``; empty for the document).
        file: The file the document came from, if any.
    """

    def __init__(self, where: str = "", *, file: str | None = None) -> None:
        self.where = where
        self.file = file or None

    @classmethod
    def at(cls, where: str) -> Self:
        """A reader for the ``where`` a driver's ``from_profile`` is given.

        Args:
            where: ``<file>: <key path>`` (``robot.yaml: devices.base``) or a key path alone.

        Returns:
            The reader (its errors read ``<file>: <key path>.<key>: ...``, as ``where`` did).
        """
        file, sep, path = where.rpartition(": ")
        return cls(path, file=file) if sep else cls(where)

    # ---- errors ----------------------------------------------------------------------------

    def path(self, key: str) -> str:
        """The full key path of ``key`` below this reader's part.

        Args:
            key: A key path relative to the part (``nodes[1].node_id``; empty: the part).

        Returns:
            The full path.
        """
        if not key:
            return self.where
        if not self.where:
            return key
        return f"{self.where}{'' if key.startswith('[') else '.'}{key}"

    def error(self, key: str, message: str) -> ProfileError:
        """The error for a problem at ``key`` (raise it).

        Args:
            key: The key path below this reader's part.
            message: What is wrong.

        Returns:
            The error.
        """
        return ProfileError(message, file=self.file, path=self.path(key))

    def fail(self, key: str, message: str) -> NoReturn:
        """Raise the error for a problem at ``key``.

        Args:
            key: The key path below this reader's part.
            message: What is wrong.

        Raises:
            ProfileError: Always.
        """
        raise self.error(key, message)

    # ---- shapes ----------------------------------------------------------------------------

    def mapping(self, value: object, key: str = "") -> Mapping[str, Any]:
        """``value`` as a mapping with text keys.

        Args:
            value: The value.
            key: Its key path.

        Returns:
            The mapping.

        Raises:
            ProfileError: Not a mapping with text keys.
        """
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            where = self.path(key) or "(top)"
            raise ProfileError(
                f"must be a mapping with text keys, got {_short(value)}", file=self.file, path=where
            )
        return value

    def known(self, value: Mapping[str, Any], keys: Iterable[str], key: str = "") -> None:
        """Refuse the first key of ``value`` (in sorted order) that is not in ``keys``.

        Args:
            value: The mapping.
            keys: The keys allowed.
            key: The mapping's key path.

        Raises:
            ProfileError: An unknown key (named, with the known ones).
        """
        allowed = set(keys)
        unknown = sorted(set(value) - allowed)
        if unknown:
            where = f"{key}.{unknown[0]}" if key else unknown[0]
            self.fail(where, f"unknown key (known: {', '.join(sorted(allowed))})")

    def items(self, value: object, key: str) -> Sequence[Mapping[str, Any]]:
        """A non-empty list of mappings (``nodes``, ``servos``).

        Args:
            value: The value.
            key: Its key path.

        Returns:
            The mappings.

        Raises:
            ProfileError: Not a non-empty list, or an item is not a mapping (named by index).
        """
        if not isinstance(value, list | tuple) or not value:
            self.fail(key, f"must be a non-empty list, got {value!r}")
        return [self.mapping(item, f"{key}[{i}]") for i, item in enumerate(value)]

    def name(self, value: object, key: str) -> str:
        """A name (:data:`NAME_PATTERN`).

        Args:
            value: The value.
            key: Its key path.

        Returns:
            The name.

        Raises:
            ProfileError: Not a name.
        """
        if not isinstance(value, str) or not NAME_PATTERN.match(value):
            self.fail(
                key,
                f"must be a name (a letter, then letters, digits, _ . -; at most 63): {value!r}",
            )
        return value

    # ---- fields ----------------------------------------------------------------------------

    def field(self, cfg: Mapping[str, Any], key: str, spec: Field[T], at: str = "") -> T:
        """Read one declared field of ``cfg``.

        Args:
            cfg: The mapping holding it.
            key: Its key.
            spec: How to read it.
            at: The mapping's key path ("" for this reader's part).

        Returns:
            The checked value, or the default when it is absent (or null).

        Raises:
            ProfileError: Required and missing, or a bad value.
        """
        full = f"{at}.{key}" if at else key
        value = cfg.get(key)
        if value is None:
            if isinstance(spec.default, _Required):
                self.fail(full, f"missing: {spec.hint}" if spec.hint else "missing")
            return spec.default
        return spec.read(self, value, full)

    def fields(
        self, cfg: Mapping[str, Any], spec: Mapping[str, Field[Any]], at: str = ""
    ) -> dict[str, Any]:
        """Read a mapping whose keys are all declared: unknown keys refused, each field read.

        Args:
            cfg: The mapping.
            spec: Its fields by key.
            at: Its key path ("" for this reader's part).

        Returns:
            Every declared key with its checked value or default (absent optional keys whose
            default is None are there as None).

        Raises:
            ProfileError: The first problem, naming its key path.
        """
        self.known(cfg, spec, at)
        return {key: self.field(cfg, key, field, at) for key, field in spec.items()}

    def entry(
        self, config: object, spec: Mapping[str, Field[Any]], kind: str = ""
    ) -> dict[str, Any]:
        """Read a device entry: a mapping, only declared keys, its own ``driver``, each field.

        Args:
            config: The entry.
            spec: Its fields by key (``driver`` is always allowed).
            kind: The driver's name: ``driver``, when still in the entry (an entry from
                :meth:`~temoto.drivers.base.Driver.detect` has it), must name it.

        Returns:
            The values as :meth:`fields` returns them (without ``driver``).

        Raises:
            ProfileError: The first problem, naming its key path.
        """
        cfg = self.mapping(config)
        self.known(cfg, {*spec, "driver"})
        if kind and cfg.get("driver", kind) != kind:
            self.fail("driver", f"must be {kind!r} for this driver, got {cfg['driver']!r}")
        return {key: self.field(cfg, key, field) for key, field in spec.items()}


def _short(value: object) -> str:
    """``value``'s repr, cut to 60 characters (a whole document can land in a message)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
