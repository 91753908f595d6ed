"""A device's recovery policy: what the Robot Manager does after a fault (``docs/safety.md``).

Every device entry of a hardware profile may have a ``recovery:`` key (every driver accepts
it, as it accepts ``safe_state``)::

    recovery: {tries: 5, backoff: 0.5, max_backoff: 5.0}   # the default
    recovery: off                                        # stay FAULT until reloaded

After a fault the manager makes the device safe, then tries up to ``tries`` times to bring it
back: each try calls the driver's ``recover()`` (clear the device's errors, reconnect) when it
is in ``FAULT`` and ``activate()`` when it is ``INACTIVE``. Try ``k`` starts
``min(backoff * 2**(k-1), max_backoff)`` seconds (of the robot's clock) after the fault or the
previous try, or at once when the driver reports that the device answers again. After the last
failed try the manager gives up: the device stays out of service and its consumers are told
``FATAL`` with ``gave up after N tries: <reason>``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from temoto.drivers.profile import Field, ProfileReader, custom, integer, number

__all__ = ["RECOVERY_FIELD", "RecoveryPolicy", "read_recovery"]


@dataclass(frozen=True, slots=True)
class RecoveryPolicy:
    """How a faulted device is brought back.

    Attributes:
        enabled: False for ``recovery: off`` (the device stays ``FAULT``).
        tries: Tries before giving up.
        backoff: Seconds before the first try; doubled before each next one.
        max_backoff: The longest wait between two tries, seconds.
    """

    enabled: bool = True
    tries: int = 5
    backoff: float = 0.5
    max_backoff: float = 5.0

    def delay(self, attempt: int) -> float:
        """Seconds to wait before try ``attempt`` (1 for the first).

        Args:
            attempt: The try's number, from 1.

        Returns:
            ``min(backoff * 2**(attempt-1), max_backoff)``.
        """
        return float(min(self.backoff * 2.0 ** max(attempt - 1, 0), self.max_backoff))

    def describe(self) -> str:
        """The policy for people (``"5 tries, backoff 0.5 s doubling up to 5 s"``, ``"off"``).

        Returns:
            The text.
        """
        if not self.enabled:
            return "off"
        up_to = f"up to {self.max_backoff:g} s"
        return f"{self.tries} tries, backoff {self.backoff:g} s doubling {up_to}"


_OFF: Final = RecoveryPolicy(enabled=False)
_DEFAULT: Final = RecoveryPolicy()

_KEYS: Final[dict[str, Field[Any]]] = {
    "tries": integer(_DEFAULT.tries, low=1, high=100),
    "backoff": number(_DEFAULT.backoff, high=60.0, unit="s"),
    "max_backoff": number(_DEFAULT.max_backoff, high=600.0, unit="s"),
}


def read_recovery(reader: ProfileReader, value: Any, path: str) -> RecoveryPolicy:
    """Read a ``recovery:`` value: ``off``/``false``, ``on``/``true`` or a mapping of the keys.

    Args:
        reader: The entry's reader (errors name the file and key path).
        value: The value as written (YAML reads a bare ``off`` as ``false``).
        path: Its key path.

    Returns:
        The policy.

    Raises:
        ProfileError: Neither of those forms, an unknown key, a value out of range, or
            ``max_backoff`` below ``backoff``.
    """
    if value is False or value == "off":
        return _OFF
    if value is True or value == "on":
        return RecoveryPolicy()
    if not isinstance(value, Mapping):
        reader.fail(
            path,
            f"must be off, on or a mapping of tries, backoff, max_backoff; got {value!r}",
        )
    values = reader.fields(reader.mapping(value, path), _KEYS, path)
    policy = RecoveryPolicy(True, values["tries"], values["backoff"], values["max_backoff"])
    if policy.max_backoff < policy.backoff:
        reader.fail(
            f"{path}.max_backoff",
            f"must be >= backoff ({policy.backoff:g} s), got {policy.max_backoff:g} s",
        )
    return policy


#: The ``recovery`` key every driver's profile entry accepts (not a constructor argument).
RECOVERY_FIELD: Final[Field[RecoveryPolicy]] = custom(read_recovery, RecoveryPolicy(), init=False)
