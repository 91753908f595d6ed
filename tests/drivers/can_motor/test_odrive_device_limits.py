"""An ODrive profile's limits against the device, read over CAN (RxSdo) before anything is written.

Against the simulator (``SimODrive``) and against a small emulator written here from the
documents alone (the official DBC, decoded and encoded with cantools, and ODrive's
``can_param_access.py`` example): it answers the RTR requests for heartbeat, estimates and
``Get_Version`` and the ``RxSdo`` reads, nothing else. Every frame the driver sends is watched
on the bus and decoded with the DBC.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import uuid
from pathlib import Path
from typing import Any

import can
import cantools
import odrive_can
import pytest

from temoto.clock import MonotonicClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimODrive
from temoto.drivers.can_motor.sim_model import AxisModel
from temoto.errors import DeviceLimitError, DriverInitError, ProfileError

DBC = Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc"
DB: Any = cantools.database.load_file(str(DBC))


def decode(msg: can.Message) -> dict[str, Any]:
    """A frame's signals by the DBC, as numbers (not the DBC's choice names)."""
    return dict(DB.decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False))


#: What a host may not send before the check (an axis state, limits, modes, set-points).
WRITES = {
    cs.Cmd.SET_AXIS_STATE,
    cs.Cmd.SET_CONTROLLER_MODE,
    cs.Cmd.SET_INPUT_POS,
    cs.Cmd.SET_INPUT_VEL,
    cs.Cmd.SET_INPUT_TORQUE,
    cs.Cmd.SET_LIMITS,
    cs.Cmd.SET_TRAJ_VEL_LIMIT,
    cs.Cmd.SET_TRAJ_ACCEL_LIMITS,
    cs.Cmd.CLEAR_ERRORS,
    cs.Cmd.ESTOP,
    cs.Cmd.REBOOT,
}

#: The endpoint ids of firmware 0.6.10 on an ODrive Pro (4.4-58) the emulator serves, written
#: out here (not taken from the code under test).
EMULATED_IDS = {388: "vel_limit", 271: "current_soft_max", 259: "torque_constant"}


def entry(ch: str, *nodes: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "heartbeat_period": 1.0,  # the emulator answers requests only
        "init_timeout": 1.0,
        "nodes": list(nodes),
        **extra,
    }


class Watcher:
    """Every frame on a virtual channel, seen from a bus of its own."""

    def __init__(self, ch: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=ch)
        self.frames: list[can.Message] = []

    def take(self) -> list[can.Message]:
        """What queued so far (the simulator's cyclic frames go on: stop at an empty queue)."""
        while (msg := self.bus.recv(0)) is not None:
            self.frames.append(msg)
        return self.frames

    def from_host(self) -> list[tuple[int, int, can.Message]]:
        """(node, cmd, frame) of every frame a host sends (requests and commands)."""
        out = []
        for msg in self.take():
            node, cmd = cs.split_id(msg.arbitration_id)
            host = msg.is_remote_frame or cmd == cs.Cmd.RXSDO or cmd in WRITES
            if host:
                out.append((node, cmd, msg))
        return out


@pytest.fixture
def channel() -> str:
    return f"odl-{uuid.uuid4().hex[:8]}"


def configure(config: dict[str, Any], where: str = "robot.yaml: devices.base") -> ODriveDriver:
    driver = ODriveDriver.from_profile("base", config, clock=MonotonicClock(), where=where)
    try:
        driver.configure()
    except BaseException:
        driver.shutdown()
        raise
    return driver


def assert_nothing_written(watcher: Watcher) -> list[dict[str, Any]]:
    """No write reached the bus; the RxSdo frames (decoded with the DBC) were all reads."""
    reads = []
    for node, cmd, msg in watcher.from_host():
        assert cmd not in WRITES, f"node {node}: {cs.Cmd(cmd).name} sent"
        if cmd == cs.Cmd.RXSDO:
            fields = decode(msg)
            assert fields["Opcode"] == 0, fields  # a read
            reads.append({"node": node, **fields})
    return reads


# ---- against the simulator ------------------------------------------------------------------


def test_a_velocity_limit_beyond_the_device_s_vel_limit_is_refused_naming_file_node_key(
    channel: str,
) -> None:
    watcher = Watcher(channel)
    link = {"interface": "virtual", "channel": channel}
    with (
        watcher.bus,
        SimODrive(link, [AxisModel(1, vel_limit=2.0), AxisModel(2)], MonotonicClock()),
    ):
        with pytest.raises(DeviceLimitError) as caught:
            configure(
                entry(
                    channel,
                    {"node_id": 1, "joint": "left", "velocity_limit": 20.0},  # 3.18 turn/s > 2
                    {"node_id": 2, "joint": "right", "velocity_limit": 20.0},
                )
            )
        reads = assert_nothing_written(watcher)
    text = str(caught.value)
    assert isinstance(caught.value, ProfileError)  # exit 2, one line
    assert isinstance(caught.value, DriverInitError)  # configure failed
    assert text.startswith("robot.yaml: devices.base.nodes[0].velocity_limit: 20 rad/s"), text
    assert "node 1 (left)" in text, text
    assert "2 turn/s" in text, text
    assert "nodes[1]" not in text, text
    assert "\n" not in text
    # vel_limit (388), current_soft_max (271), torque_constant (259) of both nodes, by the DBC
    assert {(r["node"], r["Endpoint_ID"]) for r in reads} >= {
        (n, e) for n in (1, 2) for e in (388, 271, 259)
    }


def test_a_torque_limit_beyond_torque_constant_times_current_soft_max_is_refused(
    channel: str,
) -> None:
    link = {"interface": "virtual", "channel": channel}
    with SimODrive(link, [1], MonotonicClock()):  # 0.04 N·m/A x 10 A = 0.4 N·m at the motor
        with pytest.raises(DeviceLimitError) as caught:
            configure(entry(channel, {"node_id": 1, "joint": "w", "torque_limit": 2.0}))
        assert "devices.base.nodes[0].torque_limit: 2 N·m" in str(caught.value)
        assert "0.4 N·m" in str(caught.value)
        # a gearbox multiplies what the motor makes: 3.9 N·m at the joint is 0.39 at the motor
        geared = {"node_id": 1, "joint": "w", "gear_ratio": 10.0, "torque_limit": 3.9}
        configure(entry(channel, geared | {"velocity_limit": 31.0})).shutdown()


def test_limits_within_the_device_s_are_taken_and_nothing_is_written(channel: str) -> None:
    watcher = Watcher(channel)
    link = {"interface": "virtual", "channel": channel}
    with watcher.bus, SimODrive(link, [1, 2], MonotonicClock()):
        node = {"velocity_limit": 300.0, "torque_limit": 0.4}  # 47.7 of 50 turn/s; 0.4 N·m
        driver = configure(
            entry(channel, {"node_id": 1, "joint": "l", **node}, {"node_id": 2, "joint": "r"})
        )
        reads = assert_nothing_written(watcher)  # (shutdown sets the axes IDLE)
        driver.shutdown()
    assert {r["node"] for r in reads} == {1}  # node 2 has no limit to check


def test_the_device_as_configured_counts_set_limits_and_rxsdo_writes(channel: str) -> None:
    link = {"interface": "virtual", "channel": channel}
    sim = SimODrive(link, [1], MonotonicClock())
    config = entry(channel, {"node_id": 1, "joint": "w", "velocity_limit": 60.0})  # 9.5 turn/s
    with sim, can.Bus(interface="virtual", channel=channel) as host:
        configure(config).shutdown()
        host.send(  # Set_Limits: vel_limit 5 turn/s, current limit 10 A (DBC layout)
            can.Message(
                arbitration_id=cs.arbitration_id(1, cs.Cmd.SET_LIMITS),
                data=DB.encode_message(
                    "Axis1_Set_Limits", {"Velocity_Limit": 5.0, "Current_Limit": 10.0}
                ),
                is_extended_id=False,
            )
        )
        with pytest.raises(DeviceLimitError, match="above the 5 turn/s"):
            configure(config)
        # an RxSdo write of vel_limit (opcode 1, endpoint 388, float32), unanswered in 0.6.10
        value = struct.unpack("<I", struct.pack("<f", 12.0))[0]
        data = DB.encode_message(
            "Axis1_RxSdo", {"Opcode": 1, "Endpoint_ID": 388, "Reserved": 0, "Value": value}
        )
        host.send(
            can.Message(
                arbitration_id=cs.arbitration_id(1, cs.Cmd.RXSDO), data=data, is_extended_id=False
            )
        )
        configure(config).shutdown()
        assert sim.axes[1].vel_limit == 12.0


def test_the_simulator_answers_rxsdo_reads_in_the_dbc_layout_and_ignores_unknown_ids(
    channel: str,
) -> None:
    link = {"interface": "virtual", "channel": channel}
    sim = SimODrive(link, [3], MonotonicClock(), heartbeat_period=0, encoder_period=0)
    with sim, can.Bus(interface="virtual", channel=channel) as host:
        rx = cs.arbitration_id(3, cs.Cmd.RXSDO)

        def read(endpoint: int) -> dict[str, Any] | None:
            data = DB.encode_message(
                "Axis3_RxSdo", {"Opcode": 0, "Endpoint_ID": endpoint, "Reserved": 0, "Value": 0}
            )
            host.send(can.Message(arbitration_id=rx, data=data, is_extended_id=False))
            while (msg := host.recv(0.5)) is not None:
                if msg.arbitration_id == cs.arbitration_id(3, cs.Cmd.TXSDO):
                    return dict(decode(msg))
            return None

        def as_float(fields: dict[str, Any] | None) -> float:
            assert fields is not None
            return float(struct.unpack("<f", struct.pack("<I", int(fields["Value"])))[0])

        got = read(259)
        assert got is not None
        assert (got["Reserved0"], got["Endpoint_ID"], got["Reserved1"]) == (0, 259, 0)
        assert as_float(got) == pytest.approx(0.04)  # torque_constant
        assert as_float(read(271)) == 10.0  # current_soft_max
        assert as_float(read(272)) == 20.0  # current_hard_max
        assert as_float(read(388)) == 50.0  # vel_limit
        assert read(4242) is None  # an id the firmware does not have: no answer
        assert sim.sdo_unknown == 1


# ---- against an emulator written from the documents -----------------------------------------


class Emulator:
    """ODrive axes from the DBC alone: RTR heartbeat / estimates / Get_Version, RxSdo reads.

    Args:
        ch: The virtual channel.
        values: Per node, ``{endpoint id: float}``.
        version: The ``Get_Version`` fields (firmware 0.6.10 on an ODrive Pro by default).
    """

    def __init__(
        self,
        ch: str,
        values: dict[int, dict[int, float]],
        version: tuple[int, ...] = (2, 4, 4, 58, 0, 6, 10, 0),
    ) -> None:
        self.bus = can.Bus(interface="virtual", channel=ch)
        self.values = values
        self.version = version
        self.reads: list[tuple[int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="temoto-test-emulator")

    def __enter__(self) -> Emulator:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()

    def _send(self, name: str, node: int, fields: dict[str, Any]) -> None:
        message = DB.get_message_by_name(f"Axis{node}_{name}")
        self.bus.send(
            can.Message(
                arbitration_id=message.frame_id, data=message.encode(fields), is_extended_id=False
            )
        )

    def _run(self) -> None:
        names = [
            "Protocol_Version",
            "Hw_Version_Major",
            "Hw_Version_Minor",
            "Hw_Version_Variant",
            "Fw_Version_Major",
            "Fw_Version_Minor",
            "Fw_Version_Revision",
            "Fw_Version_Unreleased",
        ]
        while not self._stop.is_set():
            msg = self.bus.recv(0.02)
            if msg is None:
                continue
            node, cmd = msg.arbitration_id >> 5, msg.arbitration_id & 0x1F
            if node not in self.values:
                continue
            if msg.is_remote_frame and cmd == 0x01:
                heartbeat = {"Axis_Error": 0, "Axis_State": 1, "Procedure_Result": 0}
                self._send("Heartbeat", node, heartbeat | {"Trajectory_Done_Flag": 0})
            elif msg.is_remote_frame and cmd == 0x09:
                self._send("Get_Encoder_Estimates", node, {"Pos_Estimate": 0, "Vel_Estimate": 0})
            elif msg.is_remote_frame and cmd == 0x00:
                self._send("Get_Version", node, dict(zip(names, self.version, strict=True)))
            elif not msg.is_remote_frame and cmd == 0x04:
                fields = DB.decode_message(
                    msg.arbitration_id, bytes(msg.data), decode_choices=False
                )
                endpoint = int(fields["Endpoint_ID"])
                if fields["Opcode"] != 0 or endpoint not in self.values[node]:
                    continue
                self.reads.append((node, endpoint))
                raw = struct.unpack("<I", struct.pack("<f", self.values[node][endpoint]))[0]
                tx = {"Reserved0": 0, "Endpoint_ID": endpoint, "Reserved1": 0, "Value": raw}
                self._send("TxSdo", node, tx)


def pro(vel_limit: float = 10.0, soft_max: float = 20.0, kt: float = 0.1) -> dict[int, float]:
    return {388: vel_limit, 271: soft_max, 259: kt}


def test_the_emulated_device_s_limits_refuse_the_profile(channel: str) -> None:
    with Emulator(channel, {5: pro(vel_limit=10.0, soft_max=20.0, kt=0.1)}) as emulator:
        with pytest.raises(DeviceLimitError) as caught:
            configure(  # 70 rad/s is 11.1 turn/s > 10; 2.5 N·m > 0.1 x 20 = 2 N·m
                entry(
                    channel,
                    {"node_id": 5, "joint": "w", "velocity_limit": 70.0, "torque_limit": 2.5},
                )
            )
        assert sorted(set(emulator.reads)) == [(5, 259), (5, 271), (5, 388)]
    text = str(caught.value)
    assert "devices.base.nodes[0].velocity_limit: 70 rad/s" in text, text
    assert "devices.base.nodes[0].torque_limit: 2.5 N·m" in text, text
    assert "above the 10 turn/s node 5 (w)" in text, text
    assert "above the 2 N·m node 5 (w)" in text, text


def test_the_emulated_device_takes_limits_within_its_own(channel: str) -> None:
    with Emulator(channel, {5: pro(), 6: pro(vel_limit=4.0)}) as emulator:
        nodes = [
            {"node_id": 5, "joint": "a", "velocity_limit": 62.8, "torque_limit": 2.0},
            {"node_id": 6, "joint": "b", "gear_ratio": 0.5, "velocity_limit": 50.0},
        ]
        configure(entry(channel, *nodes)).shutdown()
        assert {e for n, e in emulator.reads if n == 6} == {259, 271, 388}  # checked, taken


def test_a_silent_endpoint_read_times_out_naming_node_and_endpoint(channel: str) -> None:
    values = {5: {388: 10.0, 271: 20.0}}  # no torque_constant: never answered
    with Emulator(channel, values), pytest.raises(DriverInitError) as caught:
        configure(entry(channel, {"node_id": 5, "joint": "w", "torque_limit": 1.0}))
    assert not isinstance(caught.value, ProfileError)
    assert "no TxSdo answer" in str(caught.value)
    assert "axis0.config.motor.torque_constant (endpoint 259)" in str(caught.value)


def test_an_unknown_firmware_is_refused_or_skipped_with_one_line(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    newer = (2, 4, 4, 58, 0, 6, 11, 0)
    node = {"node_id": 5, "joint": "w", "velocity_limit": 999.0}
    with Emulator(channel, {5: pro()}, version=newer) as emulator:
        with pytest.raises(DeviceLimitError) as caught:
            configure(entry(channel, node))
        text = str(caught.value)
        assert text.startswith(
            "robot.yaml: devices.base.nodes[0]: node 5 (w) runs ODrive firmware 0.6.11"
            " on hardware 4.4-58"
        ), text
        assert "check_device_limits: false" in text, text
        assert "flat_endpoints" in text, text
        assert emulator.reads == []
        with caplog.at_level(logging.WARNING):
            configure(entry(channel, node, check_device_limits=False)).shutdown()
        assert "not checked" in caplog.text
        assert emulator.reads == []


def test_a_release_s_flat_endpoints_file_gives_the_ids(channel: str, tmp_path: Path) -> None:
    flat = {
        "fw_version": "0.6.11",
        "hw_version": "4.4.58",
        "endpoints": {
            "axis0.controller.config.vel_limit": {"id": 400, "type": "float", "access": "rw"},
            "axis0.config.motor.current_soft_max": {"id": 300, "type": "float"},
            "axis0.config.motor.torque_constant": {"id": 290, "type": "float"},
        },
    }
    (tmp_path / "flat_endpoints.json").write_text(json.dumps(flat))
    (tmp_path / "bad.json").write_text(json.dumps({"endpoints": {}}))
    newer = (2, 4, 4, 58, 0, 6, 11, 0)
    values = {5: {400: 3.0, 300: 20.0, 290: 0.1}}
    where = f"{tmp_path / 'robot.yaml'}: devices.base"
    with Emulator(channel, values, version=newer) as emulator:
        config = entry(channel, {"node_id": 5, "joint": "w", "velocity_limit": 20.0})
        with pytest.raises(DeviceLimitError, match="above the 3 turn/s"):
            configure(config | {"flat_endpoints": "flat_endpoints.json"}, where)  # beside it
        assert sorted(set(emulator.reads)) == [(5, 290), (5, 300), (5, 400)]
    with pytest.raises(ProfileError, match=r"devices\.base\.flat_endpoints: .*names no fw_version"):
        configure(config | {"flat_endpoints": "bad.json"}, where)
