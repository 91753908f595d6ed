"""Dynamixel safety: safe states, the Bus Watchdog, stale feedback, bad packets.

The Bus Watchdog and torque off are tested twice: against our simulator and against
:class:`EManualChain`, a small servo emulator written here from the ROBOTIS e-Manual (X series
control table, Protocol 2.0) without any of our protocol code. What each servo ends in is read
back by a separate dynamixel-sdk client after the driver closed its port.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from contract import eventually
from dxl_polled import follow
from dxl_sdk_client import Peer, SimLinks, patient_sim_links, sdk_client

from temoto.clock import Clock, ManualClock, MonotonicClock, ScaledClock
from temoto.drivers import ControlMode, DriverState, JointCommand
from temoto.drivers.dynamixel import driver as dxl_driver
from temoto.drivers.dynamixel import timing as dxl_timing
from temoto.drivers.dynamixel.driver import DynamixelDriver, poll_cycle_time
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.errors import DriverOperationError, DriverTimeoutError, ProfileError

dxl: Any = pytest.importorskip("dynamixel_sdk")

# The simulators are threads of this process: their replies wait for them, not for the clock
# (tests/drivers/dxl_sdk_client.py).
pytestmark = pytest.mark.usefixtures(patient_sim_links.__name__)

TORQUE, WATCHDOG, GOAL, PRESENT = 64, 98, 116, 132
RANGE_ERROR = 0x04  # Protocol 2.0 status error number "Data Range Error"
UNIT = 0.020  # Bus Watchdog unit (s)


def config(n: int = 3, **extra: Any) -> dict[str, Any]:
    servos = [
        {
            "id": i,
            "joint": f"j{i}",
            "model": "XM430-W350",
            "min_position": -2.0,
            "max_position": 2.0,
        }
        for i in range(1, n + 1)
    ]
    return {"link": "/dev/null", "baud": 1_000_000, "poll_rate": 50, "servos": servos, **extra}


def read1(client: tuple[Any, Any], dxl_id: int, address: int) -> int:
    port, ph = client
    for _ in range(3):
        value, result, _ = ph.read1ByteTxRx(port, dxl_id, address)
        if result == dxl.COMM_SUCCESS:
            return int(value)
    raise AssertionError(f"servo {dxl_id} did not answer READ {address}")


# ---- an emulator written from the e-Manual ------------------------------------------------------


def crc16(data: bytes) -> int:
    """CRC-16 of Protocol 2.0: polynomial 0x8005, initial value 0, MSB first, no reflection."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def packet(dxl_id: int, body: bytes) -> bytes:
    """Header, id, length (body + CRC), body (instruction or 0x55 + error, params), CRC."""
    stuffed = body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")
    head = b"\xff\xff\xfd\x00" + bytes([dxl_id]) + (len(stuffed) + 2).to_bytes(2, "little")
    frame = head + stuffed
    return frame + crc16(frame).to_bytes(2, "little")


class EManualServo:
    """One X-series servo's control table, as far as this test needs it."""

    def __init__(self, dxl_id: int) -> None:
        t = bytearray(256)
        t[0:2] = (1020).to_bytes(2, "little")  # Model Number: XM430-W350
        t[6] = 45  # Firmware Version (Bus Watchdog exists from v38)
        t[7] = dxl_id
        t[8] = 3  # Baud Rate: 1 Mbps
        t[9] = 250  # Return Delay Time
        t[11] = 3  # Operating Mode: position
        t[38:40] = (1193).to_bytes(2, "little")  # Current Limit
        t[44:48] = (200).to_bytes(4, "little")  # Velocity Limit
        t[48:52] = (4095).to_bytes(4, "little")  # Max Position Limit
        t[68] = 2  # Status Return Level
        t[116:120] = (2048).to_bytes(4, "little")  # Goal Position
        t[132:136] = (2048).to_bytes(4, "little")  # Present Position
        t[144:146] = (120).to_bytes(2, "little")  # Present Input Voltage
        t[146] = 30
        self.table = t
        self.id = dxl_id
        self.heard = 0.0  # when the last instruction packet for it arrived
        self.stopped = False

    def watchdog(self) -> int:
        return int.from_bytes(self.table[98:99], "little", signed=True)

    def step(self, now: float) -> None:
        """Bus Watchdog: while torque is on, a gap longer than 98 x 20 ms stops the servo."""
        units = self.watchdog()
        if self.table[64] == 1 and units > 0 and now - self.heard > units * UNIT:
            self.table[98] = 0xFF  # -1: Bus Watchdog error
            self.stopped = True
        if self.table[64] == 1 and not self.stopped:  # an ideal position servo
            self.table[132:136] = self.table[116:120]

    def write(self, address: int, data: bytes) -> int:
        """A WRITE; the error number of the status (0: done)."""
        end = address + len(data)
        if end > 256:
            return 0x07  # Data Length / access
        if address < 64 and self.table[64] == 1:
            return 0x07  # EEPROM only with torque off: Access Error
        goal_values = range(100, 120)  # Goal PWM(100), Current(102), Velocity(104), Position(116)
        if self.watchdog() == -1 and any(a in goal_values for a in range(address, end)):
            return RANGE_ERROR  # goal values are read-only while the watchdog error stands
        if address <= 98 < end:
            value = int.from_bytes(data[98 - address : 99 - address], "little", signed=True)
            if not 0 <= value <= 127:
                return RANGE_ERROR
        self.table[address:end] = data
        if address < 120 and end > 100:
            self.stopped = False
        return 0


class EManualChain:
    """Servos answering Protocol 2.0 on a pseudo-terminal (PING, READ, WRITE, SYNC_READ/WRITE)."""

    def __init__(self, ids: list[int], clock: Clock) -> None:
        self.clock = clock
        self.servos = {i: EManualServo(i) for i in ids}
        self.lock = threading.Lock()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._buffer = b""
        self.bytes_served = 0  # bytes read and answered (for the test's sdk_client)
        self.bytes_sent = 0  # bytes of replies written
        self.goal_writes = 0  # SYNC_WRITEs of Goal Position
        self.writes: list[tuple[int, int, bytes]] = []  # (id, address, data) of every WRITE
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        os.close(self._master)
        os.close(self._slave)

    def register(self, dxl_id: int, address: int, size: int = 1) -> int:
        with self.lock:
            servo = self.servos[dxl_id]
            servo.step(self.clock.monotonic())
            return int.from_bytes(servo.table[address : address + size], "little", signed=True)

    def _serve(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:
                continue
            self._buffer += data
            for dxl_id, inst, params in self._packets():
                with self.lock:
                    replies = self._handle(dxl_id, inst, params)
                for reply in replies:
                    self.bytes_sent += os.write(self._master, reply)
            self.bytes_served += len(data)

    def _packets(self) -> Iterator[tuple[int, int, bytes]]:
        while True:
            start = self._buffer.find(b"\xff\xff\xfd\x00")
            if start < 0 or len(self._buffer) < start + 7:
                return
            length = int.from_bytes(self._buffer[start + 5 : start + 7], "little")
            end = start + 7 + length
            if len(self._buffer) < end:
                return
            frame, self._buffer = self._buffer[start:end], self._buffer[end:]
            if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
                continue  # a bad CRC: dropped
            body = frame[7:-2].replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")
            yield frame[4], body[0], body[1:]

    def _handle(self, dxl_id: int, inst: int, params: bytes) -> list[bytes]:
        now = self.clock.monotonic()
        for servo in self.servos.values():
            servo.step(now)
        if dxl_id == 0xFE and inst in (0x82, 0x83):  # SYNC_READ / SYNC_WRITE
            address = int.from_bytes(params[0:2], "little")
            size = int.from_bytes(params[2:4], "little")
            if inst == 0x82:
                listed = [self.servos[i] for i in params[4:] if i in self.servos]
                for servo in listed:
                    servo.heard = now
                return [
                    packet(s.id, b"\x55\x00" + bytes(s.table[address : address + size]))
                    for s in listed
                ]
            self.goal_writes += address == GOAL
            for at in range(4, len(params), size + 1):
                servo = self.servos.get(params[at])
                if servo is not None:
                    servo.heard = now
                    servo.write(address, params[at + 1 : at + 1 + size])  # no status
            return []
        servo = self.servos.get(dxl_id)
        if servo is None:
            return []
        servo.heard = now
        if inst == 0x01:  # PING
            return [packet(dxl_id, b"\x55\x00" + bytes(servo.table[0:2]) + bytes(servo.table[6:7]))]
        if inst == 0x02:  # READ
            address = int.from_bytes(params[0:2], "little")
            size = int.from_bytes(params[2:4], "little")
            return [packet(dxl_id, b"\x55\x00" + bytes(servo.table[address : address + size]))]
        if inst == 0x03:  # WRITE
            self.writes.append((dxl_id, int.from_bytes(params[0:2], "little"), bytes(params[2:])))
            error = servo.write(int.from_bytes(params[0:2], "little"), params[2:])
            servo.step(now)
            return [packet(dxl_id, b"\x55" + bytes([error]))]
        return [packet(dxl_id, b"\x55\x02")]  # Instruction Error


@pytest.fixture
def emulator(patient_sim_links: SimLinks) -> Iterator[tuple[EManualChain, ManualClock]]:
    clock = ManualClock()
    chain = EManualChain([1, 2, 3], clock)
    patient_sim_links.add(chain)
    yield chain, clock
    chain.close()


# ---- Bus Watchdog -------------------------------------------------------------------------------


def hang_and_check_the_watchdog(
    driver: DynamixelDriver,
    clock: ManualClock,
    watchdog: Any,
    path: str,
    peer: Peer,
) -> None:
    """The driver stops writing; the servos stop and refuse goals within wd + one period."""
    wd, period = driver.bus_watchdog, driver.period
    assert [watchdog(i, WATCHDOG) for i in (1, 2, 3)] == [round(wd / UNIT)] * 3
    driver.command([JointCommand("j1", ControlMode.POSITION, 1.5)])
    driver._stop_polling()  # the process hangs: no more instruction packets
    stopped = clock.monotonic()
    clock.advance(wd - period - 0.001)  # the last packet went out at most a period ago
    assert [watchdog(i, WATCHDOG) for i in (1, 2, 3)] == [round(wd / UNIT)] * 3
    clock.advance(2 * period + 0.001)
    assert clock.monotonic() <= stopped + wd + period + 1e-9
    assert [watchdog(i, WATCHDOG) for i in (1, 2, 3)] == [-1, -1, -1]
    held = watchdog(1, PRESENT, 4)
    clock.advance(1.0)
    assert watchdog(1, PRESENT, 4) == held  # stopped (torque still on)
    assert watchdog(1, TORQUE) == 1
    driver.shutdown()  # torque off (the watchdog error stays until 0 is written)
    client = sdk_client(path, peer)
    port, ph = client
    try:
        assert [read1(client, i, WATCHDOG) for i in (1, 2, 3)] == [0xFF] * 3
        assert [read1(client, i, TORQUE) for i in (1, 2, 3)] == [0] * 3
        result, error = ph.write4ByteTxRx(port, 2, GOAL, 2100)
        assert (result, error & 0x7F) == (dxl.COMM_SUCCESS, RANGE_ERROR)  # goals refused
        assert ph.write1ByteTxRx(port, 2, WATCHDOG, 0) == (dxl.COMM_SUCCESS, 0)  # clears
        assert read1(client, 2, WATCHDOG) == 0
        assert ph.write4ByteTxRx(port, 2, GOAL, 2100) == (dxl.COMM_SUCCESS, 0)
    finally:
        port.closePort()


def test_bus_watchdog_on_the_simulator() -> None:
    clock = ManualClock()
    sim, entry = DynamixelDriver.simulate("arm", config(bus_watchdog=0.1), clock=clock)
    with sim:
        driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
        driver.configure()
        driver.activate()
        eventually(lambda: True, 0.05, clock)
        hang_and_check_the_watchdog(
            driver,
            clock,
            lambda i, a, size=1: sim.read_register(i, a),
            sim.path,
            sim,
        )


def test_the_simulated_bus_watchdog_counts_real_seconds_on_a_faster_clock() -> None:
    # The servo's watchdog guards against a silent host on the servo's own oscillator. A
    # ScaledClock speeds the motion up, not the host's scheduling: a process stall of 0.35 s
    # must not expire a 1 s watchdog in a demo at speed 5 (it did: 1.75 s of the clock).
    clock = ScaledClock(5)
    sim, entry = DynamixelDriver.simulate("arm", config(bus_watchdog=1.0), clock=clock)
    with sim:
        driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
        driver.configure()
        driver.activate()
        assert [sim.read_register(i, WATCHDOG) for i in (1, 2, 3)] == [50, 50, 50]
        driver._stop_polling()  # the process stalls: no more instruction packets
        hung = time.monotonic()
        time.sleep(0.35)  # 1.75 s of the clock
        if time.monotonic() - hung < 0.9:  # a loaded machine may oversleep: then no verdict
            assert [sim.read_register(i, WATCHDOG) for i in (1, 2, 3)] == [50, 50, 50]
        deadline = hung + 10.0
        while sim.read_register(1, WATCHDOG) != -1:  # expired
            assert time.monotonic() < deadline, "the watchdog never expired"
            time.sleep(0.01)
        assert time.monotonic() - hung >= 1.0  # not before one real second of silence
        driver.shutdown()


def test_bus_watchdog_on_the_e_manual_emulator(emulator: tuple[EManualChain, ManualClock]) -> None:
    chain, clock = emulator
    entry = config(bus_watchdog=0.1, link=f"serial:{chain.path}", reply_timeout=0.1)
    driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
    driver.configure()
    driver.activate()
    eventually(lambda: True, 0.05, clock)
    hang_and_check_the_watchdog(driver, clock, chain.register, chain.path, chain)


def test_no_servo_has_torque_before_its_watchdog_is_armed(
    emulator: tuple[EManualChain, ManualClock],
) -> None:
    # a SIGKILL may fall between any two writes of activate(): no moment may leave a servo
    # torqued and unwatched (the watchdog only watches while torque is on, so arming first is
    # harmless; a CI run once killed the command between servo 1's arming and servo 2's)
    chain, clock = emulator
    entry = config(bus_watchdog=0.1, link=f"serial:{chain.path}", reply_timeout=0.1)
    with DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        del chain.writes[:]
        driver.activate()
        writes = list(chain.writes)
    for dxl_id in (1, 2, 3):
        mine = [(address, data) for i, address, data in writes if i == dxl_id]
        torque_on = mine.index((TORQUE, b"\x01"))
        armed = [n for n, (address, data) in enumerate(mine) if address == WATCHDOG and data[0]]
        assert armed, mine
        assert armed[-1] < torque_on, mine


def test_steady_goal_writes_keep_the_watchdog_fed(
    emulator: tuple[EManualChain, ManualClock],
) -> None:
    chain, clock = emulator
    entry = config(bus_watchdog=0.06, link=f"serial:{chain.path}", reply_timeout=0.1)
    with DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j2", ControlMode.POSITION, 0.5)])
        writes = chain.goal_writes
        # Virtual time moves a poll period at a time, each step once the driver's write of the
        # step before arrived (lockstep: a loaded machine slows the test, it cannot starve the
        # poll thread of real time while the watchdog's virtual time runs on).
        for _ in range(25):  # 0.5 s at 50 Hz
            seen = chain.goal_writes
            clock.advance(driver.period)
            deadline = time.monotonic() + 10.0
            while chain.goal_writes == seen and time.monotonic() < deadline:
                time.sleep(0.0005)
            assert chain.goal_writes > seen, "no goal write in the poll period"
        assert [chain.register(i, WATCHDOG) for i in (1, 2, 3)] == [3, 3, 3]
        assert driver.state is DriverState.ACTIVE
        # one goal SYNC_WRITE per poll (50 Hz) although nothing was commanded meanwhile
        assert chain.goal_writes - writes >= 25
        assert chain.register(2, GOAL, 4) == driver.servos[1].ticks(0.5)


def test_activate_clears_an_expired_watchdog_first() -> None:
    clock = MonotonicClock()
    sim, entry = DynamixelDriver.simulate("arm", config(), clock=clock)
    with sim, DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        for i in (1, 2, 3):
            sim.write_register(i, WATCHDOG, -1)  # left over from an earlier run
        driver.activate()
        assert [sim.read_register(i, WATCHDOG) for i in (1, 2, 3)] == [25, 25, 25]  # 0.5 s
        driver.command([JointCommand("j3", ControlMode.POSITION, 0.7)])
        eventually(lambda: abs(driver.read_state().joints["j3"].position - 0.7) < 0.01, 3, clock)


@pytest.mark.parametrize(
    ("value", "poll_rate", "units"),
    [(None, 50, 25), (None, 2, 75), (0, 50, 0), (0.15, 50, 8), (None, 1, 0)],
)
def test_bus_watchdog_profile_values(value: float | None, poll_rate: float, units: int) -> None:
    extra = {} if value is None else {"bus_watchdog": value}
    driver = DynamixelDriver.from_profile(
        "arm", config(poll_rate=poll_rate, **extra), clock=MonotonicClock(), where="d"
    )
    assert driver.watchdog_units == units


@pytest.mark.parametrize("value", [0.02, 2.6, -1, "fast"])
def test_bad_bus_watchdog_values(value: Any) -> None:
    with pytest.raises(ProfileError, match=r"^d\.bus_watchdog: "):
        DynamixelDriver.from_profile(
            "arm", config(bus_watchdog=value), clock=MonotonicClock(), where="d"
        )


# ---- safe state ---------------------------------------------------------------------------------


@pytest.fixture
def chain() -> Iterator[tuple[DynamixelDriver, SimDynamixelChain, Clock]]:
    clock = MonotonicClock()
    sim, entry = DynamixelDriver.simulate("arm", config(6, poll_rate=100), clock=clock)
    sim.start()
    driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
    yield driver, sim, clock
    driver.shutdown()
    sim.close()


def test_safe_state_profile_key() -> None:
    make = DynamixelDriver.from_profile
    assert make("a", config(), clock=MonotonicClock(), where="d").safe_state == "torque_off"
    held = make("a", config(safe_state="hold"), clock=MonotonicClock(), where="d")
    assert held.safe_state == "hold"
    with pytest.raises(ProfileError, match=r"^d\.safe_state: must be one of torque_off, hold"):
        make("a", config(safe_state="brake"), clock=MonotonicClock(), where="d")


def test_torque_off_from_active_read_back_by_another_client(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, sim, _ = chain
    driver.configure()
    driver.activate()
    assert [sim.read_register(i, TORQUE) for i in range(1, 7)] == [1] * 6
    assert driver.make_safe("test") == "6 servos torque off"
    assert driver.state is DriverState.INACTIVE
    driver.shutdown()
    client = sdk_client(sim.path, sim)
    try:
        assert [read1(client, i, TORQUE) for i in range(1, 7)] == [0] * 6
    finally:
        client[0].closePort()


def test_torque_off_from_fault_is_sent_anyway(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, sim, clock = chain
    driver.configure()
    driver.activate()
    sim.inject("corrupt")  # the servos hear us, their replies are garbage
    eventually(lambda: driver.state is DriverState.FAULT, 3.0, clock)
    done = driver.make_safe("test")
    assert done is not None
    assert done.startswith("6 servos torque off sent; not confirmed"), done
    sim.clear()
    driver.shutdown()
    client = sdk_client(sim.path, sim)
    try:
        assert [read1(client, i, TORQUE) for i in range(1, 7)] == [0] * 6
    finally:
        client[0].closePort()


def test_torque_off_on_the_e_manual_emulator(emulator: tuple[EManualChain, ManualClock]) -> None:
    chain, clock = emulator
    entry = config(link=f"serial:{chain.path}", reply_timeout=0.1)
    driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
    driver.configure()
    driver.activate()
    assert [chain.register(i, TORQUE) for i in (1, 2, 3)] == [1, 1, 1]
    driver.shutdown()  # make_safe, then close
    client = sdk_client(chain.path, chain)
    try:
        assert [read1(client, i, TORQUE) for i in (1, 2, 3)] == [0, 0, 0]
    finally:
        client[0].closePort()


def test_hold_keeps_torque_and_stops_where_it_is() -> None:
    clock = ManualClock()
    sim, entry = DynamixelDriver.simulate("arm", config(safe_state="hold"), clock=clock)
    with sim:
        driver = DynamixelDriver.from_profile("arm", entry, clock=clock, where="a")
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j1", ControlMode.POSITION, 1.8)])
        # one poll period of virtual time per poll: the servo is where the driver last read it
        # (eventually's virtual time runs on while a loaded machine delays the polls)
        follow(driver, clock, lambda: driver.read_state().joints["j1"].position > 0.3, 3.0)
        assert driver.make_safe("test") == "3 servos hold"
        commanded = driver.servos[0].ticks(1.8)
        eventually(lambda: sim.read_register(1, GOAL) != commanded, 30.0)  # SYNC_WRITE: no reply
        goal = sim.read_register(1, GOAL)
        driver.shutdown()
        clock.advance(1.0)
        client = sdk_client(sim.path, sim)
        try:
            assert [read1(client, i, TORQUE) for i in (1, 2, 3)] == [1, 1, 1]
        finally:
            client[0].closePort()
        assert goal < driver.servos[0].ticks(1.0)  # not the commanded 1.8 rad
        assert abs(sim.read_register(1, PRESENT) - goal) <= 2


# ---- supervision --------------------------------------------------------------------------------


def test_a_hung_poll_makes_the_present_position_stale() -> None:
    clock = ManualClock()
    sim, entry = DynamixelDriver.simulate("arm", config(bus_watchdog=0), clock=clock)
    with sim, DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        driver.activate()
        driver._stop_polling()  # polls stop without any failed reply
        clock.advance(driver.feedback_max_age * 0.9)
        driver.read_state()
        assert driver.state is DriverState.ACTIVE
        clock.advance(driver.feedback_max_age * 0.2)
        driver.read_state()
        assert driver.state is DriverState.FAULT
        error = driver.health().error
        assert isinstance(error, DriverTimeoutError)
        assert "present position stale" in str(error)


def test_a_stall_of_the_process_is_judged_by_the_next_poll_not_by_the_stall(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # The poll thread wakes after a stall longer than the stream's limit (a loaded machine):
    # the chain answers its next poll, so the stream is fresh, not stale.
    clock = ManualClock()
    sim, entry = DynamixelDriver.simulate("arm", config(bus_watchdog=0), clock=clock)
    with sim, DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        driver.activate()
        polls = sim.stats["packets"]
        clock.advance(driver.feedback_max_age * 1.5)  # the stall: no poll meanwhile
        deadline = time.monotonic() + 10.0
        while sim.stats["packets"] < polls + 2:  # the poll after the stall (read and goals)
            assert time.monotonic() < deadline, "no poll after the stall"
            time.sleep(0.005)
        time.sleep(0.05)
        assert driver.state is DriverState.ACTIVE, driver.health().message
        faults = [r.getMessage() for r in caplog.records if "fault" in r.getMessage()]
        assert not faults, faults  # not even one that the next good poll cleared


def test_a_silent_chain_goes_stale_even_with_many_timeout_polls() -> None:
    clock = MonotonicClock()
    entry = config(timeout_polls=10_000, reply_timeout=0.02)
    sim, entry = DynamixelDriver.simulate("arm", entry, clock=clock)
    with sim, DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
        driver.configure()
        driver.activate()
        sim.inject("silence")
        eventually(lambda: driver.state is DriverState.FAULT, 3.0, clock)
        assert "present position stale" in driver.health().message
        assert "servos 1, 2, 3: no status packet reading" in driver.health().message  # last poll


def test_one_bad_packet_is_counted_a_burst_is_a_fault(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock], caplog: pytest.LogCaptureFixture
) -> None:
    driver, sim, clock = chain
    driver.configure()
    driver.activate()
    caplog.set_level(logging.INFO, logger="temoto.drivers.dynamixel")
    sim.inject("corrupt", replies=1)
    eventually(lambda: sim.fault("corrupt") is None, 3.0, clock)
    packets = sim.stats["packets"]
    eventually(lambda: sim.stats["packets"] > packets + 20, 3.0, clock)
    assert driver.state is DriverState.ACTIVE
    assert any("a bad status packet (1 within 1 s" in r.message for r in caplog.records)
    sim.inject("corrupt")
    eventually(lambda: driver.state is DriverState.FAULT, 3.0, clock)
    error = driver.health().error
    assert isinstance(error, DriverOperationError)
    assert "bad status packets within 1 s" in str(error)
    sim.clear()
    eventually(lambda: driver.state is DriverState.ACTIVE, 3.0, clock)


# ---- profile checks -----------------------------------------------------------------------------


def test_a_minimal_servo_entry_loads_inside_the_range() -> None:
    entry = {"link": "/dev/null", "servos": [{"id": 1, "joint": "j", "model": "XM430-W350"}]}
    driver = DynamixelDriver.from_profile("a", entry, clock=MonotonicClock(), where="d")
    servo = driver.servos[0]
    assert (servo.ticks(servo.min_position), servo.ticks(servo.max_position)) == (0, 4095)
    assert not servo.write_limits
    geared = {"id": 1, "joint": "j", "model": "XM430-W350", "gear": -2.0, "offset": 0.3}
    entry["servos"] = [geared]
    servo = DynamixelDriver.from_profile("a", entry, clock=MonotonicClock(), where="d").servos[0]
    assert sorted((servo.ticks(servo.min_position), servo.ticks(servo.max_position))) == [0, 4095]


def test_the_wire_time_formula() -> None:
    # 6 servos, 57600 baud, factory Return Delay Time 500 µs, status every 10 polls, watchdog:
    # bytes per cycle = 146 (SYNC_READ) + 44 (SYNC_WRITE) + 288 / 10 (three status reads).
    expected = 10 * (146 + 44 + 28.8) / 57600 + (6 + 1.8) * 500e-6
    assert poll_cycle_time(6, 57600, 500e-6, 10, True) == pytest.approx(expected)
    assert 1 / expected < 30  # six servos at 57600 baud top out at about 30 Hz


def test_a_poll_rate_the_wire_cannot_carry_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="temoto.drivers.dynamixel")
    DynamixelDriver.from_profile(
        "a", config(6, baud=57600), clock=MonotonicClock(), where="arm.yaml: devices.arm"
    )
    warned = [r.message for r in caplog.records if "cannot be met" in r.message]
    assert len(warned) == 1
    assert warned[0].startswith("arm.yaml: devices.arm.poll_rate: 50 Hz cannot be met")
    assert "6 servos at 57600 baud" in warned[0]
    caplog.clear()
    DynamixelDriver.from_profile("a", config(6), clock=MonotonicClock(), where="d")
    DynamixelDriver.from_profile(
        "a", config(6, baud=57600, poll_rate=20), clock=MonotonicClock(), where="d"
    )
    assert not [r for r in caplog.records if "cannot be met" in r.message]


def test_limits_and_return_delay_are_written_only_when_they_differ() -> None:
    clock = MonotonicClock()
    entry = config(return_delay_time=0.0)
    entry["servos"][2] = {"id": 3, "joint": "j3", "model": "XM430-W350"}  # no limits given
    sim, entry = DynamixelDriver.simulate("arm", entry, clock=clock)
    with sim:
        sim.write_register(1, TORQUE, 1)  # EEPROM is written with torque off only
        with DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
            driver.configure()
            low, high = driver.servos[0].limit_ticks()
        assert (low, high) == (driver.servos[0].ticks(-2.0), driver.servos[0].ticks(2.0))
        assert [sim.read_register(i, 9) for i in (1, 2, 3)] == [0, 0, 0]
        assert [sim.read_register(i, 52) for i in (1, 2, 3)] == [low, low, 0]
        assert [sim.read_register(i, 48) for i in (1, 2, 3)] == [high, high, 4095]
        writes = sim.stats["eeprom_writes"]
        assert writes == 3 + 2 * 2
        with DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
            driver.configure()
        assert sim.stats["eeprom_writes"] == writes


def test_the_usb_latency_timer_is_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="temoto.drivers.dynamixel")
    monkeypatch.setattr(dxl_timing, "USB_SERIAL_SYSFS", str(tmp_path))
    clock = MonotonicClock()
    sim, entry = DynamixelDriver.simulate("arm", config(1), clock=clock)
    with sim:
        tty_name = os.path.basename(os.path.realpath(sim.path))
        assert dxl_driver.latency_timer(sim.path) is None  # no such file: quietly skipped
        for value, warns in (("16\n", True), ("1\n", False)):
            (tmp_path / tty_name).mkdir(exist_ok=True)
            (tmp_path / tty_name / "latency_timer").write_text(value)
            caplog.clear()
            with DynamixelDriver.from_profile("arm", entry, clock=clock, where="a") as driver:
                driver.configure()
            found = [r.message for r in caplog.records if "latency timer" in r.message]
            assert bool(found) is warns, found
        assert dxl_driver.latency_timer(sim.path) == 1
