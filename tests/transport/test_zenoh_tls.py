"""Zenoh's TLS and access control with the configurations of docs/zenoh.md.

The router and robot configurations are read from docs/zenoh.md (its ``json5`` blocks whose
first line names them), with this test's certificate paths, host and port put in, so the
documentation shows what runs here. Certificates are made with ``openssl`` in the test (skipped
without it), as docs/zenoh.md says. Robots trusting the fleet's CA exchange sealed fleet
messages through a TLS router; robots that do not trust it fail at once with a TransportError
that says what to check; with mutual TLS the router's access control lets robots use the whole
``temoto/**`` prefix and a visitor only ``TEMOTO_CONTEXT``.

Denials are shown without waiting for a silence: a denied message is sent first and an allowed
one after it on the same session, and Zenoh keeps one sender's order through the router, so
once the allowed one has arrived the denied one would have too.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from temoto.errors import TransportError
from temoto.transport import FleetAuth, FleetLink, Opened, ZenohTransport
from temoto.transport.zenoh import open_router

pytest.importorskip("zenoh", reason="the zenoh extra is not installed")

from _zenoh_helpers import WAIT_S, free_port, prefix

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")

DOC = Path(__file__).resolve().parents[2] / "docs" / "zenoh.md"
DOC_DIR = "/etc/temoto/tls/"  # where the documented configurations keep the certificates
DOC_HOST = "router.example.org:7447"
DOC_LISTEN = "tls/0.0.0.0:7447"
#: Longer than a failed open takes even on a loaded machine (well under a second when idle),
#: and well short of the test's 60 s limit, so that a hang fails here, saying so.
HANG_S = 3 * WAIT_S


def doc_config(name: str) -> str:
    """The ``json5`` block of docs/zenoh.md whose first line is ``// <name>``."""
    blocks = re.findall(r"```json5\n// (\S+)\n(.*?)```", DOC.read_text(), re.DOTALL)
    found = [text for block, text in blocks if block == name]
    assert len(found) == 1, f"docs/zenoh.md has {len(found)} blocks named {name}"
    return found[0]


def openssl(*args: str | Path, cwd: Path) -> None:
    proc = subprocess.run(
        ["openssl", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 0, proc.stderr


def make_ca(where: Path, name: str) -> None:
    """``<name>.pem`` and ``<name>.key``: a CA, as docs/zenoh.md makes the fleet's."""
    openssl(
        *("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"),
        *("-nodes", "-days", "2", "-subj", f"/CN={name}"),
        *("-keyout", f"{name}.key", "-out", f"{name}.pem"),
        cwd=where,
    )


def make_cert(where: Path, ca: str, name: str, host: str = "localhost") -> None:
    """``<name>.pem`` and ``<name>.key``, common name ``name``, signed by ``ca``."""
    openssl(
        *("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"),
        *("-subj", f"/CN={name}", "-keyout", f"{name}.key", "-out", f"{name}.csr"),
        cwd=where,
    )
    (where / f"{name}.ext").write_text(f"subjectAltName=DNS:{host}\n")
    openssl(
        *("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key"),
        *("-CAcreateserial", "-days", "2", "-extfile", f"{name}.ext", "-out", f"{name}.pem"),
        cwd=where,
    )


@dataclass
class Site:
    """Certificates in ``where``; configurations of docs/zenoh.md made for them."""

    where: Path
    port: int

    def config(self, doc_name: str, file_name: str, robot: str = "robot", ca: str = "ca") -> str:
        """Write docs/zenoh.md's ``doc_name`` with this site's paths; a ``zenoh:`` URL for it."""
        text = (
            doc_config(doc_name)
            .replace(f"{DOC_DIR}robot.", f"{self.where}/{robot}.")
            .replace(f"{DOC_DIR}ca.pem", f"{self.where}/{ca}.pem")
            .replace(DOC_DIR, f"{self.where}/")
            .replace(DOC_HOST, f"localhost:{self.port}")
            .replace(DOC_LISTEN, f"tls/127.0.0.1:{self.port}")
        )
        assert "/etc/" not in text, text
        assert "7447" not in text, text
        path = self.where / file_name
        path.write_text(text)
        return str(path)


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The fleet's CA, the router's certificate and robots' ones; another CA and its robot."""
    where = tmp_path_factory.mktemp("tls")
    make_ca(where, "ca")
    make_cert(where, "ca", "router")
    for name in ("robot-1", "robot-2", "visitor"):
        make_cert(where, "ca", name)
    make_ca(where, "other-ca")
    make_cert(where, "other-ca", "stranger")
    return where


@pytest.fixture
def site(certs: Path) -> Site:
    return Site(certs, free_port())


@pytest.fixture
def tls_router(site: Site) -> Iterator[Site]:
    session = open_router((), config_file=site.config("router-tls.json5", "router.json5"))
    try:
        yield site
    finally:
        session.close()


@pytest.fixture
def acl_router(site: Site) -> Iterator[Site]:
    session = open_router((), config_file=site.config("router-acl.json5", "router.json5"))
    try:
        yield site
    finally:
        session.close()


PROBE = b"probe"


def until_heard(sender: ZenohTransport, receiver: ZenohTransport, channel: str) -> None:
    """Publish probes on ``channel`` until the receiver hears one (subscriptions propagated)."""
    heard = threading.Event()
    sub = receiver.subscribe(channel, lambda c, d: heard.set())
    deadline = time.monotonic() + WAIT_S
    while not heard.is_set():
        assert time.monotonic() < deadline, f"no probe on {channel} came through the router"
        sender.publish(channel, PROBE)
        heard.wait(0.02)
    sub.unsubscribe()


class Heard:
    """A handler that keeps what is not a probe (probes still on their way may come later)."""

    def __init__(self) -> None:
        self.data: list[bytes] = []
        self._cond = threading.Condition()

    def __call__(self, channel: str, data: bytes) -> None:
        with self._cond:
            if data != PROBE:
                self.data.append(data)
                self._cond.notify_all()

    def wait_for(self, count: int) -> list[bytes]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.data) >= count, WAIT_S), self.data
            return list(self.data)


# --- TLS ----------------------------------------------------------------------------------------


def test_robots_that_trust_the_ca_exchange_sealed_fleet_messages_over_tls(
    tls_router: Site,
) -> None:
    url = f"zenoh:{tls_router.config('robot-tls.json5', 'robot.json5')}?prefix={prefix()}"
    key = bytes(range(32))
    with ZenohTransport(url) as a, ZenohTransport(url) as b:
        assert len(a.peers()) == 1  # the router, over TLS
        alpha = FleetLink(a, FleetAuth("fleet", "alpha", key))
        beta = FleetLink(b, FleetAuth("fleet", "beta", key))
        got: list[Opened] = []
        done = threading.Event()
        beta.listen("TEMOTO_NOTIFY", lambda opened: (got.append(opened), done.set()))
        until_heard(a, b, "PROBE")
        alpha.send("TEMOTO_NOTIFY", "action_ack_t", b"over tls")
        assert done.wait(WAIT_S)
        assert [(o.sender, o.payload) for o in got] == [("alpha", b"over tls")]


@pytest.mark.parametrize(
    ("ca", "host"),
    [(None, "localhost"), ("other-ca", "localhost"), ("ca", "127.0.0.1")],
    ids=["without-the-ca", "trusting-another-ca", "at-a-host-the-certificate-does-not-name"],
)
def test_a_robot_that_does_not_trust_the_router_fails_at_once_saying_what_to_check(
    tls_router: Site, ca: str | None, host: str
) -> None:
    path = Path(tls_router.config("robot-tls.json5", "robot.json5", ca=ca or "ca"))
    text = path.read_text().replace("tls/localhost:", f"tls/{host}:")
    if ca is None:
        text = re.sub(r"transport: .*\n", "", text)
        assert "root_ca_certificate" not in text
    path.write_text(text)
    started = time.monotonic()
    with pytest.raises(TransportError) as info:
        ZenohTransport(f"zenoh:{path}")
    assert time.monotonic() - started < HANG_S
    message = str(info.value)
    assert f"Zenoh cannot open 'zenoh:{path}'" in message
    assert f"tls/{host}:{tls_router.port}" in message
    assert "root_ca_certificate must be the CA that signed the router's certificate" in message


def test_a_plain_tcp_client_at_a_tls_endpoint_fails_after_its_timeout(tls_router: Site) -> None:
    url = f"zenoh:tcp/127.0.0.1:{tls_router.port}?timeout=0.5"
    started = time.monotonic()
    with pytest.raises(TransportError, match="is a router running there"):
        ZenohTransport(url)
    assert time.monotonic() - started < HANG_S


def test_temoto_router_serves_tls_from_its_config_file(site: Site) -> None:
    conf = site.config("router-tls.json5", "router.json5")
    router = subprocess.Popen(
        [sys.executable, "-m", "temoto", "router", "--config", conf],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert f"the endpoints of {conf}" in line
        assert "--fleet-url zenoh:ROBOT.json5 (a configuration that trusts its certificate" in line
        url = f"zenoh:{site.config('robot-tls.json5', 'robot.json5')}?prefix={prefix()}"
        with ZenohTransport(url) as a, ZenohTransport(url) as b:
            until_heard(a, b, "VIA_TLS")
    finally:
        router.terminate()
        _, err = router.communicate(timeout=WAIT_S * 2)
    assert router.returncode == 0, err


def test_temoto_router_with_an_unreadable_key_exits_2(site: Site) -> None:
    conf = Path(site.config("router-tls.json5", "router.json5"))
    conf.write_text(conf.read_text().replace("router.key", "missing.key"))
    proc = subprocess.run(
        [sys.executable, "-m", "temoto", "router", "--config", str(conf)],
        capture_output=True,
        text=True,
        timeout=WAIT_S * 2,
    )
    assert proc.returncode == 2
    assert "temoto router: Zenoh router cannot listen" in proc.stderr
    assert "Invalid TLS private key file" in proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr


# --- mutual TLS and access control --------------------------------------------------------------


def robot(site: Site, name: str) -> ZenohTransport:
    """A client of the ACL router with ``name``'s certificate, on the fleet prefix ``temoto``."""
    return ZenohTransport(f"zenoh:{site.config('robot-mtls.json5', f'{name}.json5', name)}")


def test_access_control_gives_robots_the_prefix_and_a_visitor_one_channel(
    acl_router: Site,
) -> None:
    with (
        robot(acl_router, "robot-1") as one,
        robot(acl_router, "robot-2") as two,
        robot(acl_router, "visitor") as visitor,
    ):
        at_two, at_visitor = Heard(), Heard()
        for channel in ("TEMOTO_NOTIFY", "TEMOTO_CONTEXT"):
            two.subscribe(channel, at_two)
            visitor.subscribe(channel, at_visitor)
        until_heard(one, two, "TEMOTO_NOTIFY")  # robots: anything under temoto/
        until_heard(one, visitor, "TEMOTO_CONTEXT")
        until_heard(visitor, two, "TEMOTO_CONTEXT")

        # the router keeps the fleet's notifications from the visitor ...
        one.publish("TEMOTO_NOTIFY", b"robot-1 notify")
        one.publish("TEMOTO_CONTEXT", b"robot-1 context")
        assert at_visitor.wait_for(1) == [b"robot-1 context"]
        # ... and the visitor's notifications from the fleet
        visitor.publish("TEMOTO_NOTIFY", b"visitor notify")
        visitor.publish("TEMOTO_CONTEXT", b"visitor context")
        assert at_two.wait_for(3) == [b"robot-1 notify", b"robot-1 context", b"visitor context"]


def test_a_robot_with_a_certificate_of_another_ca_is_refused(acl_router: Site) -> None:
    conf = acl_router.config("robot-mtls.json5", "stranger.json5", "stranger")
    with pytest.raises(TransportError, match="for mutual TLS also enable_mtls"):
        ZenohTransport(f"zenoh:{conf}")
