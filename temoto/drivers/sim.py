"""What every device simulator shares: start/close and fault injection on command.

A simulator sits at the *device* end of the link and speaks the device's side of the wire
protocol (docs/development.md §6); the production driver talks to it exactly as to hardware.
Faults are injected by name and cleared again, so failure handling is tested deterministically:

==================  ==========================================================================
``silence``         the device stops answering and sending (a dead device, a cut cable)
``corrupt``         replies go out with a wrong checksum (CRC, MAVLink X.25) or a mangled frame
``hardware_error``  the device reports a hardware error: ``kind`` = ``overheat``, ``overload``
                    or ``voltage``
``no_heartbeat``    periodic heartbeats stop; replies to requests still come
``link_loss``       the link itself goes away (frames in neither direction) until cleared
==================  ==========================================================================

A simulator may support a subset (:attr:`Simulator.FAULTS`); injecting another one is a
``ValueError``.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Mapping
from types import TracebackType
from typing import Any, ClassVar, Final, Self

from temoto.drivers.realism import Realism

__all__ = ["FAULT_NAMES", "HARDWARE_ERRORS", "Simulator"]

#: Every fault name a simulator may support.
FAULT_NAMES: Final = frozenset(
    {"silence", "corrupt", "hardware_error", "no_heartbeat", "link_loss"}
)
#: The ``kind`` values of ``hardware_error``.
HARDWARE_ERRORS: Final = frozenset({"overheat", "overload", "voltage"})


class Simulator(ABC):
    """Base of the device simulators: lifecycle and the fault switchboard."""

    #: The faults this simulator can inject.
    FAULTS: ClassVar[frozenset[str]] = frozenset()

    def __init__(self) -> None:
        self._fault_lock = threading.Lock()
        self._faults: dict[str, dict[str, Any]] = {}
        #: The simulator's imperfections (:mod:`temoto.drivers.realism`): ``off`` unless the
        #: simulator takes a level; ``realism.describe()`` names the level and the seed to print.
        self.realism = Realism("off")

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @abstractmethod
    def start(self) -> None:
        """Open the device end of the link and start answering."""

    @abstractmethod
    def close(self) -> None:
        """Stop answering, close the link end and join the simulator's threads (idempotent)."""

    def inject(self, fault: str, **params: Any) -> None:
        """Switch a fault on (until :meth:`clear`).

        Args:
            fault: One of :attr:`FAULTS`.
            **params: Its parameters (``kind=`` for ``hardware_error``; a simulator may take
                ``device=`` to fault one device of several).

        Raises:
            ValueError: An unsupported fault or a bad parameter.
        """
        if fault not in self.FAULTS:
            known = ", ".join(sorted(self.FAULTS)) or "none"
            raise ValueError(f"{type(self).__name__} cannot inject {fault!r} (it can: {known})")
        if fault == "hardware_error" and params.get("kind", "overheat") not in HARDWARE_ERRORS:
            raise ValueError(
                f"hardware_error kind must be one of {', '.join(sorted(HARDWARE_ERRORS))}"
            )
        with self._fault_lock:
            self._faults[fault] = dict(params)
        self.on_fault_changed(fault, True)

    def clear(self, fault: str | None = None) -> None:
        """Switch one fault (or every fault) off.

        Args:
            fault: The fault, or None for all.
        """
        with self._fault_lock:
            names = list(self._faults) if fault is None else [fault]
            for name in names:
                self._faults.pop(name, None)
        for name in names:
            self.on_fault_changed(name, False)

    def fault(self, name: str) -> Mapping[str, Any] | None:
        """The parameters of an active fault, or None if it is off.

        Args:
            name: The fault.

        Returns:
            Its parameters, or None.
        """
        with self._fault_lock:
            params = self._faults.get(name)
            return None if params is None else dict(params)

    def on_fault_changed(self, fault: str, active: bool) -> None:  # noqa: B027  # optional
        """Called after a fault was switched on or off (e.g. to raise an error bit at once)."""
