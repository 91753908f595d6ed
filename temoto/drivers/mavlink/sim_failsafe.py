"""The simulated ArduCopter's failsafes: ground station lost, battery low or critical.

:class:`Failsafes` runs ArduCopter's GCS failsafe (``FS_GCS_ENABLE``, ``FS_GCS_TIMEOUT``,
``FS_OPTIONS``, the heartbeats of ``SYSID_MYGCS``) and ArduPilot's battery failsafe
(``BATT_LOW_*`` and ``BATT_CRT_*`` by voltage for ``BATT_LOW_TIMER`` s or by remaining
capacity, latched, with the ``BATT_FS_*_ACT`` actions) once per model step. A layer of
:class:`~temoto.drivers.mavlink.sim.SimVehicle` (see :mod:`~temoto.drivers.mavlink.sim_state`).
"""

from __future__ import annotations

from typing import Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_flight import FlightModel
from temoto.drivers.mavlink.sim_state import VehicleState

__all__ = ["Failsafes"]

#: FS_GCS_ENABLE / BATT_FS_*_ACT → the mode taken in the air (ArduCopter's failsafe actions;
#: SmartRTL is not simulated, so its fallbacks are taken; DO_LAND_START neither: RTL).
_GCS_FAILSAFE_MODE: Final = {
    1: "RTL",
    2: "RTL",
    3: "RTL",
    4: "LAND",
    5: "LAND",
    6: "RTL",
    7: "BRAKE",
}

_BATT_FAILSAFE_MODE: Final = {1: "LAND", 2: "RTL", 3: "RTL", 4: "LAND", 6: "RTL", 7: "BRAKE"}


class Failsafes:
    """The GCS and battery failsafes (see the module docstring).

    Args:
        state: The vehicle's state.
        flight: Takes the failsafe's action (a mode change, a disarm).
    """

    def __init__(self, state: VehicleState, flight: FlightModel) -> None:
        self.state = state
        self.flight = flight
        self._gcs_seen: float | None = None  # clock time of the GCS's newest heartbeat
        self._low_volt_since: float | None = None
        self._crt_volt_since: float | None = None

    def gcs_heartbeat(self, now: float) -> None:
        """A HEARTBEAT from the GCS (``SYSID_MYGCS``) arrived at clock time ``now``.

        Args:
            now: The clock time.
        """
        self._gcs_seen = now

    @property
    def gcs_failsafe(self) -> bool:
        """Whether the GCS failsafe is active (no GCS heartbeat for ``FS_GCS_TIMEOUT``)."""
        with self.state.lock:
            return self.state.gcs_failsafe

    @property
    def battery_failsafe(self) -> int:
        """The battery failsafe level: 0 none, 1 low, 2 critical (they latch)."""
        with self.state.lock:
            return self.state.batt_failsafe

    def check(self, now: float) -> None:
        """ArduCopter's GCS failsafe check, once per model step."""
        self._check_battery(now)
        if self.state.params["FS_GCS_ENABLE"] == 0 or self._gcs_seen is None:
            return
        late = now - self._gcs_seen > self.state.params["FS_GCS_TIMEOUT"]
        if late and not self.state.gcs_failsafe:
            self.state.gcs_failsafe = True
            self._gcs_failsafe_on()
        elif not late and self.state.gcs_failsafe:
            self.state.gcs_failsafe = False
            self.state.texts.append((p.MAV_SEVERITY_WARNING, "GCS Failsafe Cleared"))

    def _gcs_failsafe_on(self) -> None:
        warn = p.MAV_SEVERITY_WARNING
        if not self.state.armed:
            self.state.texts.append((warn, "GCS Failsafe"))
            return
        if not self.state.airborne:
            self.flight.disarm(force=True)
            self.state.texts.append((warn, "GCS Failsafe - Disarming"))
            return
        enable = int(self.state.params["FS_GCS_ENABLE"])
        continue_auto = enable == 2 or round(self.state.value("FS_OPTIONS")) & 2  # FS_OPTIONS bit 1
        if self.state.mode == "AUTO" and continue_auto:
            self.state.texts.append((warn, "GCS Failsafe - Continuing Auto Mode"))
            return
        self.state.texts.append((warn, "GCS Failsafe"))
        if enable in (3, 4):
            fallback = "RTL" if enable == 3 else "Land"
            self.state.texts.append((warn, f"SmartRTL Unavailable, Using {fallback} Mode"))
        self.flight.set_mode(_GCS_FAILSAFE_MODE.get(enable, "RTL"))

    def _volts_below(self, threshold: float, since: float | None, now: float) -> float | None:
        """When the voltage went below ``threshold`` (None: it is not below it)."""
        if threshold <= 0 or self.state.failsafe_voltage() >= threshold:
            return None
        return now if since is None else since

    def _check_battery(self, now: float) -> None:
        """ArduPilot's battery failsafe (AP_BattMonitor): low and critical, latched."""
        if self.state.value("BATT_MONITOR") == 0:
            return
        timer = self.state.value("BATT_LOW_TIMER")
        self._low_volt_since = self._volts_below(
            self.state.value("BATT_LOW_VOLT"), self._low_volt_since, now
        )
        self._crt_volt_since = self._volts_below(
            self.state.value("BATT_CRT_VOLT"), self._crt_volt_since, now
        )
        remaining = self.state.value("BATT_CAPACITY") - self.state.consumed_mah()
        crt_mah, low_mah = self.state.value("BATT_CRT_MAH"), self.state.value("BATT_LOW_MAH")
        critical = (self._crt_volt_since is not None and now - self._crt_volt_since >= timer) or (
            crt_mah > 0 and remaining < crt_mah
        )
        low = (self._low_volt_since is not None and now - self._low_volt_since >= timer) or (
            low_mah > 0 and remaining < low_mah
        )
        level = 2 if critical else 1 if low else 0
        if level <= self.state.batt_failsafe:
            return
        self.state.batt_failsafe = level
        word = "critical" if level == 2 else "low"
        self.state.texts.append(
            (
                p.MAV_SEVERITY_WARNING,
                f"Battery 1 is {word} {self.state.voltage():.2f}V"
                f" used {self.state.consumed_mah():.0f} mAh",
            )
        )
        action = int(self.state.value("BATT_FS_CRT_ACT" if level == 2 else "BATT_FS_LOW_ACT"))
        if action == 0 or not self.state.armed:
            return
        if not self.state.airborne or action == 5:  # landed: disarm; 5: terminate (motors off)
            self.flight.disarm(force=True)
            return
        mode = _BATT_FAILSAFE_MODE.get(action, "RTL")
        if self.state.mode != "LAND":  # never from landing back to something else
            self.flight.set_mode(mode)
