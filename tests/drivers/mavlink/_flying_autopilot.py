"""An independent ArduCopter end in a process of its own: a flying autopilot, and its neighbours.

Written from the MAVLink common message set (common.xml: HEARTBEAT, EXTENDED_SYS_STATE,
GLOBAL_POSITION_INT, COMMAND_LONG/COMMAND_INT → COMMAND_ACK, MAV_COMP_ID_AUTOPILOT1 = 1) and
ArduCopter's documented behaviour, not from temoto's simulator; it encodes with pymavlink
directly. Run as ``python _flying_autopilot.py GCS_PORT [options]``; it sends to
``127.0.0.1:GCS_PORT`` (where a driver with ``link: udpin:127.0.0.1:GCS_PORT`` listens) and
prints one JSON line per event on standard output, stamped with CLOCK_MONOTONIC (``t``):
``ready``, ``gcs`` (the first heartbeat of the ground station), ``command`` (every
COMMAND_LONG/COMMAND_INT, with ``command``, ``param1``, ``param2``), ``arrived`` (the autopilot
is within 1 m of a reposition target). It stops on SIGTERM or when its input closes.

What it plays:

* system 1, component 1, the autopilot: armed and flying in GUIDED (custom mode 4) at 10 m,
  HEARTBEAT and EXTENDED_SYS_STATE ``MAV_LANDED_STATE_IN_AIR`` at 1 Hz, GLOBAL_POSITION_INT and
  ATTITUDE at 10 Hz, SYS_STATUS at 1 Hz; it acknowledges every command (ACCEPTED), takes
  DO_SET_MODE's custom mode, and flies a DO_REPOSITION target at ``--speed`` m/s;
* ``--companion on_ground``: system 1, component 100 (a companion computer:
  ``MAV_TYPE_ONBOARD_CONTROLLER``, ``MAV_AUTOPILOT_INVALID``) sending EXTENDED_SYS_STATE
  ``MAV_LANDED_STATE_ON_GROUND`` at 10 Hz; ``--companion spoof LAT,LON,ALT``: the same
  component also sends GLOBAL_POSITION_INT at that position at 10 Hz;
* ``--duplicate address``: a second vehicle as system 1, component 1 from another UDP port
  (its own heartbeats and positions); ``--duplicate sequence``: the same from the same port,
  with its own sequence numbers (what a router merging two vehicles delivers).
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import sys
import threading
import time
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mav

EARTH_RADIUS = 6_378_137.0
GUIDED, LOITER = 4, 5
START = (47.397742, 8.545594, 10.0)  # lat, lon, m above home


class Sender:
    """One MAVLink sender (its ids and sequence number) on one socket."""

    def __init__(self, sock: socket.socket, gcs: tuple[str, int], system: int, comp: int) -> None:
        self.sock, self.gcs = sock, gcs
        self.mav = mav.MAVLink(None, system, comp)

    def send(self, msg: Any) -> None:
        data = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256  # as MAVLink.send() does
        self.sock.sendto(data, self.gcs)


#: Metres from the target within which the vehicle is there (it takes the target's position and
#: reports ``arrived``): the test's FlyTo tolerance (1 m) and a margin for the 1e-7 degree
#: rounding of GLOBAL_POSITION_INT, so that no position a ground station takes as arrived is
#: sent before the event.
ARRIVED = 1.05


def emit(event: str, **fields: Any) -> None:
    sys.stdout.write(json.dumps({"t": time.monotonic(), "event": event, **fields}) + "\n")
    sys.stdout.flush()


def position_msg(m: Any, lat: float, lon: float, alt: float) -> Any:
    return m.global_position_int_encode(
        0, int(lat * 1e7), int(lon * 1e7), int((488.0 + alt) * 1000), int(alt * 1000),
        0, 0, 0, 0,
    )  # fmt: skip


class Autopilot:
    def __init__(self, args: argparse.Namespace) -> None:
        self.gcs = ("127.0.0.1", args.gcs_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.ap = Sender(self.sock, self.gcs, 1, 1)
        self.companion = Sender(self.sock, self.gcs, 1, 100) if args.companion else None
        self.spoof = args.spoof
        self.twin: Sender | None = None
        if args.duplicate == "address":
            other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            other.bind(("127.0.0.1", 0))
            self.twin = Sender(other, self.gcs, 1, 1)
        elif args.duplicate == "sequence":
            self.twin = Sender(self.sock, self.gcs, 1, 1)
            self.twin.mav.seq = 128
        self.speed = args.speed
        self.lock = threading.Lock()
        self.mode = GUIDED
        self.lat, self.lon, self.alt = START
        self.target: tuple[float, float, float] | None = None
        self.gcs_seen = False
        self.stop = threading.Event()

    def rx(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            for msg in mav.MAVLink(None, 1, 1).parse_buffer(data) or []:
                self.handle(msg)

    def handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and not self.gcs_seen:
            self.gcs_seen = True
            emit("gcs")
        if kind not in ("COMMAND_LONG", "COMMAND_INT"):
            return
        emit("command", command=msg.command, param1=msg.param1, param2=msg.param2)
        with self.lock:
            if msg.command == mav.MAV_CMD_DO_SET_MODE:
                self.mode = int(msg.param2)
            elif msg.command == mav.MAV_CMD_DO_REPOSITION and kind == "COMMAND_INT":
                self.mode = GUIDED
                self.target = (msg.x / 1e7, msg.y / 1e7, float(msg.z))
        ack = self.ap.mav.command_ack_encode(msg.command, mav.MAV_RESULT_ACCEPTED)
        ack.target_system, ack.target_component = msg.get_srcSystem(), msg.get_srcComponent()
        self.ap.send(ack)

    def _left(self) -> float:
        """Metres to the target over the ground (lock held)."""
        assert self.target is not None
        lat, lon, _alt = self.target
        north = math.radians(lat - self.lat) * EARTH_RADIUS
        east = math.radians(lon - self.lon) * EARTH_RADIUS * math.cos(math.radians(lat))
        return math.hypot(north, east)

    def fly(self, dt: float) -> None:
        """One tick of flight (lock held); ``arrived`` once within :data:`ARRIVED` of the target.

        The event is written before the tick's position is sent: a ground station that ends
        its fly-to on that position cannot have done so before the event, however the two
        processes are scheduled.
        """
        if self.target is None:
            return
        lat, lon, alt = self.target
        left = self._left()
        step = min(1.0, self.speed * dt / left) if left > 0 else 1.0
        self.lat += (lat - self.lat) * step
        self.lon += (lon - self.lon) * step
        self.alt += (alt - self.alt) * step
        if self._left() <= ARRIVED:
            self.lat, self.lon, self.alt = self.target  # there: it holds the target itself
            self.target = None
            emit("arrived")

    def stream(self, n: int) -> None:
        """Tick ``n`` (10 Hz): what each sender sends."""
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_SAFETY_ARMED
        quad, ardupilot = mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA
        m = self.ap.mav
        if n % 10 == 0:
            self.ap.send(m.heartbeat_encode(quad, ardupilot, base, self.mode, 4, 3))
            self.ap.send(m.extended_sys_state_encode(0, mav.MAV_LANDED_STATE_IN_AIR))
            self.ap.send(m.sys_status_encode(0, 0, 0, 500, 16000, -1, 80, 0, 0, 0, 0, 0, 0))
        self.ap.send(position_msg(m, self.lat, self.lon, self.alt))
        self.ap.send(m.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        if self.companion is not None:
            c = self.companion.mav
            if n % 10 == 0:
                companion = mav.MAV_TYPE_ONBOARD_CONTROLLER
                self.companion.send(c.heartbeat_encode(companion, 8, 0, 0, 4, 3))  # INVALID
            self.companion.send(c.extended_sys_state_encode(0, mav.MAV_LANDED_STATE_ON_GROUND))
            if self.spoof is not None:
                self.companion.send(position_msg(c, *self.spoof))
        if self.twin is not None:
            t = self.twin.mav
            if n % 10 == 5:
                self.twin.send(t.heartbeat_encode(quad, ardupilot, 0, 0, 3, 3))
            self.twin.send(position_msg(t, START[0] + 0.001, START[1], 0.0))

    def run(self) -> None:
        rx = threading.Thread(target=self.rx, daemon=True)
        rx.start()
        emit("ready")
        tick, n = 0.1, 0
        next_t = time.monotonic()
        while not self.stop.is_set():
            with self.lock:
                self.fly(tick)
                self.stream(n)
            n += 1
            next_t += tick
            self.stop.wait(max(0.0, next_t - time.monotonic()))


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("gcs_port", type=int)
    parser.add_argument("--companion", choices=["on_ground", "spoof"])
    parser.add_argument("--spoof-at", dest="spoof_at", default="")
    parser.add_argument("--duplicate", choices=["address", "sequence"])
    parser.add_argument("--speed", type=float, default=8.0)
    args = parser.parse_args()
    args.spoof = (
        tuple(float(v) for v in args.spoof_at.split(",")) if args.companion == "spoof" else None
    )
    pilot = Autopilot(args)
    signal.signal(signal.SIGTERM, lambda *_: pilot.stop.set())
    threading.Thread(target=lambda: (sys.stdin.read(), pilot.stop.set()), daemon=True).start()
    pilot.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
