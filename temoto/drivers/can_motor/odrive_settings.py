"""The profile entry of an ODrive bus (``driver: odrive_can``): its nodes and simulated rates.

:func:`read_nodes` reads the entry's ``nodes`` (each checked by the one profile reader,
:mod:`temoto.drivers.profile`); :func:`sim_rates` reads its ``sim`` mapping, the simulated
ODrives' cyclic message rates, against the periods the driver supervises. The other keys are
declared on :class:`~temoto.drivers.can_motor.odrive.ODriveDriver` (``docs/driver-can.md``).
"""

from __future__ import annotations

import math
from typing import Final

from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor._common import read_limits, read_members
from temoto.drivers.can_motor.odrive_axes import ODriveNode
from temoto.drivers.profile import ProfileReader, number
from temoto.drivers.realism import SIM_KEYS

__all__ = ["SIM_MECHANICS", "read_nodes", "sim_mechanics", "sim_rates"]

_NODE_KEYS: Final = frozenset(
    {
        "node_id",
        "joint",
        "gear_ratio",
        "position_min",
        "position_max",
        "velocity_limit",
        "torque_limit",
    }
)
_SIM_MS: Final = number(0.0, low=0, low_open=False, describe="0 (off) or a number of ms")

#: The simulated axes' mechanics and controller settings a ``sim`` mapping may set (every axis
#: of the entry alike), by key: what it sets on
#: :class:`~temoto.drivers.can_motor.sim_model.AxisModel`, with its unit.
SIM_MECHANICS: Final = {
    "load_inertia": "kg·m² at the motor",
    "damping": "N·m per turn/s",
    "current_limit": "A",
    "vel_limit": "turn/s",
    "torque_constant": "N·m per A",
    "vel_gain": "N·m per turn/s",
    "vel_integrator_gain": "N·m per turn/s per s",
}
_POSITIVE: Final = number(0.0, low=0, low_open=False, describe="a number >= 0")

#: The cyclic messages the driver supervises, and the key that states each one's period.
_SUPERVISED: Final = {
    "heartbeat_msg_rate_ms": "heartbeat_period",
    "encoder_msg_rate_ms": "encoder_period",
}


def sim_rates(
    p: ProfileReader, raw: object, heartbeat_period: float, encoder_period: float
) -> dict[str, float]:
    """The simulated ODrives' cyclic message rates from an entry's ``sim`` mapping.

    ``sim`` maps the ODrive's ``axis.config.can`` rate settings
    (:data:`~temoto.drivers.can_motor.sim.CYCLIC_RATES`: ``torques_msg_rate_ms``,
    ``iq_msg_rate_ms``, ...) to milliseconds, 0 for off. The heartbeats and the encoder
    estimates are supervised by the driver, which expects them every ``heartbeat_period`` and
    ``encoder_period``: those two rates follow the driver's keys, and a ``sim`` value for them
    that differs (0 above all: the driver would find the axes dead or their estimates stale)
    is refused.

    Args:
        p: The entry's profile reader (for messages).
        raw: The entry's ``sim`` value (None when absent).
        heartbeat_period: The driver's ``heartbeat_period``, s.
        encoder_period: The driver's ``encoder_period``, s.

    Returns:
        ``{name: ms}`` for every rate, the supervised two included.

    Raises:
        ProfileError: ``sim`` is not a mapping, names an unknown rate, has a value that is
            not a number of ms >= 0, or turns off (or changes) a supervised stream.
    """
    from temoto.drivers.can_motor.sim import CYCLIC_RATES

    rates = {
        "heartbeat_msg_rate_ms": heartbeat_period * 1000.0,
        "encoder_msg_rate_ms": encoder_period * 1000.0,
    }
    if raw is None:
        return rates
    sim = p.mapping(raw, "sim")
    for key in sim:
        if key in SIM_MECHANICS or key in SIM_KEYS:
            continue
        if key not in CYCLIC_RATES:
            p.fail(
                f"sim.{key}",
                f"unknown; the simulator's settings are the ODrive's cyclic message rates"
                f" ({', '.join(CYCLIC_RATES)}) and the axes' mechanics"
                f" ({', '.join(SIM_MECHANICS)}) and realism, seed",
            )
        ms = p.field(sim, key, _SIM_MS, "sim")
        driver_key = _SUPERVISED.get(key)
        if driver_key is not None and not math.isclose(ms, rates[key]):
            why = (
                "0 turns them off, but the driver supervises them"
                if ms == 0
                else f"differs from {driver_key} ({rates[key] / 1000.0:g} s), which the"
                " driver expects them at"
            )
            p.fail(
                f"sim.{key}",
                f"{why}: leave it out, or set {driver_key} (the device's {key} / 1000)",
            )
        rates[key] = ms
    return rates


def sim_mechanics(p: ProfileReader, raw: object) -> dict[str, float]:
    """The simulated axes' mechanics from an entry's ``sim`` mapping (:data:`SIM_MECHANICS`).

    Args:
        p: The entry's profile reader (for messages).
        raw: The entry's ``sim`` value (None when absent).

    Returns:
        ``{key: value}`` of the keys given.

    Raises:
        ProfileError: ``sim`` is not a mapping, or a value is not a number >= 0 (the current
            limit, the velocity limit and the torque constant: > 0).
    """
    if raw is None:
        return {}
    sim = p.mapping(raw, "sim")
    out = {key: p.field(sim, key, _POSITIVE, "sim") for key in SIM_MECHANICS if key in sim}
    for key in ("current_limit", "vel_limit", "torque_constant"):
        if out.get(key, 1.0) <= 0:
            p.fail(f"sim.{key}", f"must be a positive number of {SIM_MECHANICS[key]}")
    return out


def read_nodes(reader: ProfileReader, value: object, key: str) -> list[ODriveNode]:
    """The ``nodes`` of an entry: each a node id, a joint, a gear ratio and limits.

    Args:
        reader: Where errors are raised.
        value: The list.
        key: Its key path.

    Returns:
        The nodes, in order.

    Raises:
        ProfileError: A bad node (named by its index), a duplicate id or joint.
    """
    nodes: list[ODriveNode] = []
    members = read_members(
        reader, value, key, _NODE_KEYS, "node_id", (0, cs.MAX_NODE_ID), id_word="node id"
    )
    for path, node, node_id, joint in members:
        gear = reader.field(node, "gear_ratio", number(1.0), path)
        nodes.append(ODriveNode(node_id, joint, gear, read_limits(reader, node, path)))
    return nodes
