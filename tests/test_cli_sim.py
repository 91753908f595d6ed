"""``temoto sim``: standalone simulators that real tools reach, stopped by a signal (exit 0)."""

from __future__ import annotations

import importlib.util
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import pytest
import yaml

from temoto.clock import MonotonicClock
from temoto.drivers.dynamixel.driver import DynamixelDriver
from temoto.drivers.mavlink.driver import MavlinkDriver
from temoto.drivers.mavlink.protocol import Codec
from temoto.testing.tools import require_tool

ROOT = Path(__file__).resolve().parents[1]
PROFILES = ROOT / "hw_profiles"
READ_TIMEOUT = 20.0  # real seconds for a line: generous, the machine is shared


def env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def sim_cli(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "temoto", "sim", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env(),
        check=False,
    )


class Served:
    """A running ``temoto sim``: its JSON lines as they come, its stderr at the end."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "temoto", "sim", *args, "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env(),
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        assert self.proc.stdout is not None
        self._reader = threading.Thread(target=self._read, args=(self.proc.stdout,))
        self._reader.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.put(json.loads(line))

    def next(self, timeout: float = READ_TIMEOUT) -> dict[str, Any]:
        try:
            return self.lines.get(timeout=timeout)
        except queue.Empty:
            self.proc.kill()
            _, err = self.proc.communicate()
            raise AssertionError(f"no line from temoto sim: {err[-2000:]}") from None

    def endpoints(self, count: int) -> list[dict[str, Any]]:
        return [self.next()["endpoint"] for _ in range(count)]

    def until(self, **match: Any) -> dict[str, Any]:
        while True:
            line = self.next()
            if all(line.get(k) == v for k, v in match.items()):
                return line

    def stop(self, sig: int = signal.SIGTERM) -> tuple[int, str]:
        self.proc.send_signal(sig)
        try:
            _, err = self.proc.communicate(timeout=30)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self._reader.join(5)
        return self.proc.returncode, err


@pytest.fixture
def served() -> Iterator[list[Served]]:
    running: list[Served] = []
    yield running
    for one in running:
        if one.proc.poll() is None:
            one.proc.kill()
            one.proc.communicate()
        one._reader.join(5)


def start(running: list[Served], *args: str) -> Served:
    one = Served(*args)
    running.append(one)
    return one


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


# ---- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "words"),
    [
        ((), "say what to simulate"),
        (("--profile", "x.yaml", "quad"), "not both"),
        (("quad", "--out", "udp:10.1.2.3:14550"), "loopback"),
        (("quad", "--out", "14550"), "expected udp:HOST:PORT"),
        (("quad", "--home", "47.3,8.5"), "LAT,LON,ALT"),
        (("quad", "--speedup", "0"), "more than 0"),
        (("odrive", "--node", "64"), "node id must be 0..63"),
        (("odrive", "--node", "1", "--rate", "heartbeat=-1"), "0 \\(off\\)"),
        (("odrive", "--node", "1", "--channel", "can0"), "multicast group"),
        (("mit", "--motor", "1:AK99"), "unknown model 'AK99'"),
        (("dynamixel", "--servo", "1:XM999"), "unknown model 'XM999'"),
        (("dynamixel", "--servo", "1:XM430-W350", "--servo", "1:XL430-W250"), "id of its own"),
        (("dynamixel", "--servo", "1:XM430-W350", "--baud", "1234"), "baud must be one of"),
        (("--profile", "no/such/profile.yaml"), "no/such/profile.yaml"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: tuple[str, ...], words: str) -> None:
    proc = sim_cli(*args)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert __import__("re").search(words, proc.stderr), proc.stderr


def test_every_form_has_help() -> None:
    for kind in ("quad", "odrive", "mit", "dynamixel"):
        proc = sim_cli(kind, "--help")
        assert proc.returncode == 0
        assert "usage: temoto sim " + kind in proc.stdout
    top = sim_cli("--help")
    assert "--profile FILE" in top.stdout


# ---- quad ------------------------------------------------------------------------------------


def receive(sock: socket.socket, codec: Codec, name: str, timeout: float = READ_TIMEOUT) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data, _ = sock.recvfrom(65536)
        except TimeoutError:
            break
        for msg in codec.decode_datagram(data):
            if msg.name == name:
                return msg
    raise AssertionError(f"no {name} within {timeout} s")


def drain(sock: socket.socket) -> None:
    sock.setblocking(False)
    try:
        while True:
            sock.recvfrom(65536)
    except BlockingIOError:
        pass
    finally:
        sock.setblocking(True)


def test_quad_streams_to_out_answers_a_gcs_and_stops_on_sigterm(served: list[Served]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        port = gcs.getsockname()[1]
        quad = start(
            served, "quad", "--port", "0", "--out", f"udp:127.0.0.1:{port}", "--sysid", "7"
        )
        (endpoint,) = quad.endpoints(1)
        assert endpoint["driver"] == "mavlink"
        assert endpoint["streams_to"] == [f"udp:127.0.0.1:{port}"]
        host, vehicle_port = endpoint["vehicle"].removeprefix("udp:").split(":")
        assert endpoint["link"] == f"udpout:{host}:{vehicle_port}"
        codec = Codec(255, 190)
        beat = receive(gcs, codec, "HEARTBEAT")
        assert beat.src_system == 7
        # a ground station speaks: the command reports it, and the message's first arrival
        ping = codec.encode(
            "HEARTBEAT", type=6, autopilot=8, base_mode=0, custom_mode=0, system_status=4
        )
        gcs.sendto(ping, (host, int(vehicle_port)))
        assert quad.until(event="client", talking=True)["device"] == "quad"
        assert quad.until(event="message")["name"] == "HEARTBEAT"
    code, err = quad.stop(signal.SIGTERM)
    assert code == 0, err
    assert "Traceback" not in err


def test_quad_speedup_runs_the_vehicle_clock_faster(served: list[Served]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        port = gcs.getsockname()[1]
        quad = start(served, "quad", "--port", "0", "--out", f"udp:127.0.0.1:{port}",
                     "--speedup", "10")  # fmt: skip
        quad.endpoints(1)
        codec = Codec(255, 190)
        first = receive(gcs, codec, "GLOBAL_POSITION_INT")
        t0 = time.monotonic()
        time.sleep(0.5)
        drain(gcs)  # what queued meanwhile is older than now
        later = receive(gcs, codec, "GLOBAL_POSITION_INT")
        real = time.monotonic() - t0
    boot = (later.get_int("time_boot_ms") - first.get_int("time_boot_ms")) / 1000.0
    assert boot > 5 * real  # ten times as fast, with room for a loaded machine
    assert quad.stop(signal.SIGINT)[0] == 0


def test_params_persist_across_runs(served: list[Served], tmp_path: Path) -> None:
    file = tmp_path / "quad.parm"
    codec = Codec(255, 190)

    def run_once(value: float | None) -> float:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
            gcs.bind(("127.0.0.1", 0))
            port = gcs.getsockname()[1]
            quad = start(served, "quad", "--port", "0", "--out", f"udp:127.0.0.1:{port}",
                         "--params", str(file))  # fmt: skip
            (endpoint,) = quad.endpoints(1)
            host, vport = endpoint["vehicle"].removeprefix("udp:").split(":")
            if value is not None:
                msg = codec.encode(
                    "PARAM_SET",
                    target_system=1,
                    target_component=1,
                    param_id=b"RTL_ALT",
                    param_value=value,
                    param_type=9,  # MAV_PARAM_TYPE_REAL32, as pymavlink sends it
                )
            else:
                msg = codec.encode(
                    "PARAM_REQUEST_READ",
                    target_system=1,
                    target_component=1,
                    param_id=b"RTL_ALT",
                    param_index=-1,
                )
            gcs.sendto(msg, (host, int(vport)))
            reply = receive(gcs, codec, "PARAM_VALUE")
        assert quad.stop()[0] == 0
        return float(reply.fields["param_value"])

    assert run_once(2500.0) == 2500.0
    assert run_once(None) == 2500.0


# ---- dynamixel -------------------------------------------------------------------------------


def test_dynamixel_sdk_pings_the_printed_port(served: list[Served]) -> None:
    sdk = pytest.importorskip("dynamixel_sdk")
    chain = start(served, "dynamixel", "--servo", "1:XM430-W350", "--servo", "7:XL430-W250")
    (endpoint,) = chain.endpoints(1)
    assert endpoint["link"] == f"serial:{endpoint['port']}"
    assert endpoint["servos"] == {"1": "XM430-W350", "7": "XL430-W250"}
    port = sdk.PortHandler(endpoint["port"])
    assert port.openPort()
    try:
        assert port.setBaudRate(1_000_000)
        packets = sdk.PacketHandler(2.0)
        model, result, error = packets.ping(port, 7)
        assert (result, error) == (sdk.COMM_SUCCESS, 0)
        assert model == 1060  # XL430-W250's model number (e-Manual)
        found, result = packets.broadcastPing(port)
        assert result == sdk.COMM_SUCCESS
        assert sorted(found) == [1, 7]
    finally:
        port.closePort()
    assert chain.until(event="client", talking=True)["device"] == "dynamixel"
    code, err = chain.stop(signal.SIGINT)
    assert code == 0, err
    assert "Traceback" not in err


# ---- a whole profile, driven from another process ----------------------------------------------


def test_a_profile_s_arm_is_driven_through_the_printed_link(served: list[Served]) -> None:
    pytest.importorskip("dynamixel_sdk")
    profile = PROFILES / "sim_arm.yaml"
    sim = start(served, "--profile", str(profile))
    (endpoint,) = sim.endpoints(1)
    assert endpoint["device"] == "arm"
    entry = yaml.safe_load(profile.read_text())["devices"]["arm"]
    entry["link"] = endpoint["link"]  # the profile line the command printed
    driver = DynamixelDriver.from_profile("arm", entry, clock=MonotonicClock(), where="arm")
    try:
        driver.configure()  # pings every servo and reads its model
        assert driver.joint_names[0] == "shoulder_pan"
    finally:
        driver.shutdown()
    assert sim.stop()[0] == 0


def test_a_profile_s_vehicle_is_reached_through_the_printed_link(served: list[Served]) -> None:
    profile = PROFILES / "sim_quad.yaml"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        port = gcs.getsockname()[1]
        sim = start(served, "--profile", str(profile), "--out", f"udp:127.0.0.1:{port}")
        (endpoint,) = sim.endpoints(1)
        assert endpoint["link"].startswith("udpin:127.0.0.1:")
        assert f"udp:127.0.0.1:{port}" in endpoint["streams_to"]
        receive(gcs, Codec(255, 190), "HEARTBEAT")  # the extra ground station hears it too
    entry = yaml.safe_load(profile.read_text())["devices"]["quad"]
    entry["link"] = endpoint["link"]
    driver = MavlinkDriver.from_profile("quad", entry, clock=MonotonicClock(), where="quad")
    try:
        driver.configure()  # waits for the vehicle's heartbeat
    finally:
        driver.shutdown()
    assert sim.until(event="message", name="HEARTBEAT")["device"] == "quad"
    assert sim.stop()[0] == 0


def test_out_needs_a_vehicle_in_the_profile() -> None:
    proc = sim_cli("--profile", str(PROFILES / "sim_arm.yaml"), "--out", "udp:127.0.0.1:14550")
    assert proc.returncode == 2
    assert "no MAVLink vehicle" in proc.stderr


# ---- CAN over udp_multicast, watched by python-can's own tools ---------------------------------


def _why_no_netns() -> str:
    if os.geteuid() != 0:
        return "needs root for unshare -n"
    if not (shutil.which("unshare") and shutil.which("ip")):
        return "needs unshare and ip"
    if importlib.util.find_spec("msgpack") is None:
        return "python-can's udp_multicast interface needs msgpack"
    return ""


NETNS_SCRIPT = r"""
import json, os, signal, subprocess, sys, time, pathlib, yaml
from temoto.clock import MonotonicClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.capabilities import ControlMode, JointCommand

profile, log = sys.argv[1], pathlib.Path(sys.argv[2])
sim = subprocess.Popen([sys.executable, "-m", "temoto", "sim", "--profile", profile, "--json"],
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
out = {}
try:
    endpoint = json.loads(sim.stdout.readline())["endpoint"]
    out["endpoint"] = endpoint
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "udp_multicast",
                               "-c", endpoint["link"]["channel"], "-f", str(log)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    # can.logger prints this once its bus is open: frames sent from now on are recorded
    while not logger.stdout.readline().startswith("Can Logger"):
        assert logger.poll() is None, logger.stderr.read()
    entry = yaml.safe_load(pathlib.Path(profile).read_text())["devices"]["base"]
    entry["link"] = endpoint["link"]  # the printed profile line
    entry["init_timeout"] = 3.0
    driver = ODriveDriver.from_profile("base", entry, clock=MonotonicClock(), where="base")
    try:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("left_wheel", ControlMode.VELOCITY, 2.0)])
        end = time.monotonic() + 5
        while driver.read_state().joints["left_wheel"].velocity < 1.9 and time.monotonic() < end:
            time.sleep(0.01)
        out["velocity"] = driver.read_state().joints["left_wheel"].velocity
    finally:
        driver.shutdown()
    time.sleep(0.5)
    logger.send_signal(signal.SIGINT)
    logger.wait(10)
    sim.send_signal(signal.SIGTERM)
    out["sim_rc"] = sim.wait(20)
    out["sim_err"] = sim.stderr.read()[-2000:]
finally:
    if sim.poll() is None:
        sim.kill()
ids = {}
for line in log.read_text().splitlines():  # canutils: (stamp) channel ID#DATA
    frame = next(word for word in line.split() if "#" in word)  # ID#DATA or ID#R (RTR)
    can_id = int(frame.split("#")[0], 16)
    ids[can_id] = ids.get(can_id, 0) + 1
out["ids"] = {str(k): v for k, v in ids.items()}
print(json.dumps(out))
"""


@pytest.mark.skipif(bool(_why_no_netns()), reason=_why_no_netns() or "ok")
def test_can_logger_records_the_profile_s_odrives_while_a_driver_drives_them(
    tmp_path: Path,
) -> None:
    script = (
        "ip link set lo up && ip route replace 224.0.0.0/4 dev lo && "
        f'exec "{sys.executable}" -c "$0" "$1" "$2"'
    )
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", script, NETNS_SCRIPT,
         str(PROFILES / "sim_rover.yaml"), str(tmp_path / "frames.log")],
        capture_output=True,
        text=True,
        timeout=90,
        env=env(),
        check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # the profile's virtual channel is served on python-can's own default multicast group
    assert result["endpoint"]["link"] == {"interface": "udp_multicast", "channel": "239.74.163.2"}
    assert result["endpoint"]["nodes"] == [1, 2]
    assert result["velocity"] > 1.9
    assert result["sim_rc"] == 0, result["sim_err"]
    ids = {int(k): v for k, v in result["ids"].items()}
    heartbeat, estimates = 1 << 5 | 0x01, 1 << 5 | 0x09  # node 1
    assert ids.get(heartbeat, 0) >= 5
    assert ids.get(estimates, 0) >= 50
    assert ids.get(1 << 5 | 0x0D, 0) >= 1  # the driver's Set_Input_Vel, seen on the bus too


# ---- the tools' own ways in ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "key", "ids"),
    [
        (("odrive", "--bus", "virtual", "--node", "3", "--node", "1"), "nodes", [1, 3]),
        (("mit", "--bus", "virtual", "--motor", "2:AK60-6", "--motor", "5"), "motors", [2, 5]),
    ],
)
def test_can_simulators_print_their_bus_and_ids(
    served: list[Served], args: tuple[str, ...], key: str, ids: list[int]
) -> None:
    sim = start(served, *args)
    (endpoint,) = sim.endpoints(1)
    assert endpoint["link"] == {"interface": "virtual", "channel": "temoto-sim"}
    assert endpoint[key] == ids
    assert sim.stop(signal.SIGINT)[0] == 0


def test_odrive_rates_are_printed_as_the_odrive_s_settings(served: list[Served]) -> None:
    sim = start(served, "odrive", "--bus", "virtual", "--node", "1", "--rate", "heartbeat=0",
                "--rate", "torques_msg_rate_ms=20")  # fmt: skip
    (endpoint,) = sim.endpoints(1)
    rates = endpoint["rates_ms"]
    assert rates["heartbeat_msg_rate_ms"] == 0
    assert rates["torques_msg_rate_ms"] == pytest.approx(20)
    assert rates["encoder_msg_rate_ms"] == pytest.approx(10)
    assert sim.stop()[0] == 0


def test_socat_exposes_the_chain_as_a_tcp_serial_port(served: list[Served]) -> None:
    socat = require_tool("socat", hint="apt-get install socat")
    serial = pytest.importorskip("serial")
    from temoto.drivers.dynamixel import protocol as dxl

    chain = start(served, "dynamixel", "--servo", "4:XM430-W350")
    (endpoint,) = chain.endpoints(1)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        tcp = probe.getsockname()[1]
    bridge = subprocess.Popen(
        [
            socat,
            f"TCP-LISTEN:{tcp},reuseaddr,bind=127.0.0.1",
            f"FILE:{endpoint['port']},raw,echo=0",
        ]
    )
    try:
        deadline = time.monotonic() + READ_TIMEOUT
        while True:  # until socat listens
            try:
                port = serial.serial_for_url(f"socket://127.0.0.1:{tcp}", timeout=2)
                break
            except serial.SerialException:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        with port:
            port.write(dxl.ping_packet(4))
            reply = b""
            while len(reply) < 14:  # a PING's status packet: 11 + 3 bytes
                more = port.read(14 - len(reply))
                assert more, f"no reply through socat, got {reply!r}"
                reply += more
        status = dxl.parse_packet(reply)
        assert status.id == 4
        assert dxl.from_le(status.params[:2]) == 1020  # XM430-W350's model number
    finally:
        bridge.terminate()
        bridge.wait(10)
    assert chain.stop()[0] == 0


@pytest.mark.parametrize("master", ["out", "vehicle"])
def test_mavproxy_detects_the_vehicle(served: list[Served], tmp_path: Path, master: str) -> None:
    mavproxy = require_tool("mavproxy.py", hint="pip install MAVProxy")
    out = free_udp_port()
    quad = start(served, "quad", "--port", "0", "--out", f"udp:127.0.0.1:{out}")
    (endpoint,) = quad.endpoints(1)
    # MAVProxy listening where the vehicle streams (udp:), or sending to it first (udpout:)
    url = f"udp:127.0.0.1:{out}" if master == "out" else endpoint["link"]
    proc = subprocess.Popen(
        [mavproxy, "--master", url, "--non-interactive", "--default-modules=mode"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,  # its telemetry log goes there
    )
    seen: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 60  # MAVProxy imports a lot on a loaded machine
        for line in proc.stdout:
            seen.append(line)
            if "Detected vehicle 1:1" in line or time.monotonic() > deadline:
                break
        assert any("Detected vehicle 1:1" in line for line in seen), "".join(seen)[-2000:]
        # MAVProxy's own heartbeat reaches the vehicle, which reports the client
        assert quad.until(event="message", name="HEARTBEAT")["device"] == "quad"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    assert quad.stop()[0] == 0


VIEWER_SCRIPT = r"""
import json, os, pty, re, select, signal, subprocess, sys, time
sim = subprocess.Popen([sys.executable, "-m", "temoto", "sim", "odrive", "--node", "1",
                        "--node", "2", "--json"], stdout=subprocess.PIPE,
                       stderr=subprocess.DEVNULL, text=True)
channel = json.loads(sim.stdout.readline())["endpoint"]["link"]["channel"]
pid, fd = pty.fork()  # can.viewer is a terminal program: give it one
if pid == 0:
    os.environ["TERM"] = "xterm"
    os.execv(sys.executable, [sys.executable, "-m", "can.viewer", "-i", "udp_multicast",
                              "-c", channel])
screen = b""
end = time.monotonic() + 20
wanted = (b"0x021", b"0x029", b"0x041", b"0x049")
while time.monotonic() < end and not all(i in screen for i in wanted):
    ready, _, _ = select.select([fd], [], [], 0.2)
    if ready:
        try:
            screen += os.read(fd, 65536)
        except OSError:
            break
os.kill(pid, signal.SIGINT)
os.waitpid(pid, 0)
sim.send_signal(signal.SIGINT)
ids = sorted(set(re.findall(r"0x0[0-9A-F]{2}", screen.decode(errors="replace"))))
print(json.dumps({"ids": ids, "sim_rc": sim.wait(20)}))
"""


@pytest.mark.skipif(bool(_why_no_netns()), reason=_why_no_netns() or "ok")
def test_can_viewer_shows_the_odrives_frames() -> None:
    script = (
        "ip link set lo up && ip route replace 224.0.0.0/4 dev lo && "
        f'exec "{sys.executable}" -c "$0"'
    )
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", script, VIEWER_SCRIPT],
        capture_output=True,
        text=True,
        timeout=90,
        env=env(),
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # node 1's and node 2's heartbeats (0x021, 0x041) and estimates (0x029, 0x049) on screen
    assert {"0x021", "0x029", "0x041", "0x049"} <= set(result["ids"])
    assert result["sim_rc"] == 0


def test_a_port_in_use_is_invalid_input(served: list[Served]) -> None:
    first = start(served, "quad", "--port", "0", "--out", "udp:127.0.0.1:9")
    (endpoint,) = first.endpoints(1)
    taken = endpoint["vehicle"].rsplit(":", 1)[1]
    proc = sim_cli("quad", "--port", taken)
    assert proc.returncode == 2
    assert "cannot start" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert first.stop()[0] == 0


BIND_SCRIPT = r"""
import socket, subprocess, sys
from temoto.drivers.mavlink.protocol import Codec
listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
listener.bind(("10.77.0.1", 0))
listener.settimeout(20)
port = listener.getsockname()[1]
sim = subprocess.Popen([sys.executable, "-m", "temoto", "sim", "quad", "--bind", "0.0.0.0",
                        "--port", "0", "--out", f"udp:10.77.0.1:{port}"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
try:
    codec = Codec(255, 190)
    while True:
        data, sender = listener.recvfrom(4096)
        if any(m.name == "HEARTBEAT" for m in codec.decode(data)):
            break
    print("heard", sender[0])
finally:
    sim.terminate()
    print("rc", sim.wait(20))
"""


@pytest.mark.skipif(bool(_why_no_netns()), reason=_why_no_netns() or "ok")
def test_a_vehicle_bound_to_a_network_address_streams_to_another_machine() -> None:
    # a network namespace with a network interface (one end of a veth pair) at 10.77.0.1:
    # the vehicle binds 0.0.0.0 and a ground station on that non-loopback address hears it
    script = (
        "ip link set lo up && ip link add temoto0 type veth peer name temoto1 && "
        "ip link set temoto0 up && ip link set temoto1 up && "
        "ip addr add 10.77.0.1/24 dev temoto0 && "
        f'exec "{sys.executable}" -c "$0"'
    )
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", script, BIND_SCRIPT],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "heard 10.77.0.1" in proc.stdout, proc.stdout + proc.stderr
    assert "rc 0" in proc.stdout, proc.stdout + proc.stderr


def test_bind_takes_an_address_of_this_host() -> None:
    proc = sim_cli("quad", "--bind", "not-an-address")
    assert proc.returncode == 2
    assert "IPv4 address" in proc.stderr
