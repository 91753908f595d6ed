"""Multi-robot tests over a simulated network: one network namespace per `temoto run` actor.

Every actor runs in its own namespace of a :class:`temoto.testing.netns.RobotNetwork` (veth
pairs to a bridge in a "switch" namespace, LCM multicast with ``ttl=1``). The tests cover
upstream's three-actor graph, a fan-out/fan-in graph of our own for 3 to 5 actors, a partition
in the middle of a graph and random loss on every receiving side (nftables). See
``docs/testing-networks.md``.

Needs root and ``ip`` (iproute2); the loss tests also need ``nft`` (nftables). Without root
the tests are skipped; a missing tool skips them too, except under CI (``CI=true``), where it
fails them (``make sysdeps`` installs the tools).

Synchronisation is by reading the processes' output with a deadline (:class:`Actors`), never
by sleeping.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import selectors
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from temoto.testing.netns import (
    LCM_URL,
    RobotNetwork,
    missing_requirements,
    namespaces,
    remove_leftovers,
)

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
GRAPHS = Path(__file__).resolve().parent / "graphs"
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
MULTI = UPSTREAM / "actionengine_test_engine_test_multi_actor.graph.json"
PARTITION = GRAPHS / "netns_partition.graph.json"
LOST_NOTIFICATION = GRAPHS / "netns_lost_notification.graph.json"
SETTLE_S = 1.0  # the engine's settle_timeout (default): an aborted run is done after it
ABC = ["Actor A", "Actor B", "Actor C"]
KEY = "6b" * 32  # a fixed 32-byte fleet key, hex

#: The fleet link's defaults, which `temoto run` does not let us change (temoto/fleet/actors.py).
SILENCE_S = 1.5  # --fleet-silence of the partition test: an actor not heard this long is lost
#: Extra time for process start-up, a noisy two-core machine and CPU load.
MARGIN_S = 3.0

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
]


def require(*, nft: bool = False) -> None:
    """Skip (fail under CI) when a tool the test needs is missing."""
    missing = [m for m in missing_requirements(nft=nft) if m != "root"]
    if not missing:
        return
    message = f"needs {', '.join(missing)} (`make sysdeps` installs them as root)"
    if os.environ.get("CI", "").lower() in ("true", "1"):
        pytest.fail(f"CI: {message}", pytrace=False)
    pytest.skip(message)


@pytest.fixture(autouse=True, scope="module")
def _no_leftover_namespaces() -> Iterator[None]:
    """Remove what a crashed earlier run left; check that this module leaves nothing."""
    if os.geteuid() == 0 and not missing_requirements():
        remove_leftovers()
    yield
    if os.geteuid() == 0 and not missing_requirements():
        ours = [ns for ns in namespaces() if f"-{os.getpid()}-" in ns]
        assert not ours, f"namespaces left behind: {ours}"


@pytest.fixture
def key_file(tmp_path: Path) -> Path:
    path = tmp_path / "fleet.key"
    path.write_text(KEY + "\n")
    return path


# ------------------------------------------------------------------------ processes and output


@dataclass
class Line:
    """One line of output, with the time it was read."""

    t: float
    actor: int
    stream: str  # "out" or "err"
    text: str


@dataclass
class Actors:
    """`temoto run` processes, one per robot, whose output is read as it comes (no threads).

    :meth:`pump` reads every pipe with a selector until a condition holds, every process has
    closed its output, or a deadline passes; the lines keep their arrival times.
    """

    procs: list[subprocess.Popen[bytes]]
    lines: list[Line] = field(default_factory=list)
    exited: dict[int, float] = field(default_factory=dict)  # actor -> when its output closed
    codes: list[int | None] | None = None  # set by finish()
    _sel: selectors.BaseSelector = field(default_factory=selectors.DefaultSelector)
    _partial: dict[tuple[int, str], bytes] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for i, proc in enumerate(self.procs):
            for name, pipe in (("out", proc.stdout), ("err", proc.stderr)):
                assert pipe is not None
                os.set_blocking(pipe.fileno(), False)
                self._sel.register(pipe, selectors.EVENT_READ, (i, name))

    def pump(self, until: Callable[[], bool], deadline: float) -> bool:
        """Read output until ``until()`` holds (True), or all output ended or the deadline
        passed (``until()`` then)."""
        while not until() and self._sel.get_map():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            for key, _ in self._sel.select(min(left, 0.5)):
                i, name = key.data
                data = os.read(key.fd, 65536)
                if not data:
                    self._sel.unregister(key.fileobj)
                    if not any(k.data[0] == i for k in self._sel.get_map().values()):
                        self.exited[i] = time.monotonic()
                    data = b"\n" if self._partial.get((i, name)) else b""
                buf = self._partial.pop((i, name), b"") + data
                *complete, rest = buf.split(b"\n")
                if rest:
                    self._partial[(i, name)] = rest
                now = time.monotonic()
                for raw in complete:
                    self.lines.append(Line(now, i, name, raw.decode(errors="replace")))
        return until()

    def finish(self, deadline: float) -> list[int | None]:
        """Read until every process has ended (or the deadline), then reap them (once).

        Returns:
            The exit codes (None: still running at the deadline; it is killed by the
            network's cleanup, and the caller should fail).
        """
        if self.codes is not None:
            return self.codes
        self.pump(lambda: False, deadline)
        codes: list[int | None] = []
        for proc in self.procs:
            try:
                codes.append(proc.wait(timeout=max(0.01, deadline - time.monotonic())))
            except subprocess.TimeoutExpired:
                codes.append(None)
        self._sel.close()
        for proc in self.procs:
            for pipe in (proc.stdout, proc.stderr):
                if pipe is not None:
                    pipe.close()
        self.codes = codes
        return codes

    def text(self, actor: int, stream: str | None = None) -> str:
        return "\n".join(
            ln.text
            for ln in self.lines
            if ln.actor == actor and (stream is None or ln.stream == stream)
        )

    def first(self, actor: int, pattern: str) -> Line | None:
        rx = re.compile(pattern)
        return next((ln for ln in self.lines if ln.actor == actor and rx.search(ln.text)), None)


def start_actors(
    net: RobotNetwork,
    graph: Path,
    actors: Sequence[str],
    key_file: Path,
    *extra: str,
    timeout: float = 15.0,
    url: str | Sequence[str] = LCM_URL,
) -> Actors:
    """Start `temoto run GRAPH --actor A` for every actor, actor ``i`` on robot ``i``.

    ``url`` is the fleet URL of every actor, or one per actor.
    """
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    command = [sys.executable, "-m", "temoto", "run", str(graph), "--actions", str(ACTIONS)]
    urls = [url] * len(actors) if isinstance(url, str) else list(url)
    options = ["--fleet-key-file", str(key_file), "--timeout", str(timeout), *extra]
    procs = [
        net.run(
            i,
            [*command, "--actor", actor, "--fleet-url", urls[i], *options],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            env=env,
        )
        for i, actor in enumerate(actors)
    ]
    return Actors(procs)


def describe(actors: Actors, names: Sequence[str]) -> str:
    return "\n".join(f"--- {n}:\n{actors.text(i)[-1500:]}" for i, n in enumerate(names))


def assert_all_on_true(
    actors: Actors, names: Sequence[str], graph_name: str, deadline: float
) -> None:
    """Every actor exits 0 with the graph on_true."""
    codes = actors.finish(deadline)
    assert None not in codes, f"hung: exit codes {codes}\n{describe(actors, names)}"
    assert codes == [0] * len(names), f"exit codes {codes}\n{describe(actors, names)}"
    for i, name in enumerate(names):
        assert f"{graph_name}: on_true" in actors.text(i, "out"), (name, actors.text(i))


# ---------------------------------------------------------------------- the network on its own

# Joins LCM's group, says "ready", counts datagrams until it has `want` or `window` s passed.
RECEIVER = r"""
import socket, struct, sys, time
group, port, want, window = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("", port))
mreq = struct.pack("4s4s", socket.inet_aton(group), socket.inet_aton("0.0.0.0"))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
print("ready", flush=True)
n, end = 0, time.monotonic() + window
while n < want and (left := end - time.monotonic()) > 0:
    s.settimeout(left)
    try:
        s.recv(100)
        n += 1
    except socket.timeout:
        break
print("count", n, flush=True)
"""
# Sends a datagram every 2 ms (ttl=1, like LCM_URL) until killed or `count` were sent.
SENDER = r"""
import socket, sys, time
group, port, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
for i in range(count):
    s.sendto(b"ping %d" % i, (group, port))
    time.sleep(0.002)
"""
GROUP, PORT = "239.255.76.67", 7667


def receive(
    net: RobotNetwork, sender: int, receivers: Sequence[int], want: int, window: float
) -> list[int]:
    """Datagrams each receiver got from ``sender`` (at most ``want``, within ``window`` s)."""
    procs = [
        net.run(
            r,
            [sys.executable, "-c", RECEIVER, GROUP, str(PORT), str(want), str(window)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for r in receivers
    ]
    watch = Actors(procs)
    deadline = time.monotonic() + 10
    assert watch.pump(lambda: all(watch.first(i, "^ready$") for i in range(len(procs))), deadline)
    send = net.run(
        sender,
        [sys.executable, "-c", SENDER, GROUP, str(PORT), "5000"],
        stdout=subprocess.DEVNULL,
    )
    try:
        codes = watch.finish(deadline + window)
    finally:
        send.kill()
        send.wait()
    assert codes == [0] * len(procs), [watch.text(i) for i in range(len(procs))]
    counts = []
    for i in range(len(procs)):
        line = watch.first(i, r"^count \d+$")
        assert line is not None, watch.text(i)
        counts.append(int(line.text.split()[1]))
    return counts


def test_multicast_crosses_the_switch_and_faults_apply() -> None:
    require(nft=True)
    with RobotNetwork(3) as net:
        # ttl=1 multicast from robot 0 reaches both other robots through the bridge
        assert receive(net, 0, [1, 2], want=20, window=5) == [20, 20]
        # robot 1 cut off: it hears nothing, robot 2 still does
        net.partition(1)
        got = receive(net, 0, [1, 2], want=20, window=0.5)
        assert got == [0, 20]
        net.heal(1)
        assert receive(net, 0, [1], want=20, window=5) == [20]
        # all multicast dropped on robot 2's receiving side, and counted
        net.loss(2, 100)
        assert receive(net, 0, [1, 2], want=20, window=0.5) == [20, 0]
        assert net.dropped(2) > 0
        net.loss(2, 0)
        assert net.dropped(2) == 0
        assert receive(net, 0, [2], want=20, window=5) == [20]


def test_everything_is_removed_even_after_an_exception() -> None:
    require()
    made: list[str] = []
    started: list[subprocess.Popen[bytes]] = []

    def fail_inside() -> None:
        with RobotNetwork(2) as net:
            made.extend([*net.robots, net.switch])
            started.append(net.run(1, [sys.executable, "-c", "import time; time.sleep(60)"]))
            assert set(made) <= set(namespaces())
            raise RuntimeError("deliberate")

    with pytest.raises(RuntimeError, match="deliberate"):
        fail_inside()
    assert started[0].returncode is not None  # killed and reaped
    assert not set(made) & set(namespaces())


def test_remove_leftovers_takes_only_namespaces_of_dead_owners() -> None:
    require()
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a pid that no longer runs: the owner of a "crashed" run
    stale = f"temoto-net-{gone.pid}-0-r0"
    subprocess.run(["ip", "netns", "add", stale], check=True)
    with RobotNetwork(1) as net:
        removed = remove_leftovers()
        assert stale in removed
        assert stale not in namespaces()
        assert net.robots[0] in namespaces()  # a live owner's namespace stays


# ------------------------------------------------------------------------------ fleet over it


#: Zenoh in peer mode on the switched LAN: the peers find each other by multicast scouting.
ZENOH_PEER_URL = "zenoh:"
needs_zenoh = pytest.mark.skipif(
    importlib.util.find_spec("zenoh") is None, reason="the zenoh extra is not installed"
)


@pytest.mark.parametrize(
    "url",
    [pytest.param(LCM_URL, id="lcm"), pytest.param(ZENOH_PEER_URL, id="zenoh", marks=needs_zenoh)],
)
def test_upstream_three_actor_graph_one_namespace_each(key_file: Path, url: str) -> None:
    require()
    with RobotNetwork(3) as net:
        actors = start_actors(net, MULTI, ABC, key_file, url=url)
        assert_all_on_true(actors, ABC, "engine_test_multi_actor", time.monotonic() + 25)


def fan_graph(n: int) -> dict[str, Any]:
    """A graph for robots ``Robot 0`` .. ``Robot n-1`` with hops between robots at every step.

    ``TaRelayString_0`` ("mission", Robot 0) fans out to ``TaAddString_k`` on Robot k
    ("mission and leg k"), each relayed by ``TaRelayString_k`` on another robot and checked by
    ``TaCompareString_k`` on Robot 0; the checks join in ``TaRelayString_n`` on the last robot
    (a false check is bypassed to the exit), whose output ``TaCompareString_0`` on Robot 1
    checks. The graph ends on_true iff every value arrived intact everywhere.
    """
    robots = [f"Robot {i}" for i in range(n)]
    actions: dict[str, dict[str, Any]] = {}

    def action(
        name: str, inst: int, robot: int, inputs: dict[str, str | None], out: str | None
    ) -> str:
        key = f"{name}_{inst}"
        actions[key] = {
            "name": name,
            "actor": robots[robot],
            "instance_id": inst,
            "type": "sync",
            "input_parameters": {
                p: {"pvf_type": "string"} | ({"pvf_value": v} if v is not None else {})
                for p, v in inputs.items()
            },
            "output_parameters": {out: {"pvf_type": "string"}} if out else {},
            "parents": [],
            "children": [],
        }
        return key

    def edge(parent: str, child: str, remap: tuple[str, str] | None, conditions: list[str]) -> None:
        p, c = actions[parent], actions[child]
        down: dict[str, Any] = {"name": c["name"], "instance_id": c["instance_id"]}
        if remap:
            down["remap"] = [{"from": remap[0], "to": remap[1]}]
        p["children"].append(down)
        up = {"name": p["name"], "instance_id": p["instance_id"], "required": True}
        c["parents"].append(up | {"conditions": ["on_true -> run", *conditions]})

    bypass_false = ["on_false -> bypass", "on_error -> bypass"]
    start = action("TaRelayString", 0, 0, {"string_in": "mission"}, "string_out")
    join = action("TaRelayString", n, n - 1, {"string_in": "all legs checked"}, "string_out")
    for k in range(1, n):
        add = action("TaAddString", k, k, {"str_a": None, "str_b": f"leg {k}"}, "result")
        relay = action("TaRelayString", k, k % (n - 1) + 1, {"string_in": None}, "string_out")
        check = action(
            "TaCompareString", k, 0, {"str_a": None, "str_b": f"mission and leg {k}"}, None
        )
        edge(start, add, ("string_out", "str_a"), bypass_false)
        edge(add, relay, ("result", "string_in"), bypass_false)
        edge(relay, check, ("string_out", "str_a"), bypass_false)
        edge(check, join, None, bypass_false)
    final = action("TaCompareString", 0, 1, {"str_a": None, "str_b": "all legs checked"}, None)
    edge(join, final, ("string_out", "str_a"), bypass_false)
    for a in actions.values():
        for side in ("parents", "children", "output_parameters"):
            if not a[side]:
                del a[side]
    return {
        "graph_name": f"netns_fan_{n}",
        "graph_description": f"fan-out/fan-in across {n} robots (tests/fleet/test_netns_fleet.py)",
        "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
        "graph_exit": [{"name": "TaCompareString", "instance_id": 0}],
        "actions": list(actions.values()),
    }


@pytest.mark.parametrize(
    ("n", "url"),
    [
        pytest.param(3, LCM_URL, id="3-lcm"),
        pytest.param(4, LCM_URL, id="4-lcm"),
        pytest.param(5, LCM_URL, id="5-lcm"),
        pytest.param(5, ZENOH_PEER_URL, id="5-zenoh", marks=needs_zenoh),
    ],
)
def test_fan_out_fan_in_graph_across_robots(
    n: int, url: str, tmp_path: Path, key_file: Path
) -> None:
    require()
    graph = tmp_path / f"netns_fan_{n}.graph.json"
    graph.write_text(json.dumps(fan_graph(n), indent=2))
    robots = [f"Robot {i}" for i in range(n)]
    with RobotNetwork(n) as net:
        actors = start_actors(net, graph, robots, key_file, url=url)
        assert_all_on_true(actors, robots, f"netns_fan_{n}", time.monotonic() + 25)


def test_a_partition_fails_the_graph_on_every_actor(key_file: Path) -> None:
    require()
    cut = 1  # Actor B
    with RobotNetwork(3) as net:
        actors = start_actors(
            net,
            PARTITION,
            ABC,
            key_file,
            "--progress",
            "--fleet-silence",
            str(SILENCE_S),
            timeout=15,
        )
        # every actor is past the handshake and runs its timer: cut B off in the middle
        running = [rf"netns_partition: TaTimer_{i} RUNNING" for i in range(3)]
        started = actors.pump(
            lambda: all(actors.first(i, running[i]) for i in range(3)), time.monotonic() + 15
        )
        assert started, f"the timers did not all start\n{describe(actors, ABC)}"
        t_cut = time.monotonic()
        net.partition(cut)
        codes = actors.finish(t_cut + SILENCE_S + 2 * MARGIN_S)
    report = describe(actors, ABC)
    assert None not in codes, f"hung: exit codes {codes}\n{report}"
    assert codes == [1, 1, 1], f"exit codes {codes}\n{report}"
    # One outcome: every actor aborts the run with the same reason, whether it found a peer
    # silent itself or heard the abort of a peer on its side of the cut first (B is alone on
    # its side: it finds both silent). Each actor's own finding names whom it misses.
    aborted = "netns_partition aborted: an actor was lost (not heard for"
    missed = r"netns_partition: actor '(Actor [ABC])' was lost \(not heard for"
    named_b = False
    for i, name in enumerate(ABC):
        line = actors.first(i, re.escape(aborted))
        assert line is not None, f"{name} did not abort the run\n{report}"
        own = actors.first(i, missed)
        if own is not None:
            found = re.search(missed, own.text)
            assert found is not None
            assert found.group(1) != name, own.text
            named_b = named_b or (i != cut and found.group(1) == ABC[cut])
        assert "netns_partition: on_error" in actors.text(i, "out"), (name, report)
        detected, ended = line.t - t_cut, actors.exited[i] - t_cut
        print(f"{name}: aborted {detected:.2f} s, exited {ended:.2f} s after the cut")
        assert SILENCE_S - 0.5 < detected < SILENCE_S + MARGIN_S, (name, detected)
        # a notification for a lost actor is not waited for: the run ends at once (after the
        # engine's settle_timeout, 1 s by default)
        assert ended < SILENCE_S + 1.0 + MARGIN_S, (name, ended)
    assert named_b, f"no survivor found the partitioned actor silent\n{report}"


def aborted_with(actors: Actors, i: int, graph: str) -> str | None:
    """The reason actor ``i`` aborted ``graph`` with, from its log, or None."""
    line = actors.first(i, rf"shared run {graph} aborted: ")
    return None if line is None else line.text.split(f"shared run {graph} aborted: ", 1)[1]


def test_an_actor_killed_mid_run_aborts_the_run_on_every_other(key_file: Path) -> None:
    require()
    killed = 1  # Actor B
    with RobotNetwork(3) as net:
        actors = start_actors(
            net, PARTITION, ABC, key_file, "--progress", "--fleet-silence", str(SILENCE_S)
        )
        running = [rf"netns_partition: TaTimer_{i} RUNNING" for i in range(3)]
        started = actors.pump(
            lambda: all(actors.first(i, running[i]) for i in range(3)), time.monotonic() + 15
        )
        assert started, f"the timers did not all start\n{describe(actors, ABC)}"
        t_kill = time.monotonic()
        actors.procs[killed].kill()  # SIGKILL: no LEAVE, no END, nothing
        codes = actors.finish(t_kill + SILENCE_S + SETTLE_S + 2 * MARGIN_S)
    report = describe(actors, ABC)
    assert codes[killed] == -9, report
    survivors = [i for i in range(3) if i != killed]
    assert [codes[i] for i in survivors] == [1, 1], f"exit codes {codes}\n{report}"
    reasons = {aborted_with(actors, i, "netns_partition") for i in survivors}
    assert reasons == {f"an actor was lost (not heard for {SILENCE_S:g} s)"}, report
    for i in survivors:
        ended = actors.exited[i] - t_kill
        print(f"{ABC[i]}: exited {ended:.2f} s after the kill")
        assert ended < SILENCE_S + SETTLE_S + MARGIN_S, (ABC[i], ended)


def test_a_notification_lost_on_purpose_aborts_the_run_everywhere(key_file: Path) -> None:
    require(nft=True)
    deaf = 2  # Actor C hears nothing for a while: it never acknowledges A's notification
    silence = 9.0  # longer than the notify timeout (5 s): C is still in the run when it hears
    with RobotNetwork(3) as net:
        actors = start_actors(
            net,
            LOST_NOTIFICATION,
            ABC,
            key_file,
            "--progress",
            "--fleet-silence",
            str(silence),
            timeout=40,
        )
        running = [rf"netns_lost_notification: TaTimer_{i} RUNNING" for i in range(3)]
        started = actors.pump(
            lambda: all(actors.first(i, running[i]) for i in range(3)), time.monotonic() + 15
        )
        assert started, f"the timers did not all start\n{describe(actors, ABC)}"
        t_deaf = time.monotonic()
        net.loss(deaf, 100)
        # A's timer ends after 1 s; C does not acknowledge; A aborts 5 s later
        aborted = actors.pump(
            lambda: aborted_with(actors, 0, "netns_lost_notification") is not None,
            t_deaf + 15,
        )
        assert aborted, f"A did not abort the run\n{describe(actors, ABC)}"
        net.loss(deaf, 0)  # C hears again, before it would find A and B silent
        codes = actors.finish(time.monotonic() + silence + MARGIN_S)
    report = describe(actors, ABC)
    assert codes == [1, 1, 1], f"exit codes {codes}\n{report}"
    reasons = {aborted_with(actors, i, "netns_lost_notification") for i in range(3)}
    assert len(reasons) == 1, report
    (reason,) = reasons
    assert reason is not None
    assert "TaTimer_0 (on_true)" in reason, reason
    assert "was not acknowledged by 'Actor C'" in reason, reason
    for i in range(3):
        print(f"{ABC[i]}: exited {actors.exited[i] - t_deaf:.2f} s after C went deaf")


def test_random_loss_on_every_robot_is_survived(key_file: Path) -> None:
    require(nft=True)
    with RobotNetwork(3) as net:
        for robot in range(3):
            net.loss(robot, 25)
        t0 = time.monotonic()
        actors = start_actors(net, MULTI, ABC, key_file)
        actors.finish(t0 + 25)
        took = max(actors.exited.values(), default=t0) - t0
        dropped = [net.dropped(r) for r in range(3)]
    print(f"loss 25 %: all ended {took:.2f} s after the start; dropped {dropped}")
    assert sum(dropped) > 0, "the loss rules dropped nothing"
    assert_all_on_true(actors, ABC, "engine_test_multi_actor", t0)  # all ended by now
    assert took < 10.0, took
