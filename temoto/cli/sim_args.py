"""``temoto sim``'s command line: the sub-command's arguments and their parsers.

:func:`add_sim` adds ``temoto sim`` and its forms (``quad``, ``odrive``, ``mit``, ``dynamixel``,
``--profile``) to the ``temoto`` parser; the other functions parse one option's value each and
raise :class:`argparse.ArgumentTypeError` with a message naming what was expected. Run by
:mod:`temoto.cli.sim`; the guide is ``docs/simulators.md``.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
from collections.abc import Callable
from typing import Any, Final

from temoto.cli.realism_opts import add_realism_options

__all__ = ["DEFAULT_CAN_GROUP", "DEFAULT_OUT", "DEFAULT_PORT", "add_sim", "parse_udp_address"]

#: The vehicle's own UDP port: the number ArduPilot SITL serves its first MAVLink port on
#: (SERIAL0, TCP there; this vehicle speaks UDP only).
DEFAULT_PORT: Final = 5760
#: Where the vehicle streams when no ``--out`` is given: the ground station port that
#: ``sim_vehicle.py``'s MAVProxy forwards SITL to, and where QGroundControl listens.
DEFAULT_OUT: Final = ("127.0.0.1", 14550)
#: python-can's IPv4 multicast group for ``udp_multicast`` (``UdpMulticastBus.DEFAULT_GROUP_IPv4``).
DEFAULT_CAN_GROUP: Final = "239.74.163.2"


def parse_udp_address(text: str, *, bind: str = "127.0.0.1") -> tuple[str, int]:
    """An ``--out`` / ``--sim-out`` value: ``udp:HOST:PORT`` (also ``udpout:`` or bare).

    A vehicle bound to a loopback address (the default, and always the robot command's) can
    send only to loopback addresses, so then the host must be one (or ``localhost``); a
    ground station elsewhere is reached through ``temoto sim quad --bind`` or MAVProxy's
    ``--out``.

    Args:
        text: The value.
        bind: The address the vehicle binds.

    Returns:
        ``(host, port)``.

    Raises:
        argparse.ArgumentTypeError: Not that form, a port outside 1..65535, or a host that is
            not loopback for a vehicle bound to loopback.
    """
    rest = text
    for prefix in ("udp:", "udpout:"):
        if rest.startswith(prefix):
            rest = rest[len(prefix) :]
            break
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host or not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected udp:HOST:PORT, e.g. udp:127.0.0.1:14550"
        )
    if host == "localhost":
        host = "127.0.0.1"
    if _is_loopback(bind) and not _is_loopback(host):
        raise argparse.ArgumentTypeError(
            f"{text!r}: the simulated vehicle binds {bind} and can only send to a loopback"
            " address; bind it to a network address (temoto sim quad --bind 0.0.0.0) or"
            " forward with MAVProxy (mavproxy.py --master ... --out HOST:PORT)"
        )
    return host, int(port_text)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _any_udp_address(text: str) -> tuple[str, int]:
    """``--out`` of ``temoto sim``: any host here; checked against ``--bind`` later."""
    return parse_udp_address(text, bind="0.0.0.0")


def _bind_address(text: str) -> str:
    try:
        ipaddress.IPv4Address(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected an IPv4 address of this host, e.g. 127.0.0.1 or 0.0.0.0"
        ) from None
    return text


def _home(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        lat, lon, alt = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected LAT,LON,ALT (degrees, degrees, metres above sea level)"
        ) from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(alt)):
        raise argparse.ArgumentTypeError(f"{text!r}: latitude -90..90, longitude -180..180")
    return lat, lon, alt


def _speedup(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be more than 0")
    return value


def _int_in(lo: int, hi: int, what: str) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text!r}: {what} must be {lo}..{hi}")
        return value

    return parse


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be 0 (off) or more seconds")
    return value


def _rate(text: str) -> tuple[str, float]:
    from temoto.drivers.can_motor.sim import CYCLIC_RATES

    name, sep, ms = text.partition("=")
    full = name if name.endswith("_msg_rate_ms") else f"{name}_msg_rate_ms"
    short = [n.removesuffix("_msg_rate_ms") for n in CYCLIC_RATES]
    if not sep or full not in CYCLIC_RATES:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected NAME=MS with NAME one of {', '.join(short)}"
        )
    try:
        value = float(ms)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {ms!r} is not a number of ms") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: the rate must be 0 (off) or more ms")
    return full, value


def _servo(text: str) -> tuple[int, str]:
    from temoto.drivers.dynamixel import control_table as ct

    id_text, sep, model = text.partition(":")
    if not sep or not id_text.isdigit() or not 0 <= int(id_text) <= 252:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected ID:MODEL with ID 0..252, e.g. 1:XM430-W350"
        )
    if model not in ct.MODELS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: unknown model {model!r} (known: {', '.join(ct.MODELS)})"
        )
    return int(id_text), model


def _motor(text: str) -> tuple[int, str]:
    from temoto.drivers.can_motor import mitmode

    id_text, _, model = text.partition(":")
    model = model or "AK80-9"
    try:
        motor_id = int(id_text, 0)
    except ValueError:
        motor_id = -1
    if not 1 <= motor_id <= 255:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ID[:MODEL] with ID 1..255")
    if model not in mitmode.MODELS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: unknown model {model!r} (known: {', '.join(mitmode.MODELS)})"
        )
    return motor_id, model


def add_sim(sub: Any) -> None:
    """Add ``temoto sim`` to the top-level subparsers.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.
    """
    sim = sub.add_parser(
        "sim",
        help="run device simulators that real tools (MAVProxy, QGroundControl, can.viewer,"
        " dynamixel-sdk) can use",
        description="Run a device simulator, or every device of a hardware profile, until"
        " SIGINT or SIGTERM (exit 0). Prints each simulator's endpoint as the profile line that"
        " reaches it from another process, and how the usual tools connect (docs/simulators.md).",
    )
    sim.add_argument(
        "--profile",
        metavar="FILE",
        help="simulate every device of this hardware profile (instead of a KIND)",
    )
    _common(sim, out=True)
    kinds = sim.add_subparsers(dest="sim_kind", metavar="KIND")

    quad = kinds.add_parser(
        "quad",
        help="an ArduCopter-like quadcopter speaking MAVLink 2 over UDP",
        description="A simulated ArduCopter on UDP: it binds 127.0.0.1:PORT (a ground station"
        " may send to it: udpout:127.0.0.1:PORT) and streams to every --out (default"
        f" udp:{DEFAULT_OUT[0]}:{DEFAULT_OUT[1]}, where QGroundControl and MAVProxy listen).",
    )
    quad.add_argument(
        "--bind",
        type=_bind_address,
        default="127.0.0.1",
        metavar="ADDR",
        help="the address the vehicle binds (default 127.0.0.1; 0.0.0.0 or a network"
        " address lets a ground station on another machine reach it, and --out go there)",
    )
    quad.add_argument(
        "--port",
        type=_int_in(0, 65535, "a UDP port"),
        default=DEFAULT_PORT,
        help=f"the vehicle's own UDP port (default {DEFAULT_PORT}, SITL's first MAVLink port;"
        " 0: any free one)",
    )
    quad.add_argument(
        "--speedup",
        type=_speedup,
        default=1.0,
        metavar="F",
        help="run the vehicle's clock F times faster than real time (default 1)",
    )
    quad.add_argument(
        "--params",
        metavar="FILE",
        help="the vehicle's parameter file: read at start, written when parameters change",
    )
    quad.add_argument(
        "--sysid",
        type=_int_in(1, 255, "a MAVLink system id"),
        default=1,
        metavar="N",
        help="MAVLink system id (default 1)",
    )
    quad.add_argument(
        "--home",
        type=_home,
        metavar="LAT,LON,ALT",
        help="home position (default 47.397742,8.545594,488: Zurich, as PX4's and our default)",
    )
    _common(quad, out=True)

    for kind, what in (("odrive", "ODrive axes (CANSimple)"), ("mit", "MIT-mode motors")):
        can_sim = kinds.add_parser(
            kind,
            help=f"{what} on a python-can bus",
            description=f"{what} on a python-can bus. udp_multicast crosses processes"
            " (python-can's can.viewer and can.logger -i udp_multicast -c GROUP watch it);"
            " virtual stays inside this process.",
        )
        can_sim.add_argument(
            "--bus",
            choices=("udp_multicast", "virtual"),
            default="udp_multicast",
            help="python-can interface (default udp_multicast)",
        )
        can_sim.add_argument(
            "--channel",
            metavar="C",
            help=f"the bus channel: a multicast group (default {DEFAULT_CAN_GROUP}) or a"
            " virtual channel name (default temoto-sim)",
        )
        if kind == "odrive":
            can_sim.add_argument(
                "--node",
                type=_int_in(0, 63, "a node id"),
                action="append",
                required=True,
                metavar="ID",
                help="an axis's node id 0..63 (repeatable)",
            )
            can_sim.add_argument(
                "--rate",
                type=_rate,
                action="append",
                default=[],
                metavar="NAME=MS",
                help="a cyclic message's rate as the ODrive's axis.config.can.NAME_msg_rate_ms"
                " (heartbeat=100, encoder=10, iq, error, temperature, bus_voltage, torques,"
                " powers, version; 0 = off; repeatable)",
            )
            can_sim.add_argument(
                "--watchdog",
                type=_seconds,
                default=0.0,
                metavar="S",
                help="the axes' watchdog_timeout with enable_watchdog set (default 0: off)",
            )
        else:
            can_sim.add_argument(
                "--motor",
                type=_motor,
                action="append",
                required=True,
                metavar="ID[:MODEL]",
                help="a motor id 1..255 and its model (default AK80-9; repeatable)",
            )
            can_sim.add_argument(
                "--host-id",
                type=_int_in(0, 0x7FF, "a CAN id"),
                default=0,
                metavar="ID",
                help="the CAN id replies are sent with (default 0)",
            )
            can_sim.add_argument(
                "--can-timeout",
                type=_seconds,
                default=0.0,
                metavar="S",
                help="the motors' firmware CAN timeout (default 0: off)",
            )
        _common(can_sim, out=False)

    dxl = kinds.add_parser(
        "dynamixel",
        help="a chain of DYNAMIXEL X-series servos (Protocol 2.0) on a pseudo-terminal",
        description="A chain of DYNAMIXEL servos on a pseudo-terminal: open the printed"
        " /dev/pts/N as the serial port (dynamixel-sdk's PortHandler, a serial terminal).",
    )
    dxl.add_argument(
        "--servo",
        type=_servo,
        action="append",
        required=True,
        metavar="ID:MODEL",
        help="a servo (repeatable), e.g. --servo 1:XM430-W350",
    )
    dxl.add_argument(
        "--baud",
        type=int,
        metavar="B",
        help="model the servos' baud rate: they hear only packets sent at it (default: every"
        " packet is heard, whatever the line's rate)",
    )
    _common(dxl, out=False)


def _common(p: argparse.ArgumentParser, *, out: bool) -> None:
    """Options every form takes (``--json``; ``--out`` where a vehicle can be simulated).

    Subparsers write to the same names with ``SUPPRESS`` defaults, so an option given before
    or after the kind counts.
    """
    default: Any = argparse.SUPPRESS
    add_realism_options(p, suppress=True)
    p.add_argument(
        "--json",
        action="store_true",
        default=default,
        help="print JSON lines on standard output (endpoints, then events); text to stderr",
    )
    if out:
        p.add_argument(
            "--out",
            type=_any_udp_address,
            action="append",
            default=default,
            metavar="udp:HOST:PORT",
            help="also stream each simulated vehicle to this UDP address (repeatable; loopback"
            " unless `quad --bind` names a network address; for `quad` the default is"
            f" udp:{DEFAULT_OUT[0]}:{DEFAULT_OUT[1]})",
        )
