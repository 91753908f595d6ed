"""The MAVLink parameter protocol of :class:`~temoto.drivers.mavlink.driver.MavlinkDriver`.

One parameter at a time: ``PARAM_REQUEST_READ`` → ``PARAM_VALUE`` (read) and ``PARAM_SET`` →
``PARAM_VALUE`` (write, confirmed by the value the vehicle sends back, as a float32 carries
it), each retried ``command_retries`` times; a ``PARAM_ERROR`` of newer ArduPilot firmware ends
the exchange at once. ``configure`` uses it to set the GCS failsafe (``gcs_failsafe``) and to
check that the failsafe watches this ground station.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Final

from temoto.drivers.mavlink import missions
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink._session import Session
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
)

__all__ = ["ParameterClient"]

logger = logging.getLogger(__name__)

#: The parameter naming the GCS system id whose heartbeats the failsafe watches (the older
#: name, and the one newer ArduPilot firmware uses).
_GCS_SYSID_PARAMS: Final = ("SYSID_MYGCS", "MAV_GCS_SYSID")


class ParameterClient(Session):
    """Reading and writing the vehicle's parameters (a layer of the MAVLink driver).

    Not used alone: :class:`~temoto.drivers.mavlink.driver.MavlinkDriver` is built on it.
    """

    # ---- parameters (only what configure needs; the full protocol is not here) ---------------
    # ---- parameters (public) ------------------------------------------------------------------
    def _configure_failsafe(self) -> None:
        """Set the GCS failsafe parameters and check that the failsafe watches this driver.

        Raises:
            DriverInitError: The vehicle kept another value, or watches another GCS system id.
            DriverTimeoutError: No PARAM_VALUE came back.
        """
        if not self.failsafe_params:
            return
        for name, value in self.failsafe_params.items():
            self._set_param(name, value)
        watched: float | None = None
        for name in _GCS_SYSID_PARAMS:
            got = self._read_param(name, retries=0)
            if got is not None:
                watched = got[0]
                break
        own = self._gcs_ids[0]
        if watched is None:
            logger.warning(
                "driver %s: the vehicle did not say which GCS system id its failsafe watches"
                " (%s); it must be %d, this driver's gcs_system_id",
                self.name,
                " or ".join(_GCS_SYSID_PARAMS),
                own,
            )
        elif round(watched) != own:
            raise DriverInitError(
                f"{self.name}: the vehicle's GCS failsafe watches system {round(watched)}"
                f" ({'/'.join(_GCS_SYSID_PARAMS)}), not this driver's gcs_system_id {own}:"
                " it would not notice this driver stopping; set one to the other"
            )

    def _read_param(self, name: str, *, retries: int | None = None) -> tuple[float, int] | None:
        """Ask for one parameter (PARAM_REQUEST_READ): its value and type, or None."""
        tries = 1 + (self.command_retries if retries is None else retries)
        return self._param_exchange("PARAM_REQUEST_READ", name, tries, param_index=-1)

    def _set_param(self, name: str, value: float) -> None:
        """Set one parameter (PARAM_SET) and check the PARAM_VALUE echo.

        Raises:
            DriverInitError: The vehicle has no such parameter or kept another value.
            DriverTimeoutError: No PARAM_VALUE.
        """
        current = self._read_param(name)
        if current is None:
            raise DriverTimeoutError(
                f"{self.name}: no PARAM_VALUE for {name} (does this firmware have it?)"
            )
        if _same(current[0], value):
            logger.info("driver %s: %s is %g already", self.name, name, value)
            return
        tries = 1 + self.command_retries
        got = self._param_exchange(
            "PARAM_SET", name, tries, param_value=value, param_type=current[1]
        )
        if got is None:
            raise DriverTimeoutError(
                f"{self.name}: no PARAM_VALUE after setting {name} in {tries} tries"
                f" of {self.command_timeout:g} s"
            )
        if not _same(got[0], value):
            raise DriverInitError(
                f"{self.name}: the vehicle kept {name} = {got[0]:g} (asked for {value:g})"
            )
        logger.info("driver %s: %s %g -> %g", self.name, name, current[0], value)

    def _param_exchange(
        self, message: str, name: str, tries: int, **fields: Any
    ) -> tuple[float, int] | None:
        """Send ``message`` about parameter ``name`` until a PARAM_VALUE of it answers.

        Up to ``tries`` sends, each waiting ``command_timeout``; the answer's value and type,
        or None (also at once when a PARAM_ERROR about it came: :attr:`_param_errors`).
        """
        with self._cond:
            target = self._target or 1
            self._param_errors.pop(name, None)
        for _ in range(tries):
            with self._cond:
                start = self._param_count
            self._write(
                self._codec.encode(
                    message,
                    target_system=target,
                    target_component=self.component_id,
                    param_id=name.encode(),
                    **fields,
                )
            )
            got = self._await_param(name, start)
            if got is not None:
                return got
            with self._cond:
                if name in self._param_errors:
                    break  # the vehicle answered: asking again changes nothing
        return None

    def _await_param(self, name: str, after: int) -> tuple[float, int] | None:
        def arrived() -> bool:
            return self._param_seen.get(name, 0) > after or name in self._param_errors

        if not self._await(arrived, self.command_timeout):
            return None
        with self._cond:
            if self._param_seen.get(name, 0) > after:
                return self._params[name]
        return None

    def _param_failure(self, name: str, what: str) -> DriverError:
        """The error of a parameter exchange that got no PARAM_VALUE (after its retries)."""
        with self._cond:
            error = self._param_errors.get(name)
        if error is not None:
            return DriverOperationError(
                f"{self.name}: {what} {name}: the vehicle answered PARAM_ERROR"
                f" {p.enum_name('MAV_PARAM_ERROR', error)}"
            )
        tries = 1 + self.command_retries
        hint = " (does this firmware have it?)" if what == "reading" else ""
        return DriverTimeoutError(
            f"{self.name}: no PARAM_VALUE for {name} in {tries} tries of"
            f" {self.command_timeout:g} s ({what}){hint}"
        )

    def get_param(self, name: str) -> float | int:
        """Read one parameter of the vehicle (``PARAM_REQUEST_READ`` → ``PARAM_VALUE``).

        Sent up to ``1 + command_retries`` times, each waiting ``command_timeout``. The value
        is typed by the answer's ``MAV_PARAM_TYPE``: an ``int`` for the integer types (which
        ArduPilot sends as a float holding the integer, its "C cast" encoding), a ``float``
        for ``REAL32``.

        Args:
            name: The parameter's name (``WPNAV_SPEED``; at most 16 characters).

        Returns:
            The value.

        Raises:
            ValueError: Not a parameter name.
            StateError: The driver is not configured.
            DriverTimeoutError: No PARAM_VALUE of it (a name the firmware does not have goes
                unanswered too; the message says so).
        """
        self._check_param_name(name)
        self._require_link("get_param")
        with self._param_lock:
            got = self._read_param(name)
        if got is None:
            raise self._param_failure(name, "reading")
        return missions.typed_param_value(*got)

    def set_param(self, name: str, value: float) -> float | int:
        """Set one parameter of the vehicle (``PARAM_SET`` → the ``PARAM_VALUE`` echo).

        The parameter is read first for its type (unless this driver has seen it); an integer
        type takes only integers in its range, and no more than 2**24 in size (ArduPilot carries
        every value as a float32). ``PARAM_SET`` is sent up to ``1 + command_retries`` times,
        each waiting ``command_timeout`` for the echo; a value equal to the current one is
        not sent again.

        Args:
            name: The parameter's name (at most 16 characters).
            value: The new value.

        Returns:
            The value the vehicle reports it now holds.

        Raises:
            ValueError: Not a parameter name, or a value its type cannot hold.
            StateError: The driver is not configured.
            DriverTimeoutError: No PARAM_VALUE came back (for the read or the set).
            DriverOperationError: The vehicle kept another value.
        """
        self._check_param_name(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{name}: a parameter value must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"{name}: a parameter value must be finite, got {value!r}")
        self._require_link("set_param")
        tries = 1 + self.command_retries
        with self._param_lock:
            with self._cond:
                known = self._params.get(name)
            current = known if known is not None else self._read_param(name)
            if current is None:
                raise self._param_failure(name, "reading")
            param_type = current[1]
            missions.check_param_value(name, value, param_type)
            if known is not None or not _same(current[0], value):
                got = self._param_exchange(
                    "PARAM_SET", name, tries, param_value=float(value), param_type=param_type
                )
                if got is None:
                    raise self._param_failure(name, "setting")
                current = got
        if not _same(current[0], value):
            raise DriverOperationError(
                f"{self.name}: the vehicle kept {name} = {current[0]:g} (asked for {value:g})"
            )
        logger.info("driver %s: %s = %g", self.name, name, current[0])
        return missions.typed_param_value(*current)

    def _check_param_name(self, name: str) -> None:
        if not (
            isinstance(name, str) and 0 < len(name) <= p.PARAM_ID_LEN and name.isascii()
        ) or any(c.isspace() or c == "\x00" for c in name):
            raise ValueError(
                f"{self.name}: a parameter name is 1..{p.PARAM_ID_LEN} ASCII characters without"
                f" spaces, got {name!r}"
            )


def _same(a: float, b: float) -> bool:
    """Parameter values equal as a float32 carries them."""
    return abs(a - b) <= 1e-5 * max(1.0, abs(b))
