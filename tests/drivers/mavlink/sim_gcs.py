"""pymavlink's ``mavutil`` as the ground station of the SimVehicle tests (a real client, not ours).

The GCS listens (``udpin:127.0.0.1:<port>``, as MAVProxy and QGroundControl do on 14550) and
the simulated vehicle streams to it; mavutil learns the vehicle's address from its first
datagram and answers there.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from pymavlink import mavutil

from temoto.clock import Clock, ScaledClock
from temoto.drivers.mavlink import SimVehicle

HOME = (47.397742, 8.545594, 488.0)
mavlink = mavutil.mavlink


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def ground_station(
    clock: Clock | None = None, **sim_kwargs: Any
) -> Iterator[tuple[SimVehicle, Any]]:
    """A started SimVehicle (on ``clock``, 10x real time by default) and a mavutil GCS."""
    port = free_port()
    conn = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{port}",
        source_system=255,
        source_component=190,
        dialect="ardupilotmega",
    )
    sim = SimVehicle(
        "gcs-quad",
        clock=clock or ScaledClock(10.0),
        gcs=[("127.0.0.1", port)],
        home=HOME,
        **sim_kwargs,
    )
    sim.start()
    try:
        assert conn.wait_heartbeat(timeout=5) is not None, "no heartbeat from the simulator"
        yield sim, conn
    finally:
        sim.close()
        conn.close()


def recv(
    conn: Any, kind: str | list[str], timeout: float = 5.0, cond: Callable[[Any], bool] = bool
) -> Any:
    """The next message of ``kind`` for which ``cond`` holds (AssertionError after timeout)."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        msg = conn.recv_match(type=kind, blocking=True, timeout=left)
        if msg is not None and cond(msg):
            return msg
    raise AssertionError(f"no {kind} within {timeout} s")


def none_within(conn: Any, kind: str, seconds: float, cond: Callable[[Any], bool] = bool) -> None:
    """Assert that no ``kind`` message (matching ``cond``) arrives for ``seconds`` real seconds."""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        msg = conn.recv_match(type=kind, blocking=True, timeout=left)
        assert msg is None or not cond(msg), f"unexpected {msg}"


def command(
    conn: Any,
    cmd: int,
    *params: float,
    component: int = 1,
    timeout: float = 5.0,
    texts_for: float = 0.0,
) -> tuple[int, list[str]]:
    """COMMAND_LONG; the ack's result and the STATUSTEXTs that came ``texts_for`` s after.

    mavutil's ``recv_match`` drops what it does not match, so texts are only collected when
    asked for.
    """
    values = [*params, *[0.0] * (7 - len(params))]
    conn.mav.command_long_send(conn.target_system, component, cmd, 0, *values)
    ack = recv(conn, "COMMAND_ACK", timeout, lambda m: m.command == cmd)
    texts = []
    deadline = time.monotonic() + texts_for
    while (left := deadline - time.monotonic()) > 0:
        msg = conn.recv_match(type="STATUSTEXT", blocking=True, timeout=left)
        if msg is not None:
            texts.append(msg.text)
    return int(ack.result), texts


def set_mode(conn: Any, mode: str, texts_for: float = 0.0) -> tuple[int, list[str]]:
    return command(
        conn,
        mavlink.MAV_CMD_DO_SET_MODE,
        mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        conn.mode_mapping()[mode],
        texts_for=texts_for,
    )


def set_param(conn: Any, name: str, value: float, param_type: int) -> Any:
    """PARAM_SET and the PARAM_VALUE echo."""
    conn.mav.param_set_send(conn.target_system, 1, name.encode(), value, param_type)
    return recv(conn, "PARAM_VALUE", 5.0, lambda m: m.param_id == name)


def until(pred: Callable[[], bool], seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not pred():
        assert time.monotonic() < deadline, f"{what}: not within {seconds} s"
        time.sleep(0.01)
