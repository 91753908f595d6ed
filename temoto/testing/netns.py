"""A simulated multi-robot network for tests: one network namespace per robot.

:class:`RobotNetwork` builds, as root, a small switched LAN out of Linux network namespaces::

    temoto-net-<pid>-<n>-r0        temoto-net-<pid>-<n>-sw          temoto-net-<pid>-<n>-r1
    lo, veth0 10.77.0.1/24  ────  p0 ─┐                      ┌─ p1  ────  lo, veth0 10.77.0.2/24
    224.0.0.0/4 dev veth0             br0 (mcast_snooping 0) ...        224.0.0.0/4 dev veth0

Every robot namespace gets a veth pair whose other end is a port of a bridge in a separate
"switch" namespace; multicast is routed to the robot's veth, so LCM with ``ttl=1``
(:data:`LCM_URL`) reaches every other robot through the bridge and nothing else. The host's
namespace and interfaces are never touched: every interface is created inside a namespace of
the network, and goes away with it. Names start with ``temoto-net-<pid>-`` so parallel runs do
not collide, and :func:`remove_leftovers` can remove the namespaces of a run that crashed.

Faults:

* :meth:`RobotNetwork.partition` takes the robot's port down *on the switch side* (the cable is
  cut at the switch, or the robot drove out of radio range): the robot keeps its address and
  routes, its own sends vanish without an error, and it hears nobody. :meth:`RobotNetwork.heal`
  brings the port back.
* :meth:`RobotNetwork.loss` installs an nftables rule in the robot's namespace that drops that
  percentage of the incoming UDP multicast (``numgen random mod 100 < N drop``), i.e. on the
  receiving side; :meth:`RobotNetwork.dropped` reads its counter.

Processes started with :meth:`RobotNetwork.run` (``ip netns exec``) get their own process group;
:meth:`RobotNetwork.close` (and leaving the ``with`` block, also on an exception) kills every
group still running, kills whatever else is left inside the namespaces, reaps its children and
deletes every namespace::

    with RobotNetwork(3) as net:
        procs = [net.run(i, ["temoto", "run", ...], stdout=subprocess.PIPE) for i in range(3)]
        net.partition(1)
        ...

Needs root, ``ip`` (iproute2) and, for :meth:`~RobotNetwork.loss`, ``nft`` (nftables);
:func:`missing_requirements` says what is missing. See ``docs/testing-networks.md``.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Sequence
from typing import Any, Final

from temoto._closing import Closing

__all__ = [
    "LCM_URL",
    "PREFIX",
    "NetworkSetupError",
    "RobotNetwork",
    "RoutedNetwork",
    "missing_requirements",
    "namespaces",
    "remove_leftovers",
]

PREFIX: Final = "temoto-net-"
"""Every namespace of a :class:`RobotNetwork` is named ``<PREFIX><pid>-<serial>-<role>``."""

LCM_URL: Final = "udpm://239.255.76.67:7667?ttl=1"
"""The LCM URL for a :class:`RobotNetwork`: LCM's default group, one hop (the bridge)."""

MULTICAST: Final = "224.0.0.0/4"
BRIDGE: Final = "br0"
ROBOT_IF: Final = "veth0"
LOSS_TABLE: Final = "temoto_loss"

_NAME = re.compile(re.escape(PREFIX) + r"(\d+)-\d+-(?:sw|rt|r\d+)$")
_serials = itertools.count()
_IP_TIMEOUT_S: Final = 10.0


class NetworkSetupError(RuntimeError):
    """A command that builds, changes or removes the simulated network failed."""


def missing_requirements(*, nft: bool = False) -> list[str]:
    """What this machine lacks to build a :class:`RobotNetwork`.

    Args:
        nft: Also require ``nft`` (for :meth:`RobotNetwork.loss`).

    Returns:
        Human-readable items (``"root"``, ``"ip (iproute2)"``, ``"nft (nftables)"``); empty
        if everything is there.
    """
    missing = []
    if os.geteuid() != 0:
        missing.append("root")
    if shutil.which("ip") is None:
        missing.append("ip (iproute2)")
    if nft and shutil.which("nft") is None:
        missing.append("nft (nftables)")
    return missing


def _cmd(argv: Sequence[str], stdin: str | None = None, *, check: bool = True) -> str:
    """Run a short setup command; its output, or NetworkSetupError naming it and its stderr."""
    try:
        proc = subprocess.run(
            list(argv),
            input=stdin,
            capture_output=True,
            text=True,
            timeout=_IP_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as err:
        raise NetworkSetupError(f"{' '.join(argv)}: {err}") from err
    if check and proc.returncode != 0:
        raise NetworkSetupError(
            f"{' '.join(argv)}: exit {proc.returncode}: {proc.stderr.strip() or proc.stdout}"
        )
    return proc.stdout


def namespaces(prefix: str = PREFIX) -> list[str]:
    """The named network namespaces (``ip netns list``) whose names start with ``prefix``.

    Args:
        prefix: The name prefix.

    Returns:
        Their names, sorted.
    """
    if shutil.which("ip") is None:
        return []
    names = (line.split()[0] for line in _cmd(["ip", "netns", "list"]).splitlines() if line)
    return sorted(n for n in names if n.startswith(prefix))


def _kill_inside(ns: str) -> list[int]:
    """SIGKILL every process inside a namespace; their pids."""
    out = _cmd(["ip", "netns", "pids", ns], check=False)
    pids = [int(p) for p in out.split() if p.isdigit()]
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return pids


def _delete(ns: str) -> None:
    """Kill what runs inside a namespace, then delete it (its interfaces go with it)."""
    _kill_inside(ns)
    _cmd(["ip", "netns", "delete", ns])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_leftovers(*, all_owners: bool = False) -> list[str]:
    """Remove the namespaces that a crashed earlier run of :class:`RobotNetwork` left behind.

    A namespace is a leftover when its owner (the pid in its name) is no longer running, or,
    with ``all_owners``, whenever it has our prefix. Processes still inside are killed first.

    Args:
        all_owners: Also remove the namespaces of live processes (this one included).

    Returns:
        The names removed.

    Raises:
        NetworkSetupError: A namespace could not be removed.
    """
    removed = []
    for ns in namespaces():
        match = _NAME.match(ns)
        if match is None:
            continue
        if all_owners or not _alive(int(match.group(1))):
            _delete(ns)
            removed.append(ns)
    return removed


class RobotNetwork(Closing):
    """Network namespaces for ``robots`` robots on one simulated switch (a context manager).

    Building needs root and ``ip``; on a failure halfway, whatever was built is removed
    before the error is raised.

    Args:
        robots: How many robot namespaces (1 to 250).
        subnet: The robots' /24 as its first three octets; robot ``i`` gets ``.i+1``.

    Attributes:
        robots: The robot namespaces' names, by robot index.
        switch: The switch namespace's name.
        addresses: The robots' IPv4 addresses, by robot index.

    Raises:
        ValueError: A bad ``robots`` count or subnet.
        NetworkSetupError: A setup command failed.
    """

    _middle = "sw"  # the role suffix of the namespace between the robots

    def __init__(self, robots: int, *, subnet: str = "10.77.0") -> None:
        if not 1 <= robots <= 250:
            raise ValueError(f"robots must be 1..250, not {robots}")
        if not re.fullmatch(r"10\.\d{1,3}\.\d{1,3}", subnet):
            raise ValueError(f"subnet must look like '10.x.y', not {subnet!r}")
        base = f"{PREFIX}{os.getpid()}-{next(_serials)}-"
        self.switch = base + self._middle
        self.robots = [f"{base}r{i}" for i in range(robots)]
        self.addresses = [f"{subnet}.{i + 1}" for i in range(robots)]
        self._procs: list[subprocess.Popen[Any]] = []
        self._made: list[str] = []
        self._closed = False
        try:
            self._build(subnet)
        except BaseException as err:
            try:
                self.close()
            except NetworkSetupError as cleanup:
                err.add_note(f"removing the half-built network failed too: {cleanup}")
            raise

    def _build(self, subnet: str) -> None:
        for ns in [self.switch, *self.robots]:
            _cmd(["ip", "netns", "add", ns])
            self._made.append(ns)
        switch = [
            "link set lo up",
            f"link add {BRIDGE} type bridge mcast_snooping 0",
            f"link set {BRIDGE} up",
        ]
        for i, ns in enumerate(self.robots):
            # created in the switch namespace, the robot's end moved straight into its own
            switch += [
                f"link add p{i} type veth peer name {ROBOT_IF} netns {ns}",
                f"link set p{i} master {BRIDGE}",
                f"link set p{i} up",
            ]
        _cmd(["ip", "-n", self.switch, "-batch", "-"], "\n".join(switch) + "\n")
        for ns, address in zip(self.robots, self.addresses, strict=True):
            robot = [
                "link set lo up",
                f"addr add {address}/24 dev {ROBOT_IF}",
                f"link set {ROBOT_IF} up",
                f"route replace {MULTICAST} dev {ROBOT_IF}",
            ]
            _cmd(["ip", "-n", ns, "-batch", "-"], "\n".join(robot) + "\n")

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{len(self.robots)} robots"
        return f"<RobotNetwork {self.switch.removesuffix('-sw')} {state}>"

    def namespace(self, robot: int | str) -> str:
        """The namespace of a robot.

        Args:
            robot: Its index, or its namespace name.

        Returns:
            The namespace name.

        Raises:
            LookupError: No such robot in this network.
        """
        if isinstance(robot, int):
            if 0 <= robot < len(self.robots):
                return self.robots[robot]
        elif robot in self.robots:
            return robot
        raise LookupError(f"{self!r} has no robot {robot!r}")

    def _index(self, robot: int | str) -> int:
        return self.robots.index(self.namespace(robot))

    def run(
        self, robot: int | str, argv: Sequence[str], **popen_kwargs: Any
    ) -> subprocess.Popen[Any]:
        """Start a program inside a robot's namespace (``ip netns exec``).

        The process is the leader of a new process group (``start_new_session``), which
        :meth:`close` kills if it is still running. The caller should wait for it (or
        ``communicate``); :meth:`close` reaps whatever it had to kill.

        Args:
            robot: The robot's index or namespace.
            argv: The program and its arguments.
            **popen_kwargs: Passed to :class:`subprocess.Popen` (``stdout=PIPE``, ``env``,
                ``text``...); ``start_new_session`` must not be false.

        Returns:
            The process.

        Raises:
            ValueError: ``start_new_session=False`` was asked for.
            NetworkSetupError: The network is closed.
        """
        return self._run_in(self.namespace(robot), argv, **popen_kwargs)

    def _run_in(self, ns: str, argv: Sequence[str], **popen_kwargs: Any) -> subprocess.Popen[Any]:
        if self._closed:
            raise NetworkSetupError(f"{self!r}: cannot start a program")
        if not popen_kwargs.setdefault("start_new_session", True):
            raise ValueError("processes in a RobotNetwork need their own session")
        proc: subprocess.Popen[Any] = subprocess.Popen(
            ["ip", "netns", "exec", ns, *argv], **popen_kwargs
        )
        self._procs.append(proc)
        return proc

    def partition(self, robot: int | str) -> None:
        """Cut a robot off the network: its switch port goes down.

        The robot's own interface loses its carrier but keeps its address and routes: what it
        sends is dropped without an error, and nothing reaches it.

        Args:
            robot: The robot's index or namespace.
        """
        _cmd(["ip", "-n", self.switch, "link", "set", f"p{self._index(robot)}", "down"])

    def heal(self, robot: int | str) -> None:
        """Undo :meth:`partition`: the robot's switch port comes back up.

        Args:
            robot: The robot's index or namespace.
        """
        _cmd(["ip", "-n", self.switch, "link", "set", f"p{self._index(robot)}", "up"])

    def loss(self, robot: int | str, percent: float) -> None:
        """Drop a percentage of the UDP multicast that reaches a robot (on its receiving side).

        Installs (or replaces) the nftables table ``inet temoto_loss`` in the robot's namespace
        with one rule on the input hook: ``ip daddr 224.0.0.0/4 meta l4proto udp numgen random
        mod 100 < N counter drop`` (without ``numgen`` for 100 %). Percent 0 removes the
        table.

        Args:
            robot: The robot's index or namespace.
            percent: 0 to 100, rounded to a whole percent.

        Raises:
            ValueError: Percent out of range.
            NetworkSetupError: ``nft`` is missing or failed.
        """
        if not 0 <= percent <= 100:
            raise ValueError(f"loss must be 0..100 %, not {percent}")
        ns = self.namespace(robot)
        script = [f"table inet {LOSS_TABLE}", f"delete table inet {LOSS_TABLE}"]
        share = round(percent)
        if share > 0:
            chance = f" numgen random mod 100 < {share}" if share < 100 else ""
            script += [
                f"table inet {LOSS_TABLE} {{",
                "  chain input {",
                "    type filter hook input priority filter; policy accept;",
                f"    ip daddr {MULTICAST} meta l4proto udp{chance} counter drop",
                "  }",
                "}",
            ]
        _cmd(["ip", "netns", "exec", ns, "nft", "-f", "-"], "\n".join(script) + "\n")

    def dropped(self, robot: int | str) -> int:
        """How many packets the :meth:`loss` rule of a robot has dropped so far.

        Args:
            robot: The robot's index or namespace.

        Returns:
            The rule's packet counter (0 without a loss rule).
        """
        ns = self.namespace(robot)
        out = _cmd(
            ["ip", "netns", "exec", ns, "nft", "list", "table", "inet", LOSS_TABLE], check=False
        )
        match = re.search(r"counter packets (\d+)", out)
        return int(match.group(1)) if match else 0

    def close(self, term_timeout: float = 2.0) -> None:
        """Stop every process started here, and delete every namespace. Idempotent.

        Process groups still running get SIGTERM, and SIGKILL after ``term_timeout``; then
        anything else left inside the namespaces is killed, the processes started here are
        reaped (their pipes closed), and the namespaces are deleted.

        Args:
            term_timeout: How long processes get to exit after SIGTERM.

        Raises:
            NetworkSetupError: A namespace could not be deleted (all others were).
        """
        if self._closed:
            return
        self._closed = True
        running = [p for p in self._procs if p.poll() is None]
        _signal_groups(running, signal.SIGTERM)
        deadline = time.monotonic() + term_timeout
        for proc in running:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        _signal_groups([p for p in running if p.returncode is None], signal.SIGKILL)
        for ns in self._made:
            with contextlib.suppress(NetworkSetupError):  # _delete tries again and reports
                _kill_inside(ns)
        for proc in running:
            # reaps it and closes its pipes; nothing is left to hold them open
            with contextlib.suppress(subprocess.TimeoutExpired, ValueError, OSError):
                proc.communicate(timeout=_IP_TIMEOUT_S)
        failures = []
        for ns in reversed(self._made):
            try:
                _delete(ns)
            except NetworkSetupError as err:
                failures.append(str(err))
        self._made.clear()
        if failures:
            raise NetworkSetupError("; ".join(failures))


def _signal_groups(procs: Sequence[subprocess.Popen[Any]], sig: signal.Signals) -> None:
    for proc in procs:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, sig)


class RoutedNetwork(RobotNetwork):
    """Robots on different subnets joined only by a router namespace (a context manager).

    ::

        <pid>-<n>-r0                       <pid>-<n>-rt                        <pid>-<n>-r1
        veth0 10.78.0.2/24 ──── p0 10.78.0.1/24   p1 10.78.1.1/24 ──── veth0 10.78.1.2/24
        default via 10.78.0.1   ip_forward=1, no multicast routing  default via 10.78.1.1

    Robot ``i`` has the /24 ``10.x.(y+i)`` of its own, a veth pair to the router namespace and a
    default route through it. Unicast is routed between the subnets; multicast is not (Linux
    forwards multicast only with a multicast routing daemon, and none runs), so LCM opens
    (the default route covers its group) but hears nobody, while a Zenoh router run in the
    router namespace (:meth:`run_router`) joins everyone over TCP. The robots' addresses are
    :attr:`addresses`, the router's on each robot's subnet :attr:`gateways`.

    :meth:`partition` and :meth:`heal` take the router's port of the robot down and up;
    :meth:`loss` drops a share of *every* IPv4 packet crossing the robot's link, in both
    directions (TCP included, unlike :meth:`RobotNetwork.loss`).

    Args:
        robots: How many robot namespaces (1 to 250).
        subnet: The first robot's /24 as its first three octets; the third octet counts up.

    Attributes:
        router: The router namespace's name (also :attr:`switch`, for the inherited calls).
        gateways: The router's address on each robot's subnet, by robot index.

    Raises:
        ValueError: A bad ``robots`` count or subnet, or subnets past ``.255``.
        NetworkSetupError: A setup command failed.
    """

    _middle = "rt"

    def __init__(self, robots: int, *, subnet: str = "10.78.0") -> None:
        match = re.fullmatch(r"(10\.\d{1,3})\.(\d{1,3})", subnet)
        if match is None:
            raise ValueError(f"subnet must look like '10.x.y', not {subnet!r}")
        if int(match.group(2)) + robots - 1 > 255:
            raise ValueError(f"{robots} subnets from {subnet} run past 255")
        self._net, self._first = match.group(1), int(match.group(2))
        self.gateways = [f"{self._net}.{self._first + i}.1" for i in range(robots)]
        super().__init__(robots, subnet=subnet)

    @property
    def router(self) -> str:
        """The router namespace's name."""
        return self.switch

    def _build(self, subnet: str) -> None:
        self.addresses = [f"{self._net}.{self._first + i}.2" for i in range(len(self.robots))]
        for ns in [self.switch, *self.robots]:
            _cmd(["ip", "netns", "add", ns])
            self._made.append(ns)
        router = ["link set lo up"]
        for i, (ns, gateway) in enumerate(zip(self.robots, self.gateways, strict=True)):
            router += [
                f"link add p{i} type veth peer name {ROBOT_IF} netns {ns}",
                f"addr add {gateway}/24 dev p{i}",
                f"link set p{i} up",
            ]
        _cmd(["ip", "-n", self.switch, "-batch", "-"], "\n".join(router) + "\n")
        _cmd(["ip", "netns", "exec", self.switch, "sysctl", "-qw", "net.ipv4.ip_forward=1"])
        for ns, address, gateway in zip(self.robots, self.addresses, self.gateways, strict=True):
            robot = [
                "link set lo up",
                f"addr add {address}/24 dev {ROBOT_IF}",
                f"link set {ROBOT_IF} up",
                f"route add default via {gateway}",
            ]
            _cmd(["ip", "-n", ns, "-batch", "-"], "\n".join(robot) + "\n")

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{len(self.robots)} robots"
        return f"<RoutedNetwork {self.switch.removesuffix('-rt')} {state}>"

    def run_router(self, argv: Sequence[str], **popen_kwargs: Any) -> subprocess.Popen[Any]:
        """Start a program inside the router namespace (``temoto router``, ``zenohd``).

        Args:
            argv: The program and its arguments.
            **popen_kwargs: As for :meth:`RobotNetwork.run`.

        Returns:
            The process (its own process group; :meth:`close` stops it).

        Raises:
            ValueError: ``start_new_session=False`` was asked for.
            NetworkSetupError: The network is closed.
        """
        return self._run_in(self.switch, argv, **popen_kwargs)

    def loss(self, robot: int | str, percent: float) -> None:
        """Drop a percentage of every IPv4 packet on a robot's link, both ways.

        Installs (or replaces) the nftables table ``inet temoto_loss`` in the robot's namespace
        (input hook, packets arriving on ``veth0``) and ``inet temoto_loss_p<i>`` in the router
        namespace (input and forward hooks, packets arriving on ``p<i>``), each with the rule
        ``meta nfproto ipv4 numgen random mod 100 < N counter drop``. Percent 0 removes them.

        Args:
            robot: The robot's index or namespace.
            percent: 0 to 100, rounded to a whole percent.

        Raises:
            ValueError: Percent out of range.
            NetworkSetupError: ``nft`` is missing or failed.
        """
        if not 0 <= percent <= 100:
            raise ValueError(f"loss must be 0..100 %, not {percent}")
        i = self._index(robot)
        share = round(percent)
        for ns, table, iface, hooks in (
            (self.robots[i], LOSS_TABLE, ROBOT_IF, ("input",)),
            (self.switch, f"{LOSS_TABLE}_p{i}", f"p{i}", ("input", "forward")),
        ):
            script = [f"table inet {table}", f"delete table inet {table}"]
            if share > 0:
                chance = f" numgen random mod 100 < {share}" if share < 100 else ""
                script.append(f"table inet {table} {{")
                for hook in hooks:
                    script += [
                        f"  chain {hook} {{",
                        f"    type filter hook {hook} priority filter; policy accept;",
                        f'    iifname "{iface}" meta nfproto ipv4{chance} counter drop',
                        "  }",
                    ]
                script.append("}")
            _cmd(["ip", "netns", "exec", ns, "nft", "-f", "-"], "\n".join(script) + "\n")

    def dropped(self, robot: int | str) -> int:
        """How many packets the :meth:`loss` rules of a robot's link have dropped so far.

        Args:
            robot: The robot's index or namespace.

        Returns:
            The sum of the rules' packet counters, both ways (0 without loss rules).
        """
        i = self._index(robot)
        total = 0
        for ns, table in ((self.robots[i], LOSS_TABLE), (self.switch, f"{LOSS_TABLE}_p{i}")):
            out = _cmd(
                ["ip", "netns", "exec", ns, "nft", "list", "table", "inet", table], check=False
            )
            total += sum(int(n) for n in re.findall(r"counter packets (\d+)", out))
        return total
