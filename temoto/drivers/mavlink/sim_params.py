"""The simulated ArduCopter's parameters: the table, the stored types and the ``.param`` file.

:data:`PARAMETERS` is a realistic subset of ArduCopter 4.5's parameters (name → ArduCopter's
default, ``MAV_PARAM_TYPE``), the ones a ground station usually looks at and the ones that
drive :class:`~temoto.drivers.mavlink.sim.SimVehicle`'s model (navigation speeds, RTL and LAND,
the GCS and battery failsafes, arming checks). Integer parameters hold what ArduPilot's
``AP_Int8``/``AP_Int16``/``AP_Int32`` would (``AP_Param::set_float``: 0.01 added away from
zero, clamped to the type's range, truncated); ``REAL32`` ones hold a single-precision float,
as PARAM_VALUE carries it.

:func:`load_param_file` and :func:`save_param_file` read and write the format that MAVProxy
(``param save``), Mission Planner and ArduPilot's SITL defaults files use: one ``NAME VALUE``
or ``NAME,VALUE`` per line, ``#`` comments. Pure functions and constants; no threads.
"""

from __future__ import annotations

import contextlib
import math
import os
import struct
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Final

from temoto.drivers.mavlink import protocol as p

__all__ = [
    "PARAMETERS",
    "READ_ONLY",
    "load_param_file",
    "save_param_file",
    "stored_value",
]

_I8, _I16, _I32, _F = (
    p.MAV_PARAM_TYPE_INT8,
    p.MAV_PARAM_TYPE_INT16,
    p.MAV_PARAM_TYPE_INT32,
    p.MAV_PARAM_TYPE_REAL32,
)

#: The simulated parameters: name → (ArduCopter's default, MAV_PARAM_TYPE). Units as in
#: ArduPilot (cm, cm/s, ms, mAh, V); the ones the model uses are listed in the SimVehicle docs.
PARAMETERS: Final[Mapping[str, tuple[float, int]]] = {
    # arming
    "ARMING_CHECK": (1.0, _I32),
    "ARMING_ACCTHRESH": (0.75, _F),
    "DISARM_DELAY": (10.0, _I8),
    "AUTO_OPTIONS": (0.0, _I32),
    # battery monitor and its failsafe
    "BATT_MONITOR": (4.0, _I8),
    "BATT_CAPACITY": (3300.0, _I32),
    "BATT_ARM_VOLT": (0.0, _F),
    "BATT_ARM_MAH": (0.0, _I32),
    "BATT_LOW_VOLT": (10.5, _F),
    "BATT_CRT_VOLT": (0.0, _F),
    "BATT_LOW_MAH": (0.0, _F),
    "BATT_CRT_MAH": (0.0, _F),
    "BATT_LOW_TIMER": (10.0, _I8),
    "BATT_FS_LOW_ACT": (0.0, _I8),
    "BATT_FS_CRT_ACT": (0.0, _I8),
    "BATT_FS_VOLTSRC": (0.0, _I8),
    # failsafes
    "FS_GCS_ENABLE": (0.0, _I8),
    "FS_GCS_TIMEOUT": (5.0, _F),
    "FS_THR_ENABLE": (1.0, _I8),
    "FS_THR_VALUE": (975.0, _I16),
    "FS_EKF_ACTION": (1.0, _I8),
    "FS_EKF_THRESH": (0.8, _F),
    "FS_CRASH_CHECK": (1.0, _I8),
    "FS_OPTIONS": (0.0, _I32),
    # identity
    "SYSID_THISMAV": (1.0, _I16),
    "SYSID_MYGCS": (255.0, _I16),
    "SYSID_ENFORCE": (0.0, _I8),
    "FRAME_CLASS": (1.0, _I8),
    "FRAME_TYPE": (1.0, _I8),
    # waypoint navigation
    "WPNAV_SPEED": (1000.0, _F),
    "WPNAV_SPEED_UP": (250.0, _F),
    "WPNAV_SPEED_DN": (150.0, _F),
    "WPNAV_RADIUS": (200.0, _F),
    "WPNAV_ACCEL": (250.0, _F),
    "WPNAV_ACCEL_Z": (100.0, _F),
    "WP_YAW_BEHAVIOR": (2.0, _I8),
    "LOIT_SPEED": (1250.0, _F),
    "ANGLE_MAX": (3000.0, _I16),
    # the simulated world (ArduPilot SITL's SIM_* names): wind speed m/s, direction it comes from
    "SIM_WIND_SPD": (0.0, _F),
    "SIM_WIND_DIR": (180.0, _F),
    "PILOT_SPEED_UP": (250.0, _I16),
    "PILOT_TKOFF_ALT": (0.0, _F),
    # return to launch and landing
    "RTL_ALT": (1500.0, _I32),
    "RTL_ALT_FINAL": (0.0, _I16),
    "RTL_CLIMB_MIN": (0.0, _I16),
    "RTL_SPEED": (0.0, _I16),
    "RTL_LOIT_TIME": (5000.0, _I32),
    "RTL_CONE_SLOPE": (3.0, _F),
    "LAND_SPEED": (50.0, _I16),
    "LAND_SPEED_HIGH": (0.0, _I16),
    "LAND_ALT_LOW": (1000.0, _I16),
    # missions and fence
    "MIS_TOTAL": (0.0, _I16),
    "MIS_RESTART": (0.0, _I8),
    "MIS_OPTIONS": (0.0, _I16),
    "FENCE_ENABLE": (0.0, _I8),
    "FENCE_TYPE": (7.0, _I8),
    "FENCE_ACTION": (1.0, _I8),
    "FENCE_ALT_MAX": (100.0, _F),
    "FENCE_RADIUS": (300.0, _F),
    # flight modes on the RC switch
    "FLTMODE1": (0.0, _I8),
    "FLTMODE2": (0.0, _I8),
    "FLTMODE3": (0.0, _I8),
    "FLTMODE4": (0.0, _I8),
    "FLTMODE5": (0.0, _I8),
    "FLTMODE6": (0.0, _I8),
    "FLTMODE_CH": (5.0, _I8),
    # estimation, sensors, motors, links
    "AHRS_EKF_TYPE": (3.0, _I8),
    "EK3_ENABLE": (1.0, _I8),
    "GPS_TYPE": (1.0, _I8),
    "COMPASS_USE": (1.0, _I8),
    "MOT_SPIN_ARM": (0.1, _F),
    "MOT_SPIN_MIN": (0.15, _F),
    "MOT_THST_HOVER": (0.35, _F),
    "SCHED_LOOP_RATE": (400.0, _I16),
    "SERIAL0_BAUD": (115.0, _I32),
    "SERIAL0_PROTOCOL": (2.0, _I8),
    "LOG_BACKEND_TYPE": (1.0, _I8),
}

#: Parameters a PARAM_SET cannot change (ArduPilot answers "Param write denied" and the
#: stored value): the mission's item count is the mission's, not the user's.
READ_ONLY: Final = frozenset({"MIS_TOTAL"})

_INT_RANGE: Final = {
    _I8: (-128, 127),
    _I16: (-32768, 32767),
    _I32: (-(2**31), 2**31 - 1),
}


def stored_value(param_type: int, value: float) -> float:
    """``value`` as a parameter of ``param_type`` holds it.

    Integers as ArduPilot's ``AP_Param::set_float`` stores them: the single-precision value
    plus 0.01 (minus 0.01 if negative), clamped to the type's range, truncated toward zero
    (2500.7 → 2500, 2.995 → 3, -3.7 → -3). ``REAL32`` becomes the nearest single-precision
    float (what a PARAM_VALUE carries back).

    Args:
        param_type: A ``MAV_PARAM_TYPE``.
        value: A finite number.

    Returns:
        The stored value.
    """
    single = _f32(value)
    limits = _INT_RANGE.get(param_type)
    if limits is None:
        return single
    nudged = _f32(single + _f32(-0.01 if single < 0 else 0.01))  # float arithmetic, as on board
    return float(math.trunc(min(max(nudged, limits[0]), limits[1])))


def _f32(value: float) -> float:
    """``value`` rounded to single precision (what a C ``float`` holds)."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def load_param_file(path: str | os.PathLike[str]) -> dict[str, float]:
    """Read a ``.param``/``.parm`` file (MAVProxy, Mission Planner, ArduPilot SITL defaults).

    One parameter per line, ``NAME VALUE`` (spaces or tabs) or ``NAME,VALUE``; blank lines
    and ``#`` comments (whole lines or after the value) are skipped. A name seen twice keeps
    its last value, as ArduPilot's defaults files do.

    Args:
        path: The file.

    Returns:
        Name → value, in file order.

    Raises:
        ValueError: A line that is not ``NAME VALUE`` with a finite number, naming the file and
            the line number.
        OSError: The file cannot be read.
    """
    out: dict[str, float] = {}
    text = Path(path).read_text(encoding="utf-8")
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 2:
            raise ValueError(f"{os.fspath(path)}:{number}: expected 'NAME VALUE', got {raw!r}")
        name, text_value = parts
        if len(name) > 16 or not all(c.isalnum() or c == "_" for c in name):
            raise ValueError(f"{os.fspath(path)}:{number}: bad parameter name {name!r}")
        try:
            value = float(text_value)
        except ValueError:
            raise ValueError(
                f"{os.fspath(path)}:{number}: {name}: value {text_value!r} is not a number"
            ) from None
        if not math.isfinite(value):
            raise ValueError(f"{os.fspath(path)}:{number}: {name}: value must be finite")
        out[name.upper()] = value
    return out


def save_param_file(
    path: str | os.PathLike[str], params: Mapping[str, float], types: Mapping[str, int]
) -> None:
    """Write parameters as ``NAME VALUE`` lines, atomically (a temporary file, then a rename).

    A reader never sees a half-written file, and a crash mid-write leaves the old one.

    Args:
        path: The file.
        params: Name → value; written sorted by name.
        types: Name → ``MAV_PARAM_TYPE`` (integers are written without a fraction); names
            missing here are written as floats.

    Raises:
        OSError: The directory cannot be written.
    """
    target = Path(path)
    lines = ["# ArduCopter parameters of a temoto simulated vehicle (NAME VALUE)"]
    for name in sorted(params):
        value = params[name]
        if types.get(name, _F) in _INT_RANGE:
            lines.append(f"{name} {round(value)}")
        else:
            lines.append(f"{name} {value!r}")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent or ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
