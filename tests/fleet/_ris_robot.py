"""Robots for the multi-process RIS tests and the ``ris`` benchmark, over LCM or Zenoh.

One file, four roles (``python _ris_robot.py ROLE ...``), run inside a network namespace in
which multicast is routed to loopback (see ``test_remote_resources_processes.py``):

``provider NAME URL PERIOD``
    Robot B: a registrar with a Process Manager, RIS and remote resources. Prints ``ready``,
    then obeys ``stats`` (prints its counters as JSON) and ``quit`` (closes, prints the
    counters, exits) on stdin.
``consumer NAME URL PERIOD``
    Robot A: a registrar with RIS and remote resources, no servers. Prints ``ready`` once it
    knows a robot that offers ``process``, then obeys ``load TAG`` (prints ``loaded REF PID
    MS``), ``release REF`` (prints ``released REF``) and ``quit``. Every status update of a
    loaded process is printed as ``status REF STATUS UNIX_TIME MESSAGE``.
``driver [URL]``
    Starts B and A on the fleet URL (default LCM multicast; for a ``zenoh:`` URL a `temoto
    router` first), and runs the test scenario; prints one JSON object.
``bench N``
    Starts B and A, and measures N crashes and loads; prints one JSON object.

The fleet key comes from ``TEMOTO_FLEET_KEY``. Every child is reaped, and every process B
started is killed, even when something fails.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from typing import Any

URL = "udpm://239.255.76.67:7667?ttl=0"
PERIOD_S = 0.1
MISSED = 3


class Lines:
    """Lines from a file descriptor, with a timeout."""

    def __init__(self, fd: int) -> None:
        self.fd, self.buf = fd, b""

    def next(self, timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None
            chunk = os.read(self.fd, 65536)
            if not chunk:
                return None
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode()

    def expect(self, prefix: str, timeout: float = 10.0) -> str:
        """The next line starting with ``prefix`` (others are skipped); raises on timeout."""
        deadline = time.monotonic() + timeout
        while True:
            line = self.next(max(0.0, deadline - time.monotonic()))
            if line is None:
                raise RuntimeError(f"no {prefix!r} line within {timeout} s")
            if line.startswith(prefix):
                return line


_out_lock = threading.Lock()


def say(line: str) -> None:
    with _out_lock:
        os.write(1, (line + "\n").encode())


def robot(role: str, name: str, url: str, period: float) -> None:
    from temoto.core.registrar import Registrar, StatusUpdate
    from temoto.fleet.resources import RemoteResources, response_of
    from temoto.fleet.ris import ResourceInfoSync
    from temoto.managers.process import ProcessManager, ProcessRequest, ProcessResponse
    from temoto.transport import FleetAuth, FleetLink, key_from_env, open_transport

    with contextlib.ExitStack() as stack:
        transport = stack.enter_context(open_transport(url))
        link = FleetLink(transport, FleetAuth("risfleet", name, key_from_env()))
        registrar = Registrar(name)
        stack.callback(registrar.close)
        if role == "provider":
            manager = ProcessManager(registrar, grace=1.0)
            stack.callback(manager.shutdown)
        ris = stack.enter_context(
            ResourceInfoSync(link, registrar, name, period_s=period, missed=MISSED)
        )
        remote = stack.enter_context(RemoteResources(link, registrar, ris))
        if role == "consumer":
            known = threading.Event()
            ris.subscribe(on_joined=lambda _: known.set(), on_changed=lambda _: known.set())
            while not ris.providers("process"):
                known.wait(1.0)
                known.clear()
        say("ready")
        for line in sys.stdin:
            words = line.split()
            if not words:
                continue
            if words[0] == "quit":
                break
            if words[0] == "stats":
                say(json.dumps({"remote": remote.stats, "ris": ris.stats}))
            elif words[0] == "load":
                tag = words[1]

                def on_status(update: StatusUpdate, tag: str = tag) -> None:
                    now = time.time()
                    say(
                        f"status {update.reference_id} {update.status.value} {now} {update.message}"
                    )

                request = ProcessRequest(
                    sys.executable, ("-c", f"import time; time.sleep(60)  # {tag}")
                )
                t0 = time.perf_counter()
                held = remote.request("process", request, client="main", on_status=on_status)
                ms = (time.perf_counter() - t0) * 1e3
                pid = response_of(held, ProcessResponse).pid
                say(f"loaded {held.id} {pid} {ms}")
            elif words[0] == "release":
                registrar.release(words[1])
                say(f"released {words[1]}")
    say(json.dumps({"remote": remote.stats, "ris": ris.stats}))


class Robots:
    """Starts robot B and robot A in this namespace; kills what is left on exit."""

    def __init__(self, url: str = URL) -> None:
        self.url = url
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.lines: dict[str, Lines] = {}
        self.pids: list[int] = []  # processes B started, killed at the end if still there

    def start(self, role: str, name: str) -> None:
        proc = subprocess.Popen(
            [sys.executable, __file__, role, name, self.url, str(PERIOD_S)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        self.procs[name] = proc
        assert proc.stdout is not None
        self.lines[name] = Lines(proc.stdout.fileno())

    def tell(self, name: str, command: str) -> None:
        stdin = self.procs[name].stdin
        assert stdin is not None
        stdin.write((command + "\n").encode())
        stdin.flush()

    def load(self, tag: str) -> tuple[str, int, float]:
        self.tell("A", f"load {tag}")
        _, ref, pid, ms = self.lines["A"].expect("loaded ").split()
        self.pids.append(int(pid))
        return ref, int(pid), float(ms)

    def __enter__(self) -> Robots:
        return self

    def __exit__(self, *exc: object) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        for pid in self.pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def wait_exit(pid: int, timeout: float) -> float | None:
    """Seconds until the process exited (pidfd, no polling), or None if it did not."""
    t0 = time.monotonic()
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return 0.0
    try:
        if select.select([fd], [], [], timeout)[0]:
            return time.monotonic() - t0
        return None
    finally:
        os.close(fd)


def crash(robots: Robots, tag: str) -> tuple[float, str, float]:
    """Load a process on B through A, kill it: (status latency s, message, load ms)."""
    ref, pid, load_ms = robots.load(tag)
    t0 = time.time()
    os.kill(pid, signal.SIGKILL)
    line = robots.lines["A"].expect(f"status {ref} FATAL ")
    _, _, _, stamp, message = line.split(" ", 4)
    robots.tell("A", f"release {ref}")
    robots.lines["A"].expect(f"released {ref}")
    return float(stamp) - t0, message, load_ms


def start_both(robots: Robots) -> None:
    robots.start("provider", "B")
    robots.lines["B"].expect("ready", 20)
    robots.start("consumer", "A")
    robots.lines["A"].expect("ready", 20)


def driver(url: str) -> None:
    from _router import start_router, stop_router

    result: dict[str, Any] = {}
    router = start_router(url)
    with contextlib.ExitStack() as stack:
        stack.callback(stop_router, router)
        robots = stack.enter_context(Robots(url))
        start_both(robots)
        # 1. a process on B crashes: A's consumer is told
        latency, message, load_ms = crash(robots, "crash")
        result.update(status_latency_s=latency, status_message=message, load_ms=load_ms)
        # 2. A releases: B stops the process
        ref, pid, _ = robots.load("kept")
        robots.tell("A", f"release {ref}")
        robots.lines["A"].expect(f"released {ref}")
        result["release_stop_s"] = wait_exit(pid, 10.0)
        # 3. A dies (SIGKILL): B stops A's process after the missed periods
        _, pid, _ = robots.load("orphan")
        robots.procs["A"].kill()
        robots.procs["A"].wait()
        result["orphan_stop_s"] = wait_exit(pid, 10.0)
        robots.tell("B", "quit")
        result["b_stats"] = json.loads(robots.lines["B"].expect("{", 10))
        robots.procs["B"].wait(10)
        result["b_code"] = robots.procs["B"].returncode
    print(json.dumps(result), flush=True)


def bench(rounds: int) -> None:
    latencies, loads = [], []
    with Robots() as robots:
        start_both(robots)
        crash(robots, "warmup")
        for i in range(rounds):
            latency, _, load_ms = crash(robots, f"r{i}")
            latencies.append(latency)
            loads.append(load_ms)
        robots.tell("A", "quit")
        robots.tell("B", "quit")
        for proc in robots.procs.values():
            proc.wait(10)
    print(json.dumps({"status_s": latencies, "load_ms": loads}), flush=True)


if __name__ == "__main__":
    if sys.argv[1] in ("provider", "consumer"):
        robot(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]))
    elif sys.argv[1] == "driver":
        driver(sys.argv[2] if len(sys.argv) > 2 else URL)
    else:
        bench(int(sys.argv[2]))
