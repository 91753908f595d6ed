"""``temoto sim``: the device simulators as a standalone command, for real tools to use.

``temoto sim quad|odrive|mit|dynamixel ...`` starts one simulator; ``temoto sim --profile
FILE`` starts the simulator of every device of a hardware profile (each built by its driver's
``simulate()``, so the profile's simulator settings apply). Either way the command prints what
it serves, then keeps serving until SIGINT or SIGTERM, and exits 0 (ARCHITECTURE.md §8: a
server stopped by a signal); invalid input is exit status 2 with a one-line message.

What it prints on standard output, per device, is the ``link`` line a profile uses to reach the
simulator from another process (``link: {interface: udp_multicast, channel: 239.74.163.2}``,
``link: serial:/dev/pts/7``, ``link: udpout:127.0.0.1:5760``), and how the usual tools connect
(MAVProxy, python-can's ``can.viewer``, a serial terminal); then a line whenever a client starts
or stops talking to a simulator (none of these links has a connect of its own: UDP, CAN and a
pseudo-terminal only show traffic), and, for a MAVLink vehicle, the first time each message
arrives. With ``--json`` standard output carries JSON lines only (one per endpoint, then one per
event) and the text goes to standard error. ``docs/simulators.md`` is the guide.

Kept apart from :mod:`temoto.cli` so that other commands import no driver code. Like
:mod:`temoto.cli`, this module prints.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final

from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.errors import ConfigError, DriverError

__all__ = [
    "DEFAULT_CAN_GROUP",
    "DEFAULT_OUT",
    "DEFAULT_PORT",
    "Endpoint",
    "add_sim",
    "endpoint_for",
    "parse_udp_address",
    "sim_command",
]

#: The vehicle's own UDP port: the number ArduPilot SITL serves its first MAVLink port on
#: (SERIAL0, TCP there; this vehicle speaks UDP only).
DEFAULT_PORT: Final = 5760
#: Where the vehicle streams when no ``--out`` is given: the ground station port that
#: ``sim_vehicle.py``'s MAVProxy forwards SITL to, and where QGroundControl listens.
DEFAULT_OUT: Final = ("127.0.0.1", 14550)
#: python-can's IPv4 multicast group for ``udp_multicast`` (``UdpMulticastBus.DEFAULT_GROUP_IPv4``).
DEFAULT_CAN_GROUP: Final = "239.74.163.2"
#: Seconds without traffic after which a client counts as gone (and its return as a new one).
QUIET_S: Final = 2.0
#: Real seconds between two looks at the simulators' traffic.
WATCH_PERIOD_S: Final = 0.1


@dataclass
class Endpoint:
    """What one simulator serves, as a profile would reach it.

    Attributes:
        device: The device's name.
        driver: The driver's profile name (``mavlink``, ``odrive_can``, ...).
        link: The profile's ``link`` value for a driver in another process.
        tools: How the usual tools connect (command lines).
        extra: More facts for the JSON line (ports, ids).
    """

    device: str
    driver: str
    link: Any
    tools: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def line(self) -> str:
        """The text line: ``<device> (<driver>): link: <value>``."""
        return f"{self.device} ({self.driver}): link: {_flow(self.link)}"

    def summary(self) -> str:
        """One line: :meth:`line` and how the first of the tools connects."""
        return f"{self.line()}   # {self.tools[0]}" if self.tools else self.line()

    def json(self) -> dict[str, Any]:
        """The JSON line's object."""
        return {"device": self.device, "driver": self.driver, "link": self.link, **self.extra}


def _flow(value: Any) -> str:
    """A link value as one line of YAML (``{interface: udp_multicast, channel: ...}``)."""
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {v}" for k, v in value.items()) + "}"
    return str(value)


# ---- arguments -------------------------------------------------------------------------------


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


# ---- running ---------------------------------------------------------------------------------


class _Printer:
    """Text lines (and JSON lines with ``--json``) from several threads."""

    def __init__(self, as_json: bool, out: IO[str] | None = None) -> None:
        self.as_json = as_json
        self.out = out or sys.stdout
        self.text = sys.stderr if as_json else self.out
        self.broken = False  # a reader went away (``temoto sim quad | head -1``)
        self._lock = threading.Lock()

    def say(self, line: str, event: Mapping[str, Any] | None = None) -> None:
        with self._lock:
            if self.broken:
                return
            try:
                self.text.write(line + "\n")
                self.text.flush()
                if self.as_json and event is not None:
                    self.out.write(json.dumps(event, sort_keys=True) + "\n")
                    self.out.flush()
            except BrokenPipeError:
                self.broken = True


@dataclass
class _Served:
    """A running simulator and how the command watches it."""

    endpoint: Endpoint
    sim: Any
    traffic: Callable[[], tuple[int, set[str]]]


def sim_command(args: argparse.Namespace, out: IO[str] | None = None) -> int:
    """Run ``temoto sim`` until SIGINT or SIGTERM.

    Args:
        args: The parsed arguments.
        out: Where endpoints and events go (default standard output).

    Returns:
        0 (stopped by a signal); 2 for invalid input (with a message on stderr).

    Raises:
        ConfigError: Invalid input (a bad profile, neither or both of KIND and --profile).
        BrokenPipeError: The reader of the output went away (the simulators are closed).
    """
    from temoto._cli_fleet import SignalExit

    kind = getattr(args, "sim_kind", None)
    profile = getattr(args, "profile", None)
    if (kind is None) == (profile is None):
        raise ConfigError(
            "temoto sim: say what to simulate: a KIND (quad, odrive, mit, dynamixel) or"
            " --profile FILE, not both"
        )
    printer = _Printer(bool(getattr(args, "json", False)), out)
    with SignalExit() as signals, ExitStack() as stack:
        if kind is None:
            served = _from_profile(Path(str(profile)), args, stack)
        else:
            served = [_one(str(kind), args, stack)]
        _announce(printer, served, profile)
        if printer.broken:
            raise BrokenPipeError("the reader of temoto sim's output went away")
        watcher = threading.Thread(
            target=_watch, args=(printer, served, signals.stop), name="temoto-sim-watch"
        )
        watcher.start()
        try:
            while not signals.stop.wait(WATCH_PERIOD_S) and not printer.broken:
                pass
        finally:
            signals.stop.set()
            watcher.join()
    if printer.broken:
        raise BrokenPipeError("the reader of temoto sim's output went away")
    return 0


def _started(stack: ExitStack, sim: Any, what: str) -> None:
    """Start ``sim`` and close it when the command ends."""
    try:
        sim.start()
    except (OSError, DriverError) as err:
        sim.close()
        raise ConfigError(f"{what}: cannot start: {err}") from err
    stack.callback(sim.close)


def _one(kind: str, args: argparse.Namespace, stack: ExitStack) -> _Served:
    if kind == "quad":
        return _quad(args, stack)
    if kind in ("odrive", "mit"):
        return _can(kind, args, stack)
    return _dynamixel(args, stack)


def _quad(args: argparse.Namespace, stack: ExitStack) -> _Served:
    from temoto.drivers.mavlink.sim import SimVehicle

    clock: Clock = ScaledClock(args.speedup) if args.speedup != 1.0 else MonotonicClock()
    kwargs: dict[str, Any] = {}
    if args.home is not None:
        kwargs["home"] = args.home
    if args.params is not None:
        kwargs["params_file"] = args.params
    outs = getattr(args, "out", None) or [DEFAULT_OUT]
    _outs_reachable(outs, args.bind)
    try:
        sim = SimVehicle(
            "quad",
            clock=clock,
            gcs=outs,
            host=args.bind,
            port=args.port,
            system_id=args.sysid,
            **kwargs,
        )
    except (ValueError, OSError) as err:
        where = f"--params {args.params}: " if args.params is not None else ""
        raise ConfigError(f"temoto sim quad: {where}{err}") from err
    _started(stack, sim, f"quad on udp {args.bind}:{args.port}")
    return _Served(_vehicle_endpoint("quad", sim, None, outs), sim, _mavlink_traffic(sim))


def _outs_reachable(outs: Sequence[tuple[str, int]], bind: str) -> None:
    """Refuse ``--out`` addresses a vehicle bound to ``bind`` cannot send to."""
    for host, port in outs:
        try:
            parse_udp_address(f"udp:{host}:{port}", bind=bind)
        except argparse.ArgumentTypeError as err:
            raise ConfigError(f"temoto sim: --out {err}") from None


def _vehicle_endpoint(
    device: str, sim: Any, link: str | None, gcs: Sequence[tuple[str, int]]
) -> Endpoint:
    """A vehicle's endpoint; ``link`` is the driver's (a profile's), else ``udpout:`` to it."""
    host, port = sim.address
    outs = [f"udp:{h}:{p}" for h, p in gcs]
    first = outs[0] if outs else None
    tools = [f"mavproxy.py --master udpout:{host}:{port}   (MAVProxy sends first, then hears)"]
    if first is not None:
        tools.append(f"mavproxy.py --master {first}   (or QGroundControl: it listens on 14550)")
    return Endpoint(
        device,
        "mavlink",
        link or f"udpout:{host}:{port}",
        tools,
        {"vehicle": f"udp:{host}:{port}", "streams_to": outs},
    )


def _mavlink_traffic(sim: Any) -> Callable[[], tuple[int, set[str]]]:
    def traffic() -> tuple[int, set[str]]:
        received = dict(sim.received)
        return sum(received.values()), set(received)

    return traffic


def _can_link(args: argparse.Namespace) -> dict[str, Any]:
    if args.bus == "udp_multicast":
        channel = args.channel or DEFAULT_CAN_GROUP
        try:
            if not ipaddress.ip_address(channel).is_multicast:
                raise ValueError
        except ValueError:
            raise ConfigError(
                f"--channel {channel!r}: udp_multicast needs a multicast group address"
                f" (e.g. {DEFAULT_CAN_GROUP})"
            ) from None
        return {"interface": "udp_multicast", "channel": channel}
    return {"interface": "virtual", "channel": args.channel or "temoto-sim"}


def _can(kind: str, args: argparse.Namespace, stack: ExitStack) -> _Served:
    from temoto.drivers.can_motor import mitmode
    from temoto.drivers.can_motor.sim import MitModel, SimMitMotor, SimODrive

    link = _can_link(args)
    clock = MonotonicClock()
    try:
        if kind == "odrive":
            sim: Any = SimODrive(
                link,
                args.node,
                clock,
                watchdog_timeout=args.watchdog,
                rates_ms=dict(args.rate),
            )
            ids = sorted(args.node)
            driver = "odrive_can"
        else:
            models = [MitModel(i, mitmode.MODELS[m]) for i, m in args.motor]
            sim = SimMitMotor(
                link, models, clock, host_id=args.host_id, can_timeout=args.can_timeout
            )
            ids = sorted(i for i, _ in args.motor)
            driver = "mit_can"
    except ValueError as err:  # duplicate ids
        raise ConfigError(f"temoto sim {kind}: {err}") from err
    _started(stack, sim, f"{kind} on {_flow(link)}")
    endpoint = _can_endpoint(kind, driver, link, ids)
    if kind == "odrive":
        endpoint.extra["rates_ms"] = {name: period * 1000.0 for name, period in sim.periods.items()}
    return _Served(endpoint, sim, _counter(lambda: sim.frames_received))


def _can_endpoint(device: str, driver: str, link: Mapping[str, Any], ids: list[int]) -> Endpoint:
    key = "nodes" if driver == "odrive_can" else "motors"
    tools: list[str] = []
    if link["interface"] == "udp_multicast":
        channel = link["channel"]
        tools = [
            f"python -m can.viewer -i udp_multicast -c {channel}",
            f"python -m can.logger -i udp_multicast -c {channel} -f frames.log",
        ]
    else:
        tools = ["a virtual bus reaches only this process: use --bus udp_multicast for tools"]
    return Endpoint(device, driver, dict(link), tools, {key: ids})


def _counter(read: Callable[[], int]) -> Callable[[], tuple[int, set[str]]]:
    def traffic() -> tuple[int, set[str]]:
        return read(), set()

    return traffic


def _dynamixel(args: argparse.Namespace, stack: ExitStack) -> _Served:
    from temoto.drivers.dynamixel.sim import SimDynamixelChain

    servos = dict(args.servo)
    if len(servos) != len(args.servo):
        raise ConfigError("temoto sim dynamixel: each --servo needs an id of its own")
    try:
        sim = SimDynamixelChain(servos, clock=MonotonicClock(), name="dynamixel", baud=args.baud)
    except (ValueError, OSError) as err:
        raise ConfigError(f"temoto sim dynamixel: {err}") from err
    _started(stack, sim, "dynamixel chain")
    link = f"serial:{sim.path}" + (f"?baud={args.baud}" if args.baud else "")
    return _Served(_dxl_endpoint("dynamixel", sim, link, servos), sim, _dxl_traffic(sim))


def _dxl_endpoint(device: str, sim: Any, link: str, servos: Mapping[int, str]) -> Endpoint:
    tools = [
        f"dynamixel-sdk: PortHandler({sim.path!r}), Protocol 2.0",
        f"socat TCP-LISTEN:4001,reuseaddr,fork FILE:{sim.path},raw,echo=0   (a TCP serial port)",
    ]
    extra = {"port": sim.path, "servos": {str(i): m for i, m in sorted(servos.items())}}
    return Endpoint(device, "dynamixel", link, tools, extra)


def _dxl_traffic(sim: Any) -> Callable[[], tuple[int, set[str]]]:
    return _counter(lambda: int(sim.stats["packets"]))


# ---- a whole profile -------------------------------------------------------------------------


def _from_profile(path: Path, args: argparse.Namespace, stack: ExitStack) -> list[_Served]:
    from temoto.config import load_profile
    from temoto.drivers import driver_class

    clock = MonotonicClock()
    profile = load_profile(path, clock=clock)
    outs: list[tuple[str, int]] = getattr(args, "out", None) or []
    _outs_reachable(outs, "127.0.0.1")  # a profile's simulated vehicles bind loopback
    groups: dict[str, str] = {}  # virtual channel → the multicast group serving it
    served: list[_Served] = []
    for name, spec in profile.devices.items():
        config = dict(spec.config)
        link = config.get("link")
        if isinstance(link, Mapping) and link.get("interface") == "virtual":
            group = groups.setdefault(str(link.get("channel")), _group(len(groups)))
            config["link"] = {"interface": "udp_multicast", "channel": group}
        try:
            cls: Any = driver_class(spec.driver)
            sim, settings = cls.simulate(name, config, clock=clock)
        except DriverError as err:  # a driver whose library is missing, a busy resource
            raise ConfigError(f"{path}: devices.{name}: {err}") from err
        if outs and hasattr(sim, "add_gcs"):
            for host, port in outs:
                sim.add_gcs(host, port)
        _started(stack, sim, f"{path}: devices.{name}")
        served.append(_profile_served(name, spec.driver, sim, settings, outs))
    if outs and not any(s.endpoint.driver == "mavlink" for s in served):
        raise ConfigError(f"--out: {path} has no MAVLink vehicle to stream")
    return served


def _group(index: int) -> str:
    """The multicast group of the ``index``-th virtual CAN channel of a profile."""
    base = ipaddress.ip_address(DEFAULT_CAN_GROUP)
    return str(base + index)


def endpoint_for(
    name: str,
    driver: str,
    sim: Any,
    settings: Mapping[str, Any],
    outs: Sequence[tuple[str, int]] = (),
) -> Endpoint:
    """The endpoint of a started simulator that a driver's ``simulate()`` made.

    Args:
        name: The device's name.
        driver: The driver's profile name.
        sim: The simulator (started: a vehicle's own port is known only then).
        settings: The entry ``simulate()`` returned (its ``link`` reaches the simulator).
        outs: The extra ground stations a vehicle streams to (``--out``, ``--sim-out``).

    Returns:
        The endpoint (a driver of another kind: its ``link`` alone).
    """
    link = settings.get("link")
    if driver == "mavlink":
        text = str(link)
        host, _, port = text.rpartition(":")  # the driver's udpin: port the vehicle streams to
        gcs = [(host.partition(":")[2], int(port)), *outs] if port.isdigit() else list(outs)
        return _vehicle_endpoint(name, sim, text, gcs)
    if driver == "dynamixel":
        servos = {
            int(s["id"]): str(s.get("model", "?"))
            for s in settings.get("servos", [])
            if isinstance(s, Mapping) and isinstance(s.get("id"), int)
        }
        return _dxl_endpoint(name, sim, str(link), servos)
    if isinstance(link, Mapping) and driver in ("odrive_can", "mit_can"):
        ids = sorted(getattr(sim, "axes", None) or getattr(sim, "motors", {}))
        return _can_endpoint(name, driver, link, ids)
    return Endpoint(name, driver, link)


def _profile_served(
    name: str,
    driver: str,
    sim: Any,
    settings: Mapping[str, Any],
    outs: Sequence[tuple[str, int]],
) -> _Served:
    endpoint = endpoint_for(name, driver, sim, settings, outs)
    if driver == "mavlink":
        return _Served(endpoint, sim, _mavlink_traffic(sim))
    if driver == "dynamixel":
        return _Served(endpoint, sim, _dxl_traffic(sim))
    if hasattr(sim, "frames_received"):
        return _Served(endpoint, sim, _counter(lambda: sim.frames_received))
    return _Served(endpoint, sim, _counter(lambda: 0))


# ---- output ----------------------------------------------------------------------------------


def _announce(printer: _Printer, served: Sequence[_Served], profile: str | None) -> None:
    if profile is not None:
        printer.say(
            f"temoto sim: {profile}: a copy of the profile with `sim: false` and these links"
            " drives the simulators from another process:"
        )
    for one in served:
        printer.say(one.endpoint.line(), {"endpoint": one.endpoint.json()})
        for tool in one.endpoint.tools:
            printer.say(f"  {tool}")
    printer.say("temoto sim: serving; Ctrl-C stops")


def _watch(printer: _Printer, served: Sequence[_Served], stop: threading.Event) -> None:
    """Say when a client starts or stops talking to each simulator (and new MAVLink messages)."""
    state = {id(s): _Traffic() for s in served}
    while not stop.wait(WATCH_PERIOD_S):
        now = time.monotonic()
        for one in served:
            for line, event in state[id(one)].update(one.endpoint.device, one.traffic(), now):
                printer.say(line, event)


@dataclass
class _Traffic:
    """One simulator's traffic as last seen."""

    count: int = 0
    names: set[str] = field(default_factory=set)
    last: float | None = None  # when traffic was last seen (None: the client is quiet)

    def update(
        self, device: str, seen: tuple[int, set[str]], now: float
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        count, names = seen
        if count > self.count:
            if self.last is None:
                yield (
                    f"{device}: a client is talking ({count - self.count} messages so far)",
                    {"event": "client", "device": device, "talking": True},
                )
            self.last = now
        elif self.last is not None and now - self.last >= QUIET_S:
            yield (
                f"{device}: the client went quiet ({QUIET_S:g} s without traffic)",
                {"event": "client", "device": device, "talking": False},
            )
            self.last = None
        for name in sorted(names - self.names):
            yield (
                f"{device}: first {name}",
                {"event": "message", "device": device, "name": name},
            )
        self.count = count
        self.names |= names
