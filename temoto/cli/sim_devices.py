"""``temoto sim``'s simulators: each started, closed with the command, and described.

:func:`serve_kind` starts the simulator of one ``temoto sim KIND`` form and
:func:`serve_profile` the simulator of every device of a hardware profile (each built by its
driver's ``simulate()``; virtual CAN channels become multicast groups so that other processes
reach them). Each comes back as a :class:`Served`: the simulator, its :class:`Endpoint` (the
``link`` a profile uses to reach it, and how the usual tools connect) and a reader of its
traffic. :func:`endpoint_for` describes a simulator a driver's ``simulate()`` made (the robot
command uses it too). Invalid input raises :class:`~temoto.errors.ConfigError`.
"""

from __future__ import annotations

import argparse
import ipaddress
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from temoto.cli.sim_args import DEFAULT_CAN_GROUP, DEFAULT_OUT, parse_udp_address
from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.errors import ConfigError, DriverError

__all__ = ["Endpoint", "Served", "endpoint_for", "serve_kind", "serve_profile"]


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


@dataclass
class Served:
    """A running simulator and how the command watches it."""

    endpoint: Endpoint
    sim: Any
    traffic: Callable[[], tuple[int, set[str]]]


def _started(stack: ExitStack, sim: Any, what: str) -> None:
    """Start ``sim`` and close it when the command ends."""
    try:
        sim.start()
    except (OSError, DriverError) as err:
        sim.close()
        raise ConfigError(f"{what}: cannot start: {err}") from err
    stack.callback(sim.close)


def serve_kind(kind: str, args: argparse.Namespace, stack: ExitStack) -> Served:
    """Start the simulator of ``temoto sim KIND`` and close it when ``stack`` closes.

    Args:
        kind: ``quad``, ``odrive``, ``mit`` or ``dynamixel``.
        args: The parsed arguments of that form.
        stack: Closes the simulator.

    Returns:
        The running simulator.

    Raises:
        ConfigError: Invalid arguments, or the simulator cannot start.
    """
    if kind == "quad":
        return _quad(args, stack)
    if kind in ("odrive", "mit"):
        return _can(kind, args, stack)
    return _dynamixel(args, stack)


def _quad(args: argparse.Namespace, stack: ExitStack) -> Served:
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
            realism=args.realism,
            seed=args.seed,
            **kwargs,
        )
    except (ValueError, OSError) as err:
        where = f"--params {args.params}: " if args.params is not None else ""
        raise ConfigError(f"temoto sim quad: {where}{err}") from err
    _started(stack, sim, f"quad on udp {args.bind}:{args.port}")
    return Served(_vehicle_endpoint("quad", sim, None, outs), sim, _mavlink_traffic(sim))


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


def _can(kind: str, args: argparse.Namespace, stack: ExitStack) -> Served:
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
                realism=args.realism,
                seed=args.seed,
                device=kind,
            )
            ids = sorted(args.node)
            driver = "odrive_can"
        else:
            models = [MitModel.of(i, m) for i, m in args.motor]
            sim = SimMitMotor(
                link,
                models,
                clock,
                host_id=args.host_id,
                can_timeout=args.can_timeout,
                realism=args.realism,
                seed=args.seed,
                device=kind,
            )
            ids = sorted(i for i, _ in args.motor)
            driver = "mit_can"
    except ValueError as err:  # duplicate ids
        raise ConfigError(f"temoto sim {kind}: {err}") from err
    _started(stack, sim, f"{kind} on {_flow(link)}")
    endpoint = _can_endpoint(kind, driver, link, ids)
    if kind == "odrive":
        endpoint.extra["rates_ms"] = {name: period * 1000.0 for name, period in sim.periods.items()}
    return Served(endpoint, sim, _counter(lambda: sim.frames_received))


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


def _dynamixel(args: argparse.Namespace, stack: ExitStack) -> Served:
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
    return Served(_dxl_endpoint("dynamixel", sim, link, servos), sim, _dxl_traffic(sim))


def _dxl_endpoint(device: str, sim: Any, link: str, servos: Mapping[int, str]) -> Endpoint:
    tools = [
        f"dynamixel-sdk: PortHandler({sim.path!r}), Protocol 2.0",
        f"socat TCP-LISTEN:4001,reuseaddr,fork FILE:{sim.path},raw,echo=0   (a TCP serial port)",
    ]
    extra = {"port": sim.path, "servos": {str(i): m for i, m in sorted(servos.items())}}
    return Endpoint(device, "dynamixel", link, tools, extra)


def _dxl_traffic(sim: Any) -> Callable[[], tuple[int, set[str]]]:
    return _counter(lambda: int(sim.stats["packets"]))


def serve_profile(path: Path, args: argparse.Namespace, stack: ExitStack) -> list[Served]:
    """Start the simulator of every device of a hardware profile, closed when ``stack`` closes.

    Args:
        path: The profile.
        args: The parsed arguments (``--out``).
        stack: Closes the simulators.

    Returns:
        The running simulators, in the profile's order.

    Raises:
        ConfigError: A bad profile, ``--out`` without a vehicle, a simulator that cannot start.
    """
    from temoto.config import load_profile
    from temoto.drivers import driver_class

    clock = MonotonicClock()
    profile = load_profile(path, clock=clock)
    outs: list[tuple[str, int]] = getattr(args, "out", None) or []
    _outs_reachable(outs, "127.0.0.1")  # a profile's simulated vehicles bind loopback
    groups: dict[str, str] = {}  # virtual channel → the multicast group serving it
    served: list[Served] = []
    for name, spec in profile.devices.items():
        config = dict(spec.config)
        link = config.get("link")
        if isinstance(link, Mapping) and link.get("interface") == "virtual":
            group = groups.setdefault(str(link.get("channel")), _group(len(groups)))
            config["link"] = {"interface": "udp_multicast", "channel": group}
        own = config.get("sim")
        if own is None or isinstance(own, Mapping):  # the entry's own keys win
            level: dict[str, Any] = {"realism": args.realism}
            if args.seed is not None:
                level["seed"] = args.seed
            config["sim"] = {**level, **(own or {})}
        try:
            sim, settings = driver_class(spec.driver).simulate(name, config, clock=clock)
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
) -> Served:
    endpoint = endpoint_for(name, driver, sim, settings, outs)
    if driver == "mavlink":
        return Served(endpoint, sim, _mavlink_traffic(sim))
    if driver == "dynamixel":
        return Served(endpoint, sim, _dxl_traffic(sim))
    if hasattr(sim, "frames_received"):
        return Served(endpoint, sim, _counter(lambda: sim.frames_received))
    return Served(endpoint, sim, _counter(lambda: 0))
