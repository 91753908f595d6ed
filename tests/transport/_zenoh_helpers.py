"""Helpers of the Zenoh transport tests: free ports, fleet prefixes, waiting for routes."""

from __future__ import annotations

import itertools
import os
import socket
import threading
import time

from temoto.transport import ZenohTransport

WAIT_S = 5.0
_prefixes = itertools.count()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def prefix() -> str:
    return f"test-{os.getpid()}-{next(_prefixes)}"


def until_routed(sender: ZenohTransport, receiver: ZenohTransport) -> None:
    """Publish probes until the receiver hears one: its subscriptions have reached the sender.

    Zenoh propagates a new subscription to the router and on to the publishers
    asynchronously; this waits for that on events, the way the fleet's handshake does.
    """
    heard = threading.Event()
    sub = receiver.subscribe("PROBE", lambda c, d: heard.set())
    deadline = time.monotonic() + WAIT_S
    while not heard.is_set():
        assert time.monotonic() < deadline, "the router never carried a probe"
        sender.publish("PROBE", b"")
        heard.wait(0.02)
    sub.unsubscribe()
