"""ResourceInfoSync: adverts, discovery, requests, withdrawal, lost robots, bad messages."""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any, ClassVar

import pytest
from _ris_helpers import WAIT_S, Fleet, Got

from temoto.clock import ManualClock
from temoto.core.registrar import LoadContext, Registrar, ResourceServer
from temoto.fleet.ris import RIS_CHANNEL, RIS_STATS, ResourceInfoSync, RobotInfo
from temoto.lcm_types import handshake_t, ris_advert_t, ris_request_t, ris_server_t, ris_withdraw_t
from temoto.transport import codec
from temoto.transport.inprocess import live_buses

_buses = itertools.count()


@pytest.fixture
def fleet(request: pytest.FixtureRequest) -> Iterator[Fleet]:
    bus = f"ris-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:
        yield Fleet(bus, stack)
    assert bus not in live_buses()


@dataclass(frozen=True)
class CamReq:
    name: str


@dataclass(frozen=True)
class CamResp:
    ok: bool


class Cameras(ResourceServer[CamReq, CamResp]):
    name: ClassVar[str] = "camera"
    request_type: ClassVar[type[Any]] = CamReq
    response_type: ClassVar[type[Any]] = CamResp

    def on_load(self, request: CamReq, ctx: LoadContext) -> CamResp:
        return CamResp(True)

    def on_unload(self, request: CamReq, response: CamResp) -> None:
        pass


class Lidars(Cameras):
    name: ClassVar[str] = "lidar"


def advert(
    robot: str, *servers: str, seq: int = 1, period_ms: int = 100, manager: str | None = None
) -> Any:
    msg = ris_advert_t()
    msg.manager = robot if manager is None else manager
    msg.robot, msg.seq, msg.period_ms = robot, seq, period_ms
    msg.servers = []
    for name in servers:
        item = ris_server_t()
        item.name, item.request_type, item.offer = name, "x:Y", ""
        msg.servers.append(item)
    return msg


def wait_known(ris: ResourceInfoSync, robot: str, timeout: float = WAIT_S) -> RobotInfo:
    got = Got()
    cancel = ris.subscribe(on_joined=got)
    try:
        info = ris.robot_info(robot)
        if info is None:
            got.wait_until(lambda calls: any(c[0].robot == robot for c in calls), timeout)
            info = ris.robot_info(robot)
        assert info is not None
        return info
    finally:
        cancel()


# ================================================================ adverts and discovery


def test_robots_discover_each_others_servers(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    b = fleet.robot("B", period_s=60.0)
    info = wait_known(b.ris, "A")
    assert (info.manager, info.servers, info.period_s) == ("A", {}, 60.0)
    got = Got()
    b.ris.subscribe(on_joined=got)
    # a server registered after the RIS started is advertised at the next advert
    a.registrar.register(Cameras())
    wait_providers(b.ris, "camera", ["A"], refresh=a.ris)
    info = b.ris.robot_info("A")
    assert info is not None
    assert info.servers["camera"].request_type == f"{__name__}:CamReq"
    # the proxy server "remote" is never advertised; a robot does not list itself
    assert "remote" not in info.servers
    assert [r.robot for r in b.ris.robots()] == ["A"]
    assert [r.robot for r in wait_all(a.ris, ["B"])] == ["B"]
    assert b.ris.robot_info("B") is None
    assert b.ris.providers("lidar") == []
    assert b.ris.by_manager("A") is not None
    assert got.calls == []  # A was known already: no second "joined"


def wait_providers(
    ris: ResourceInfoSync, server: str, robots: list[str], refresh: ResourceInfoSync | None = None
) -> None:
    """Wait for ``ris`` to see ``robots`` as the providers of ``server`` (RIS events)."""
    events = Got()
    cancel = ris.subscribe(on_joined=events, on_changed=events, on_lost=events)
    try:
        if refresh is not None:
            refresh.refresh()
        events.wait_until(lambda _: ris.providers(server) == robots)
    finally:
        cancel()


def wait_all(ris: ResourceInfoSync, robots: list[str]) -> list[RobotInfo]:
    for robot in robots:
        wait_known(ris, robot)
    return ris.robots()


def test_share_limits_what_is_advertised(fleet: Fleet) -> None:
    a = fleet.robot("A", share=["lidar", "nothing"])
    a.registrar.register(Cameras())
    a.registrar.register(Lidars())
    assert [s.name for s in a.ris.offered()] == ["lidar"]
    b = fleet.robot("B")
    assert set(wait_known(b.ris, "A").servers) == {"lidar"}


def test_a_joining_robot_learns_the_fleet_at_once_not_after_a_period(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    a.registrar.register(Cameras())
    raw = fleet.raw("watcher", RIS_CHANNEL)
    # A has advertised at start already; only an answer to a request brings another advert
    ask = ris_request_t()
    ask.requester, ask.manager = "watcher", ""
    raw.send(ask)
    (answer,) = raw.wait_type("ris_advert_t")
    assert (answer.robot, answer.manager, answer.period_ms) == ("A", "A", 60_000)
    assert [s.name for s in answer.servers] == ["camera"]
    assert a.ris.stats["requests_received"] == 1
    # a new robot asks at start: it knows A long before A's next periodic advert
    b = fleet.robot("B", period_s=60.0)
    t0 = time.monotonic()
    wait_known(b.ris, "A", timeout=WAIT_S)
    assert time.monotonic() - t0 < 10.0
    # a request for another manager is not answered; each request for A is (at once, or up
    # to 50 ms later if an answer just went out: requests meanwhile share that answer, so each
    # is sent once the answer before it came)
    seen = len(raw.decoded("ris_advert_t"))
    ask.manager = "someone-else"
    raw.send(ask)
    ask.manager = "A"
    raw.send(ask)  # ...but this one is
    raw.wait_type("ris_advert_t", count=seen + 1)
    raw.send(ask)  # and so is this one, a little later (one answer per 50 ms at most)
    raw.wait_type("ris_advert_t", count=seen + 2)
    assert len(raw.decoded("ris_advert_t")) == seen + 2  # someone-else's got none


def test_a_robot_that_closes_withdraws_and_is_lost_at_once(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    with ExitStack() as b_stack:
        b = fleet.robot("B", period_s=60.0, stack=b_stack)
        b.registrar.register(Cameras())
        b.ris.refresh()
        wait_known(a.ris, "B")
        lost = Got()
        a.ris.subscribe(on_lost=lost)
    (info, reason), *_ = lost.wait_for(1)
    assert (info.robot, reason) == ("B", "withdrew")
    assert a.ris.robots() == []
    assert a.ris.stats["lost"] == 1


def test_withdrawing_servers_removes_them_for_good(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    a.registrar.register(Cameras())
    a.registrar.register(Lidars())
    b = fleet.robot("B", period_s=60.0)
    wait_providers(b.ris, "camera", ["A"])
    a.ris.withdraw(["camera"])
    wait_providers(b.ris, "camera", [])
    raw = fleet.raw("watcher", RIS_CHANNEL)
    a.ris.refresh()  # the next adverts leave it out
    (msg, *_) = raw.wait_type("ris_advert_t")
    assert [s.name for s in msg.servers] == ["lidar"]
    assert b.ris.providers("camera") == []
    assert b.ris.providers("lidar") == ["A"]
    with pytest.raises(ValueError, match="at least one"):
        a.ris.withdraw([])


# ================================================================ lost robots


def test_a_silent_robot_is_lost_after_missed_periods_and_joins_again(fleet: Fleet) -> None:
    a = fleet.robot("A", missed=3)
    lost, joined = Got(), Got()
    a.ris.subscribe(on_lost=lost, on_joined=joined)
    raw = fleet.raw("ghost", RIS_CHANNEL)
    raw.send(advert("ghost", "camera", period_ms=50))
    t0 = time.monotonic()
    joined.wait_for(1)
    ((info, reason),) = lost.wait_for(1)
    elapsed = time.monotonic() - t0
    assert info.robot == "ghost"
    assert reason == "no adverts for 3 periods"
    assert elapsed >= 0.15 - 0.02  # its own period (50 ms) times missed, not A's (100 ms)
    assert a.ris.providers("camera") == []
    assert lost.threads == ["temoto-fleet-ris-calls"]
    raw.send(advert("ghost", "camera", seq=2, period_ms=50))
    joined.wait_for(2)
    assert a.ris.stats["joined"] == 2
    assert a.ris.stats["lost"] >= 1


def test_a_robot_that_keeps_advertising_is_never_lost(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=0.05, missed=10)
    b = fleet.robot("B", period_s=0.05, missed=10)
    lost = Got()
    a.ris.subscribe(on_lost=lost)
    b.ris.subscribe(on_lost=lost)
    wait_known(a.ris, "B")
    wait_known(b.ris, "A")
    assert lost.quiet_for(1, 1.0)  # 20 periods: each would have been lost after 10 silent ones
    assert b.ris.stats["adverts_received"] >= 5


def test_silences_are_measured_on_the_injected_clock(fleet: Fleet) -> None:
    clock = ManualClock(start=1000.0)
    registrar = Registrar("A")
    fleet.stack.callback(registrar.close)
    ris = fleet.stack.enter_context(
        ResourceInfoSync(fleet.link("A"), registrar, "A", period_s=3600.0, clock=clock)
    )
    lost = Got()
    ris.subscribe(on_lost=lost)
    raw = fleet.raw("ghost", RIS_CHANNEL)
    raw.send(advert("ghost", period_ms=1000))
    wait_known(ris, "ghost")
    clock.advance(2.9)
    ris.refresh()  # an advert: the timer has looked at the silences after the advance
    raw.wait_type("ris_advert_t")
    assert lost.calls == []
    clock.advance(0.2)  # wakes the timer, which waits on the clock: no refresh needed
    ((info, reason),) = lost.wait_for(1)
    assert info.robot == "ghost"
    assert reason == "no adverts for 3 periods"


def test_a_plain_function_is_refused_as_a_clock(fleet: Fleet) -> None:
    registrar = Registrar("A")
    fleet.stack.callback(registrar.close)
    with pytest.raises(TypeError, match=r"temoto\.clock\.Clock.*MonotonicClock"):
        ResourceInfoSync(fleet.link("A"), registrar, "A", clock=time.monotonic)  # type: ignore[arg-type]


# ================================================================ bad messages


def introduced(a: Any, raw: Any, name: str, *servers: str) -> None:
    """``raw`` (speaking as ``name``) adverts once and A takes it: A holds its session key.

    A burst sent before A holds a new sender's session key reaches A only through resends (the
    newest 256 at most), not in the order it was sent: the tests that count what A made of a
    sequence of messages introduce their senders first.
    """
    raw.send(advert(name, *servers))
    deadline = time.monotonic() + WAIT_S
    while a.ris.robot_info(name) is None:
        assert time.monotonic() < deadline, f"{name}'s advert was not taken: {a.link.stats}"
        time.sleep(0.01)


def test_bad_messages_are_counted_and_dropped_never_raised(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    raw = fleet.raw("mallory", RIS_CHANNEL)
    m = fleet.raw("m", RIS_CHANNEL)  # a robot's adverts name that robot (docs/security.md)
    introduced(a, raw, "mallory")
    introduced(a, m, "m")
    joined = Got()
    a.ris.subscribe(on_joined=joined)
    before = a.ris.stats
    # garbage that is not an envelope: the authentication drops it
    fleet.link("noise").transport.publish(RIS_CHANNEL, b"\x00garbage")
    # sealed, but not a RIS message / not decodable / another version
    hs = handshake_t()
    hs.graph = hs.session = hs.actor = "x"
    hs.actors, hs.heard = "", b""
    raw.send(hs)
    raw.send_raw("nonsense_t", b"abc")
    raw.send_raw("ris_advert_t", b"\x01\x02")
    bad_version = advert("mallory")
    codec.encode(bad_version)
    bad_version.version = 99
    raw.send_raw("ris_advert_t", bad_version.encode())
    # decodable, but invalid: own robot name, empty names, no period, duplicate servers
    raw.send(advert(""))
    m.send(advert("m", manager=""))
    m.send(advert("m", period_ms=0))
    m.send(advert("m", "camera", "camera"))
    request = ris_request_t()
    request.requester, request.manager = "", ""
    raw.send(request)
    # naming another robot than the sender: mallory speaking as A
    raw.send(advert("A"))
    withdraw = ris_withdraw_t()
    withdraw.manager, withdraw.robot, withdraw.servers = "A", "A", []
    raw.send(withdraw)
    # a good advert, then an older one (stale)
    m.send(advert("m", "camera", seq=10))
    m.send(advert("m", seq=9))
    fleet.raw("zz-marker", RIS_CHANNEL).send(advert("zz-marker"))
    joined.wait_until(lambda calls: any(c[0].robot == "zz-marker" for c in calls))
    deadline = time.monotonic() + WAIT_S  # three senders: their messages may cross
    while time.monotonic() < deadline and (a.ris.stats["stale"] < 1 or a.ris.stats["impostor"] < 2):
        time.sleep(0.01)
    stats = a.ris.stats
    assert stats["decode_errors"] - before["decode_errors"] == 3
    assert stats["unexpected"] - before["unexpected"] == 6
    assert stats["impostor"] == 2
    assert stats["stale"] == 1
    assert a.link.stats["garbage"] >= 1
    assert a.link.stats["handler_error"] == 0
    assert a.ris.providers("camera") == ["m"]  # the stale advert did not replace the good one
    assert a.ris.robot_info("A") is None
    assert set(stats) == set(RIS_STATS)


def test_random_payloads_never_reach_a_handler_error(fleet: Fleet) -> None:
    a = fleet.robot("A", period_s=60.0)
    raw = fleet.raw("f", RIS_CHANNEL)  # its adverts name it: they reach the RIS's checks
    rng = random.Random(5)
    good = codec.encode(advert("f", "camera"))[1]
    introduced(a, raw, "f", "camera")
    for i in range(300):
        kind = rng.choice(["ris_advert_t", "ris_request_t", "ris_withdraw_t"])
        if i % 2:
            payload = bytes(rng.randrange(256) for _ in range(rng.randrange(60)))
        else:  # flip bytes of a valid advert: may still decode, with odd fields
            data = bytearray(good)
            for _ in range(rng.randrange(1, 4)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            payload, kind = bytes(data), "ris_advert_t"
        raw.send_raw(kind, payload)
    marker = advert("f", "zz-marker")
    marker.boot = "a-new-boot"  # taken whatever the fuzz left of f
    raw.send(marker)
    deadline = time.monotonic() + WAIT_S
    while a.ris.providers("zz-marker") != ["f"]:
        assert time.monotonic() < deadline, (
            f"the marker advert was not taken: {a.ris.stats} {a.link.stats}"
        )
        time.sleep(0.01)
    assert a.link.stats["handler_error"] == 0
    assert a.ris.stats["decode_errors"] > 0


def test_arguments_are_checked(fleet: Fleet) -> None:
    registrar = Registrar("A")
    fleet.stack.callback(registrar.close)
    link = fleet.link("A")
    with pytest.raises(ValueError, match="robot"):
        ResourceInfoSync(link, registrar, "")
    with pytest.raises(ValueError, match="period_s"):
        ResourceInfoSync(link, registrar, "A", period_s=0)
    with pytest.raises(ValueError, match="missed"):
        ResourceInfoSync(link, registrar, "A", missed=0)


def test_a_robot_heard_with_a_new_boot_id_restarted_and_is_lost_and_joined_at_once(
    fleet: Fleet,
) -> None:
    a = fleet.robot("A", period_s=60.0)
    lost, joined = Got(), Got()
    a.ris.subscribe(on_lost=lost, on_joined=joined)
    raw = fleet.raw("m", RIS_CHANNEL)
    first = advert("m", "camera", seq=100)
    first.boot = "boot-1"
    raw.send(first)
    joined.wait_for(1)
    # the same boot id with a lower seq is stale; a new boot id is a new start, whatever its seq
    stale = advert("m", seq=99)
    stale.boot = "boot-1"
    raw.send(stale)
    restarted = advert("m", "lidar", seq=5)
    restarted.boot = "boot-2"
    raw.send(restarted)
    ((info, reason),) = lost.wait_for(1)
    assert (info.robot, info.boot, reason) == ("m", "boot-1", "restarted")
    (_, (again,)) = joined.wait_for(2)
    assert (again.robot, again.boot, again.seq) == ("m", "boot-2", 5)
    assert a.ris.providers("lidar") == ["m"]
    assert a.ris.providers("camera") == []
    assert a.ris.stats["stale"] == 1
    assert a.ris.boot != fleet.robot("B", period_s=60.0).ris.boot


def test_an_advert_heard_after_its_robots_withdraw_does_not_bring_it_back(fleet: Fleet) -> None:
    # a closing robot's last advert can be overtaken by its withdraw: that start stays gone,
    # a new start (a new boot id) joins again
    a = fleet.robot("A", period_s=60.0)
    raw = fleet.raw("M", RIS_CHANNEL)
    joined, lost = Got(), Got()
    a.ris.subscribe(on_joined=joined, on_lost=lost)

    def start(seq: int, boot: str) -> Any:
        msg = advert("M", "camera", seq=seq)
        msg.boot = boot
        return msg

    raw.send(start(1, "boot-1"))
    joined.wait_for(1)
    withdraw = ris_withdraw_t()
    withdraw.manager, withdraw.robot, withdraw.servers = "M", "M", []
    raw.send(withdraw)
    (info, reason), *_ = lost.wait_for(1)
    assert (info.robot, reason) == ("M", "withdrew")
    stale = a.ris.stats["stale"]
    raw.send(start(2, "boot-1"))  # sent before the withdraw, heard after it
    deadline = time.monotonic() + WAIT_S
    while a.ris.stats["stale"] == stale:
        assert time.monotonic() < deadline, "the late advert was not seen"
        time.sleep(0.005)
    assert a.ris.robots() == []
    raw.send(start(1, "boot-2"))  # the robot started again
    joined.wait_for(2)
    assert [r.robot for r in a.ris.robots()] == ["M"]
