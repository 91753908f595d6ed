"""Remote resources: robot A uses processes of robot B through the RIS, on an in-process bus."""

from __future__ import annotations

import itertools
import os
import random
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any, ClassVar

import pytest
from _ris_helpers import WAIT_S, Fleet, Got, Raw, Robot, alive, wait_exit

from temoto.core.registrar import LoadContext, ResourceServer, Status, StatusUpdate
from temoto.errors import (
    NoProviderError,
    RemoteError,
    ResourceLoadError,
    TransportTimeoutError,
)
from temoto.fleet.resources import (
    RESOURCE_CHANNEL,
    RESOURCE_STATS,
    RemoteRequest,
    RemoteResources,
    RemoteResponse,
    remote_request,
    response_of,
)
from temoto.fleet.ris import RIS_CHANNEL
from temoto.lcm_types import (
    resource_release_t,
    resource_reply_t,
    resource_request_t,
    resource_status_t,
    ris_advert_t,
    ris_server_t,
)
from temoto.managers.process import ProcessRequest, ProcessResponse
from temoto.testing import ProcessLeakCheck
from temoto.transport.inprocess import live_buses

_buses = itertools.count()
SLEEPER = ProcessRequest(sys.executable, ("-c", "import time; time.sleep(60)"))
PROCESS_TYPE = "temoto.managers.process:ProcessRequest"


@pytest.fixture(autouse=True)
def no_leaked_processes(monkeypatch: pytest.MonkeyPatch) -> Iterator[ProcessLeakCheck]:
    """Every process a test here starts must be gone when it ends (stragglers are killed)."""
    check = ProcessLeakCheck()
    monkeypatch.setenv(check.variable, check.mark)
    yield check
    leaked = check.kill_leftovers()
    if leaked:
        pytest.fail(f"test left processes running: {leaked}", pytrace=False)


@pytest.fixture
def fleet(request: pytest.FixtureRequest) -> Iterator[Fleet]:
    bus = f"res-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:
        yield Fleet(bus, stack)
    assert bus not in live_buses()


def sleeper(tag: str) -> ProcessRequest:
    """A process that sleeps for a minute; ``tag`` makes requests distinct."""
    return ProcessRequest(sys.executable, ("-c", f"import time; time.sleep(60)  # {tag}"))


def pair(fleet: Fleet, **a_args: Any) -> tuple[Robot, Robot]:
    """Robot A (no servers) and robot B (process manager), each knowing the other."""
    b = fleet.robot("B", processes=True)
    a = fleet.robot("A", **a_args)
    known = Got()
    a.ris.subscribe(on_joined=known)
    if a.ris.providers("process") != ["B"]:
        known.wait_until(lambda _: a.ris.providers("process") == ["B"])
    b_known = Got()
    b.ris.subscribe(on_joined=b_known)
    if b.ris.robot_info("A") is None:
        b_known.wait_until(lambda _: b.ris.robot_info("A") is not None)
    return a, b


def remote(robot: Robot) -> RemoteResources:
    assert robot.remote is not None
    return robot.remote


def fatal(got: Got) -> list[StatusUpdate]:
    calls = got.wait_until(lambda calls: any(c[0].status is Status.FATAL for c in calls))
    return [c[0] for c in calls if c[0].status is Status.FATAL]


# ================================================================ request types


def test_remote_requests_are_canonical_values() -> None:
    one = RemoteRequest("B", "process", '{"b": 1, "a": [1, 2]}')
    two = RemoteRequest("B", "process", '{"a":[1,2],"b":1}')
    assert one == two
    assert one.request_json == '{"a":[1,2],"b":1}'
    built = remote_request("process", SLEEPER, "B")
    assert built.request_type == PROCESS_TYPE
    assert ProcessRequest(**__import__("json").loads(built.request_json)) == SLEEPER
    with pytest.raises(ValueError, match="JSON object"):
        RemoteRequest("B", "process", "[1]")
    with pytest.raises(ValueError, match="not JSON"):
        RemoteRequest("B", "process", "{")
    with pytest.raises(ValueError, match="empty"):
        RemoteRequest("", "process", "{}")
    with pytest.raises(TypeError, match="priority"):
        RemoteRequest("B", "process", "{}", priority="high")  # type: ignore[arg-type]
    response = RemoteResponse(
        "B", "r1", "process:x", '{"pid": 5, "pgid": 5, "start_time": 1, "started_at": 2.0}'
    )
    assert response.decode(ProcessResponse).pid == 5


# ================================================================ the done-when scenario


def test_a_remote_process_crash_reaches_the_consumer_and_a_release_stops_it(
    fleet: Fleet,
) -> None:
    a, b = pair(fleet)
    got = Got()
    crashed = remote(a).request("process", sleeper("crash"), client="me", on_status=got)
    assert crashed.server == "remote"
    pid = response_of(crashed, ProcessResponse).pid
    assert alive(pid)
    ((held_for,),) = [list(remote(b).held().values())]
    assert held_for == "A"
    (ref,) = b.registrar.references()
    assert ref.client.startswith("A/remote:")
    t0 = time.monotonic()
    os.kill(pid, signal.SIGKILL)
    (update,) = fatal(got)
    latency = time.monotonic() - t0
    assert latency < 0.5, f"the crash took {latency * 1e3:.1f} ms to reach A"
    assert update.reference_id == crashed.id
    assert update.message.startswith("robot 'B': ")
    assert "SIGKILL" in update.message
    assert got.threads == ["temoto-fleet-resources-calls"]
    a.registrar.release(crashed.id)

    kept = remote(a).request("process", sleeper("kept"), client="me")
    pid = response_of(kept, ProcessResponse).pid
    a.registrar.release(kept.id)
    assert wait_exit(pid), "releasing on A did not stop the process on B"
    assert a.registrar.resources() == []
    stats = remote(a).stats
    assert stats["requests_sent"] >= 2  # resent if B was slow to answer (a loaded machine)
    assert stats["replies_received"] == 2
    assert stats["releases_sent"] >= 2
    assert set(stats) == set(RESOURCE_STATS)


def test_equal_requests_share_one_remote_reference(fleet: Fleet) -> None:
    a, b = pair(fleet)
    one = remote(a).request("process", SLEEPER, client="c1")
    two = remote(a).request("process", SLEEPER, client="c2")
    assert one.resource_id == two.resource_id
    assert one.id != two.id
    assert len(b.registrar.references()) == 1
    stats = remote(b).stats
    assert stats["requests_received"] - stats["duplicates"] == 1  # resends are not served
    pid = response_of(one, ProcessResponse).pid
    a.registrar.release(one.id)
    assert not wait_exit(pid, 0.3)  # c2 still holds it
    assert len(b.registrar.references()) == 1
    a.registrar.release(two.id)
    assert wait_exit(pid)


class Camera(ResourceServer[str, str]):
    """A local server of robot A whose resource runs its process on robot B."""

    name: ClassVar[str] = "camera"
    request_type: ClassVar[type[Any]] = str
    response_type: ClassVar[type[Any]] = str

    def __init__(self, remote: RemoteResources) -> None:
        self.remote = remote
        self.pids: list[int] = []

    def on_load(self, request: str, ctx: LoadContext) -> str:
        process = self.remote.request("process", sleeper(request))  # a dependency
        self.pids.append(response_of(process, ProcessResponse).pid)
        return f"camera {request}"

    def on_unload(self, request: str, response: str) -> None:
        pass


def test_remote_resources_are_dependencies_released_in_cascade(fleet: Fleet) -> None:
    a, b = pair(fleet)
    camera = Camera(remote(a))
    a.registrar.register(camera)
    got = Got()
    front = a.registrar.call("camera", "front", client="user", on_status=got)
    (proxy,) = a.registrar.dependencies(front.id)
    assert proxy.server == "remote"
    assert proxy.request.robot == "B"
    os.kill(camera.pids[0], signal.SIGKILL)
    (update,) = fatal(got)
    assert update.hops == ("remote", "camera")  # up the chain, as for a local dependency
    assert "robot 'B'" in update.message

    rear = a.registrar.call("camera", "rear", client="user")
    pid = camera.pids[1]
    assert len(b.registrar.references()) == 2
    a.registrar.release(rear.id)  # the camera goes, and its process on B with it
    assert wait_exit(pid)
    a.registrar.release(front.id)
    assert a.registrar.resources() == []


def test_an_action_acquires_a_remote_process_and_hears_its_crash(fleet: Fleet) -> None:
    from temoto import Action, ActionCatalog, ActionEngine, parse_graph, parse_umrf
    from temoto.core.states import Result
    from temoto.errors import ResourceBrokenError

    a, _ = pair(fleet)
    pids: list[int] = []
    seen: list[str] = []
    acquired = threading.Event()

    class UseRemote(Action):
        def on_run(self) -> bool:
            held = self.acquire("remote", remote_request("process", SLEEPER, "B"))
            pids.append(response_of(held, ProcessResponse).pid)
            acquired.set()
            try:
                self.wait_until_stopped(10)
            except ResourceBrokenError as err:
                seen.append(str(err))
                return False
            return True

    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(UseRemote, parse_umrf({"name": "UseRemote", "type": "sync"}))
    graph = parse_graph({"graph_name": "g", "actions": [{"name": "UseRemote", "type": "sync"}]})
    releases = fleet.raw("observer", RESOURCE_CHANNEL)
    with ActionEngine("A", actions=catalog, registrar=a.registrar) as engine:
        engine.start(graph)
        assert acquired.wait(WAIT_S)
        os.kill(pids[0], signal.SIGKILL)
        assert engine.wait("g", WAIT_S) is Result.FALSE
    assert len(seen) == 1
    assert "FATAL: robot 'B': " in seen[0]
    assert a.registrar.resources() == []
    (ack, *_) = [m for m in releases.wait_type("resource_reply_t", 2) if m.message == "released"]
    assert ack.provider == "B"


# ================================================================ lost robots


def test_a_lost_provider_makes_its_resources_fatal(fleet: Fleet) -> None:
    with ExitStack() as b_stack:
        b = fleet.robot("B", processes=True, stack=b_stack)
        a = fleet.robot("A")
        known = Got()
        a.ris.subscribe(on_joined=known)
        if a.ris.robot_info("B") is None:
            known.wait_for(1)
        got = Got()
        held = remote(a).request("process", SLEEPER, client="me", on_status=got)
        b.link.transport.close()  # B falls silent: no adverts, no withdrawal
        t0 = time.monotonic()
        (update,) = fatal(got)
        elapsed = time.monotonic() - t0
        assert update.message == "robot 'B' was lost: no adverts for 3 periods"
        assert elapsed >= 0.2  # B was heard less than a period before it fell silent
        assert remote(a).stats["lost_fatal"] == 1
        assert a.registrar.info(held.id).failed
        a.registrar.release(held.id)  # B is not heard: one try, no resends
    # B closing released what A held there (its process is stopped)
    assert a.registrar.resources() == []


def test_a_lost_consumer_has_its_references_released(fleet: Fleet) -> None:
    b = fleet.robot("B", processes=True)
    with ExitStack() as a_stack:
        a = fleet.robot("A", stack=a_stack)
        known = Got()
        a.ris.subscribe(on_joined=known)
        if a.ris.robot_info("B") is None:
            known.wait_for(1)
        one = remote(a).request("process", sleeper("one"), client="me")
        two = remote(a).request("process", sleeper("two"), client="me")
        pids = [response_of(r, ProcessResponse).pid for r in (one, two)]
        lost = Got()
        b.ris.subscribe(on_lost=lost)
        a.link.transport.close()  # A dies: silent
        ((info, reason),) = lost.wait_for(1)
        assert (info.robot, reason) == ("A", "no adverts for 3 periods")
        for pid in pids:
            assert wait_exit(pid), "B did not stop the process of the lost robot A"
    assert remote(b).held() == {}
    assert remote(b).stats["released_for_lost"] == 2


# ================================================================ errors


def test_an_unknown_server_is_a_typed_error(fleet: Fleet) -> None:
    a, _ = pair(fleet)
    with pytest.raises(NoProviderError, match="no robot offers server 'warp_drive'") as err:
        remote(a).request("warp_drive", SLEEPER)
    assert err.value.server == "warp_drive"
    assert isinstance(err.value, LookupError)
    with pytest.raises(NoProviderError, match="robot 'Z' is not known"):
        remote(a).request("process", SLEEPER, robot="Z")
    with pytest.raises(NoProviderError, match="does not offer server 'camera'"):
        remote(a).request("camera", SLEEPER, robot="B")
    with pytest.raises(NoProviderError, match="this robot"):
        remote(a).request("process", SLEEPER, robot="A")
    # through the registrar, the proxy's load refuses it the same way (chained)
    with pytest.raises(ResourceLoadError, match="does not offer server 'camera'") as chained:
        a.registrar.call("remote", RemoteRequest("B", "camera", "{}"))
    assert isinstance(chained.value.__cause__, NoProviderError)
    with pytest.raises(ResourceLoadError, match=r"takes temoto\.managers\.process:Process"):
        a.registrar.call("remote", RemoteRequest("B", "process", "{}", "my:Type"))
    assert a.registrar.resources() == []


def test_a_refusal_carries_the_providers_message(fleet: Fleet) -> None:
    a, b = pair(fleet)
    bad = ProcessRequest("no-such-program-here")
    with pytest.raises(ResourceLoadError) as err:
        remote(a).request("process", bad)
    text = str(err.value)
    assert "robot 'B' could not serve 'process'" in text
    assert "'no-such-program-here' was not found on PATH" in text
    cause = err.value.__cause__
    assert isinstance(cause, RemoteError)
    chain = []
    link: BaseException | None = cause.__cause__
    while link is not None:
        chain.append(str(link))
        link = link.__cause__
    assert chain[0].startswith("ResourceLoadError: server 'process' could not load")
    assert chain[-1].startswith("ValueError: executable")
    # the JSON of a request B cannot rebuild
    with pytest.raises(ResourceLoadError, match="could not serve 'process'"):
        a.registrar.call("remote", RemoteRequest("B", "process", '{"nope": 1}'))
    assert remote(b).stats["refused"] == 2
    assert b.registrar.resources() == []
    assert a.registrar.resources() == []


# ================================================================ protocol details


def ghost_provider(fleet: Fleet, name: str = "ghost") -> Raw:
    """A hand-driven provider that advertises a "process" server and answers nothing."""
    raw = fleet.raw(name, RESOURCE_CHANNEL)
    advert = ris_advert_t()
    advert.manager, advert.robot, advert.seq, advert.period_ms = name, name, 1, 60_000
    item = ris_server_t()
    item.name, item.request_type, item.offer = "process", PROCESS_TYPE, ""
    advert.servers = [item]
    raw.send(advert, RIS_CHANNEL)
    return raw


def reply_to(request: Any, reference: str, code: int = 1) -> Any:
    reply = resource_reply_t()
    reply.request_id, reply.provider, reply.consumer = (
        request.request_id,
        request.provider,
        request.consumer,
    )
    reply.code, reply.reference_id, reply.resource_id = code, reference, "process:g"
    reply.response = '{"pid": 1, "pgid": 1, "start_time": 1, "started_at": 1.0}'
    return reply


def known(a: Robot, robot: str) -> None:
    got = Got()
    a.ris.subscribe(on_joined=got)
    if a.ris.robot_info(robot) is None:
        got.wait_for(1)


def test_an_unanswered_request_times_out_and_a_late_reply_is_released(fleet: Fleet) -> None:
    a = fleet.robot("A", timeout_s=0.3, resend_s=0.05)
    ghost = ghost_provider(fleet)
    known(a, "ghost")
    with pytest.raises(ResourceLoadError, match="robot 'ghost' did not answer") as err:
        remote(a).request("process", SLEEPER, robot="ghost")
    assert isinstance(err.value.__cause__, TransportTimeoutError)
    requests = ghost.wait_type("resource_request_t", 2)
    assert len({r.request_id for r in requests}) == 1  # resends carry the same id
    assert remote(a).stats["timeouts"] == 1
    # the reply comes after all: A gives the reference back
    ghost.send(reply_to(requests[0], "late-ref"))
    (release,) = ghost.wait_type("resource_release_t")
    assert (release.provider, release.reference_id) == ("ghost", "late-ref")


def test_a_status_that_overtakes_its_reply_is_delivered_after_the_load(fleet: Fleet) -> None:
    a = fleet.robot("A")
    ghost = ghost_provider(fleet)
    known(a, "ghost")
    got = Got()
    results: list[Any] = []
    caller = threading.Thread(
        target=lambda: results.append(
            remote(a).request("process", SLEEPER, robot="ghost", on_status=got)
        ),
        name="test-caller",
    )
    caller.start()
    (request, *_) = ghost.wait_type("resource_request_t")
    status = resource_status_t()
    status.provider, status.consumer, status.reference_id = "ghost", "A", "r-early"
    status.resource_id, status.status, status.message = "process:g", 5, "died at once"
    status.origin, status.hops = "process:g", ["process"]
    ghost.send(status)
    ghost.send(reply_to(request, "r-early"))
    caller.join(WAIT_S)
    assert len(results) == 1
    (update,) = fatal(got)
    assert update.message == "robot 'ghost': died at once"
    assert update.reference_id == results[0].id


def test_resent_requests_and_releases_are_answered_from_memory(fleet: Fleet) -> None:
    b = fleet.robot("B", processes=True)
    raw = fleet.raw("R", RESOURCE_CHANNEL)
    advert = ris_advert_t()
    advert.manager, advert.robot, advert.seq, advert.period_ms, advert.servers = (
        "R",
        "R",
        1,
        60_000,
        [],
    )
    raw.send(advert, RIS_CHANNEL)
    request = resource_request_t()
    request.request_id, request.provider, request.consumer = "R/1", "B", "R"
    request.server, request.request = "process", codec_json(SLEEPER)
    request.client, request.priority, request.exclusive = "", 0, False
    raw.send(request)
    (first,) = raw.wait_type("resource_reply_t")
    raw.send(request)  # a resend: same reply, no second reference
    second = raw.wait_type("resource_reply_t", 2)[1]
    assert first.code == second.code == 1
    assert (first.reference_id, first.response) == (second.reference_id, second.response)
    assert len(b.registrar.references()) == 1
    assert remote(b).stats["duplicates"] >= 1
    pid = __import__("json").loads(first.response)["pid"]

    release = resource_release_t()
    release.request_id, release.provider, release.consumer = "R/2", "B", "R"
    release.reference_id = first.reference_id
    raw.send(release)
    raw.send(release)
    replies = raw.wait_type("resource_reply_t", 4)
    assert [r.message for r in replies[2:]] == ["released", "released"]
    assert wait_exit(pid)
    release.request_id = "R/3"  # another release of the same reference: already done
    raw.send(release)
    release.request_id, release.reference_id = "R/4", "no-such-ref"
    raw.send(release)
    replies = raw.wait_type("resource_reply_t", 6)
    assert [(r.code, r.message) for r in replies[4:]] == [
        (1, "already released"),
        (2, "no reference no-such-ref held for 'R'"),
    ]


def codec_json(request: Any) -> str:
    from temoto.core.registrar.messages import canonical_json

    return canonical_json(request)


def test_bad_resource_messages_are_counted_and_dropped(fleet: Fleet) -> None:
    a, b = pair(fleet)
    raw = fleet.raw("mallory", RESOURCE_CHANNEL)

    def markers(tag: str) -> None:  # each robot answers a release of an unknown reference
        for provider in ("A", "B"):
            marker = resource_release_t()
            marker.request_id, marker.provider = f"{tag}/{provider}", provider
            marker.consumer, marker.reference_id = "mallory", "marker"
            raw.send(marker)

    # first the robots hold mallory's session (a keyed fleet re-sends what a receiver could not
    # open yet, but only the last messages: the 200 below would push the first ones out)
    markers("hello")
    assert len(raw.wait_type("resource_reply_t", 2)) == 2
    fleet.link("noise").transport.publish(RESOURCE_CHANNEL, b"\xffnot an envelope")
    raw.send(ris_advert_t_for("mallory"))  # a RIS message on the wrong channel
    raw.send_raw("resource_status_t", b"\x00\x01")
    raw.send_raw("unknown_t", b"")
    status = resource_status_t()
    status.provider, status.consumer, status.reference_id = "B", "A", "nope"
    status.resource_id, status.status, status.message, status.origin = "x", 42, "?", "x"
    status.hops = []
    raw.send(status)  # in B's name (its provider): mallory speaking as B
    status.status = 5
    raw.send(status)  # in B's name again
    request = resource_request_t()
    request.request_id, request.provider, request.consumer = "", "B", "mallory"
    request.server, request.request, request.client = "process", "{}", ""
    raw.send(request)  # no request id
    request.request_id, request.consumer = "m/1", "B"
    raw.send(request)  # in B's name (its consumer), to B itself
    rng = random.Random(7)
    for _ in range(200):
        kind = rng.choice(
            ["resource_request_t", "resource_reply_t", "resource_release_t", "resource_status_t"]
        )
        raw.send_raw(kind, bytes(rng.randrange(256) for _ in range(rng.randrange(80))))
    markers("m")  # after the rest
    replies = raw.wait_type("resource_reply_t", 4)[2:]
    assert {(r.provider, r.code) for r in replies} == {("A", 2), ("B", 2)}
    # still working, and nothing raised
    held = remote(a).request("process", SLEEPER, client="me")
    a.registrar.release(held.id)
    for robot in (a, b):
        assert robot.link.stats["handler_error"] == 0
    assert a.link.stats["garbage"] >= 1
    # In a keyed fleet a message sent before its receiver had the sender's session is asked
    # for again and comes later than the markers: the counts are waited for.
    deadline = time.monotonic() + WAIT_S
    while True:
        stats_a, stats_b = remote(a).stats, remote(b).stats  # copies
        done = stats_a["impostor"] >= 2 and stats_b["unexpected"] >= 2
        done = done and stats_a["unexpected"] >= 1 and stats_b["impostor"] >= 1
        if (done and stats_a["decode_errors"] >= 2) or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    why = (stats_a, stats_b, a.link.stats, b.link.stats, raw.link.stats)
    assert stats_a["unexpected"] >= 1, why  # the advert
    assert stats_a["impostor"] >= 2, why  # the statuses in B's name (docs/security.md)
    assert stats_b["unexpected"] >= 2, why  # the advert, no request id
    assert stats_b["impostor"] >= 1, why  # the request in B's own name
    assert stats_a["decode_errors"] >= 2
    assert stats_b["requests_received"] - stats_b["duplicates"] == 1  # only A's real one


def ris_advert_t_for(name: str) -> Any:
    advert = ris_advert_t()
    advert.manager, advert.robot, advert.seq, advert.period_ms, advert.servers = (
        name,
        name,
        1,
        100,
        [],
    )
    return advert


def test_closing_the_provider_releases_what_remote_consumers_hold(fleet: Fleet) -> None:
    a = fleet.robot("A")
    with ExitStack() as b_stack:
        fleet.robot("B", processes=True, stack=b_stack)
        known(a, "B")
        got = Got()
        held = remote(a).request("process", SLEEPER, client="me", on_status=got)
        pid = response_of(held, ProcessResponse).pid
    assert wait_exit(pid)
    (update,) = fatal(got)
    assert update.message == "robot 'B' was lost: withdrew"
    a.registrar.release(held.id)


def test_a_consumer_that_restarts_quickly_has_its_old_references_released_at_once(
    fleet: Fleet,
) -> None:
    b = fleet.robot("B", processes=True, period_s=60.0)  # silences would take minutes
    with ExitStack() as a_stack:
        a = fleet.robot("A", stack=a_stack, period_s=60.0)
        known = Got()
        a.ris.subscribe(on_joined=known)
        if a.ris.robot_info("B") is None:
            known.wait_for(1)
        one = remote(a).request("process", sleeper("one"), client="me")
        pid = response_of(one, ProcessResponse).pid
        old_boot = a.ris.boot
        lost = Got()
        b.ris.subscribe(on_lost=lost)
        a.link.transport.close()  # A dies without a word ...
        again = fleet.robot("A", period_s=60.0)  # ... and is back at once: a new boot id
        assert again.ris.boot != old_boot
        ((info, reason),) = lost.wait_for(1)
        assert (info.robot, reason) == ("A", "restarted")
        assert wait_exit(pid), "B did not stop the process of A's previous start"
    assert remote(b).held() == {}
    assert remote(b).stats["released_for_lost"] == 1
