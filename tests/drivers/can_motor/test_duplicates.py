"""Two devices on one id are refused before anything is armed.

A second ODrive answering as node 1, or a second MIT motor answering as id 1, present from
the start: ``configure`` refuses with a message that says "duplicate", and the wire (watched by a
listener) shows that no axis was told a state and no motor entered motor mode.
"""

from __future__ import annotations

import time
import uuid

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimMitMotor, SimODrive
from temoto.errors import DriverInitError


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(0)) is not None:
        out.append(msg)
    return out


def odrive_entry(ch: str) -> dict[str, object]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "heartbeat_period": 0.1,
        "encoder_period": 0.01,
        "init_timeout": 0.5,
        "nodes": [{"node_id": 1, "joint": "left"}, {"node_id": 2, "joint": "right"}],
    }


def test_a_second_odrive_node_1_is_refused_before_arming() -> None:
    clock = ManualClock()
    ch = f"dup-odrive-{uuid.uuid4().hex[:8]}"
    link = {"interface": "virtual", "channel": ch}
    driver = ODriveDriver.from_profile("base", odrive_entry(ch), clock=clock, where="devices.base")
    with (
        SimODrive(link, [1, 2], clock),
        SimODrive(link, [1], clock),
        can.Bus(interface="virtual", channel=ch) as wire,
    ):
        try:
            with pytest.raises(DriverInitError, match="duplicate ODrive node 1") as info:
                driver.configure()
        finally:
            driver.shutdown()
        frames = drain(wire)
    assert "(left)" in str(info.value)
    assert "Nothing was armed" in str(info.value)
    kinds = {cs.split_id(m.arbitration_id)[1] for m in frames}
    assert cs.Cmd.SET_AXIS_STATE not in kinds


#: Real seconds between two heartbeat requests of the duplicate probe (sent in one loop).
BURST_GAP_S = 0.003


class LateAnswers:
    """Extra heartbeats of node 1 once, during the duplicate probe (its requests are a burst).

    On a busy machine answers to earlier requests can arrive together, late, during the probe
    (seen: "12 heartbeats answered 6 requests"). One device on the id answers the next probe
    normally, so the driver must not call it a duplicate.
    """

    def __init__(self, channel: str, extra: int) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.extra, self.sent, self.previous = extra, 0, -1.0
        self.notifier = can.Notifier(self.bus, [self.on_frame])

    def on_frame(self, msg: can.Message) -> None:
        node, cmd = cs.split_id(msg.arbitration_id)
        if self.sent or node != 1 or cmd != cs.Cmd.HEARTBEAT or not msg.is_remote_frame:
            return
        now = time.monotonic()
        if now - self.previous > BURST_GAP_S:  # the probe's requests come back to back
            self.previous = now
            return
        beat = cs.encode_heartbeat(0, cs.AxisState.IDLE)
        for _ in range(self.extra):
            self.bus.send(can.Message(arbitration_id=msg.arbitration_id, data=beat,
                                      is_extended_id=False))  # fmt: skip
        self.sent = self.extra

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def test_a_burst_of_late_answers_is_not_a_duplicate() -> None:
    # 6 late answers during the first probe: 12 and more, over one device's 11
    clock = ManualClock()
    ch = f"dup-odrive-{uuid.uuid4().hex[:8]}"
    driver = ODriveDriver.from_profile("base", odrive_entry(ch), clock=clock, where="devices.base")
    with SimODrive({"interface": "virtual", "channel": ch}, [1, 2], clock):
        late = LateAnswers(ch, extra=6)
        try:
            driver.configure()
            assert late.sent == 6
        finally:
            late.close()
            driver.shutdown()


def test_one_odrive_per_node_is_not_a_duplicate() -> None:
    clock = ManualClock()
    ch = f"dup-odrive-{uuid.uuid4().hex[:8]}"
    driver = ODriveDriver.from_profile("base", odrive_entry(ch), clock=clock, where="devices.base")
    with SimODrive({"interface": "virtual", "channel": ch}, [1, 2], clock):
        try:
            driver.configure()
            driver.activate()
        finally:
            driver.shutdown()


def test_a_second_mit_motor_1_is_refused_before_motor_mode() -> None:
    clock = ManualClock()
    ch = f"dup-mit-{uuid.uuid4().hex[:8]}"
    link = {"interface": "virtual", "channel": ch}
    entry = {
        "link": link,
        "poll_rate": 10.0,
        "init_timeout": 0.5,
        "motors": [
            {"motor_id": 1, "joint": "shoulder", "model": "AK80-9"},
            {"motor_id": 2, "joint": "elbow", "model": "AK80-9"},
        ],
    }
    driver = MitMotorDriver.from_profile("arm", entry, clock=clock, where="devices.arm")
    with (
        SimMitMotor(link, [1, 2], clock),
        SimMitMotor(link, [1], clock),
        can.Bus(interface="virtual", channel=ch) as wire,
    ):
        try:
            with pytest.raises(DriverInitError, match="duplicate MIT motor id 1") as info:
                driver.configure()
        finally:
            driver.shutdown()
        frames = drain(wire)
    assert "(shoulder)" in str(info.value)
    sent = [bytes(m.data) for m in frames if m.arbitration_id in (1, 2)]
    assert sent
    assert mm.CMD_ENTER not in sent
