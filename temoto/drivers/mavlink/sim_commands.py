"""The simulated ArduCopter's answers: what it does with each message it receives.

:class:`CommandHandler` dispatches one received message by name: the GCS's HEARTBEAT (for the
failsafe), the parameter protocol (list, read, set; the ``.param`` file written back), the
mission protocol (to :class:`~temoto.drivers.mavlink.sim_mission.MissionService`) and the
guided forms of MISSION_ITEM, COMMAND_LONG and COMMAND_INT (each answered with a COMMAND_ACK
and then any STATUSTEXT saying why, as ArduPilot orders them), SET_MODE,
SET_POSITION_TARGET_GLOBAL_INT, REQUEST_DATA_STREAM, TIMESYNC and MAVLink FTP (NAKed: the
vehicle has no files). :meth:`CommandHandler.handle` takes the lock itself and returns the
frames to send back. A part of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`).
"""

from __future__ import annotations

import logging
import math
from typing import ClassVar, Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Message
from temoto.drivers.mavlink.sim_auto import AutoMission
from temoto.drivers.mavlink.sim_failsafe import Failsafes
from temoto.drivers.mavlink.sim_flight import FlightModel
from temoto.drivers.mavlink.sim_mission import MissionItem
from temoto.drivers.mavlink.sim_params import READ_ONLY, save_param_file
from temoto.drivers.mavlink.sim_state import STREAM_GROUPS, VehicleState
from temoto.drivers.mavlink.sim_telemetry import VehicleTelemetry

__all__ = ["CommandHandler"]

logger = logging.getLogger(__name__)

_FORCE_DISARM: Final = 21196.0  # ArduPilot's magic param2 of a forced disarm

_BANNER: Final = ("ArduCopter V4.5.7 (temoto simulator)", "Frame: QUAD/X")

_FTP_SESSION_OPS: Final = frozenset(
    {p.FTP_OP_READ_FILE, p.FTP_OP_WRITE_FILE, p.FTP_OP_BURST_READ_FILE, 12}  # 12: truncate
)


class CommandHandler:
    """The vehicle's answers to received messages (see the module docstring).

    Args:
        state: The vehicle's state.
        telemetry: Builds the answers.
        auto: The mission (MISSION_SET_CURRENT, MISSION_START, a changed plan).
        flight: Arming, modes, takeoff, reposition, home.
        failsafes: Told of the GCS's heartbeats.
    """

    _MISSION_MESSAGES: ClassVar[frozenset[str]] = frozenset(
        {
            "MISSION_COUNT",
            "MISSION_ITEM_INT",
            "MISSION_ITEM",
            "MISSION_REQUEST_LIST",
            "MISSION_REQUEST_INT",
            "MISSION_REQUEST",
            "MISSION_CLEAR_ALL",
            "MISSION_ACK",
        }
    )

    def __init__(
        self,
        state: VehicleState,
        telemetry: VehicleTelemetry,
        auto: AutoMission,
        flight: FlightModel,
        failsafes: Failsafes,
    ) -> None:
        self.state = state
        self.telemetry = telemetry
        self.auto = auto
        self.flight = flight
        self.failsafes = failsafes
        #: Every COMMAND_LONG/COMMAND_INT answered: (command, MAV_RESULT), oldest first.
        self.acks: list[tuple[int, int]] = []

    def handle(self, msg: Message) -> list[bytes]:
        """Act on one received message (takes the lock).

        Args:
            msg: The message.

        Returns:
            The frames to send back.
        """
        target = msg.fields.get("target_system")
        if target not in (None, 0, self.state.codec.system_id):
            return []
        if msg.fields.get("target_component") not in (None, 0, self.state.codec.component_id):
            return []  # for another component of this system (a camera, a gimbal)
        name = msg.name
        if name == "HEARTBEAT":
            with self.state.lock:
                if msg.src_system == round(self.state.params["SYSID_MYGCS"]):
                    self.failsafes.gcs_heartbeat(self.state.clock.monotonic())
            return []
        if name == "PARAM_REQUEST_LIST":
            with self.state.lock:
                self.state.texts.extend((p.MAV_SEVERITY_INFO, text) for text in _BANNER)
                self.telemetry.list_params()
            return []
        if name in ("PARAM_REQUEST_READ", "PARAM_SET"):
            return self._param_message(msg)
        if name in ("MISSION_ITEM_INT", "MISSION_ITEM") and msg.get_int("current") in (2, 3):
            return self._guided_item(msg)
        if name in self._MISSION_MESSAGES:
            with self.state.lock:
                frames = self.state.plans.handle(msg, self.state.clock.monotonic())
                self.auto.check_plan()
            return frames
        if name == "MISSION_SET_CURRENT":
            with self.state.lock:
                self.auto.set_current(msg.get_int("seq"))
                frames, self.state.outbox = self.state.outbox, []
            return frames
        if name in ("COMMAND_LONG", "COMMAND_INT"):
            cmd = msg.get_int("command")
            with self.state.lock:
                result, extra = self._command(msg, cmd)
                self.acks.append((cmd, result))
                texts, self.state.texts = self.state.texts, []
            ack = self.state.codec.encode(
                "COMMAND_ACK",
                command=cmd,
                result=result,
                progress=0,
                result_param2=0,
                target_system=msg.src_system,
                target_component=msg.src_component,
            )
            return [ack, *extra, *self.telemetry.text_frames(texts)]  # ArduPilot: the reason after
        if name == "SET_MODE":
            custom = msg.get_int("custom_mode")
            with self.state.lock:
                result = self.flight.set_mode(p.mode_name(custom))
                texts, self.state.texts = self.state.texts, []
            ack = self.state.codec.encode(
                "COMMAND_ACK",
                command=p.MSG_ID["SET_MODE"],
                result=result,
                target_system=msg.src_system,
                target_component=msg.src_component,
            )
            return [ack, *self.telemetry.text_frames(texts)]
        if name == "SET_POSITION_TARGET_GLOBAL_INT":
            if msg.get_int("type_mask") & 0b111 == 0:
                with self.state.lock:
                    frame = msg.get_int("coordinate_frame")
                    self.flight.reposition(
                        msg.get_int("lat_int") / 1e7,
                        msg.get_int("lon_int") / 1e7,
                        msg.get_float("alt"),
                        amsl=frame in (p.MAV_FRAME_GLOBAL, p.MAV_FRAME_GLOBAL_INT),
                        change_mode=False,
                    )
            return []
        if name == "REQUEST_DATA_STREAM":
            self._request_data_stream(msg)
            return []
        if name == "TIMESYNC":
            if msg.get_int("tc1") != 0:
                return []  # an answer to someone's request, not a request
            now_ns = round((self.state.clock.monotonic() - self.state.t0) * 1e9)
            return [self.state.codec.encode("TIMESYNC", tc1=max(now_ns, 1), ts1=msg.get_int("ts1"))]
        if name == "FILE_TRANSFER_PROTOCOL":
            return self._ftp(msg)
        return []

    def _param_message(self, msg: Message) -> list[bytes]:
        """PARAM_REQUEST_READ and PARAM_SET: the PARAM_VALUE answer (none if unknown).

        As ArduPilot: a read by index answers with that index, a read by name and the echo of
        a set with index -1 (65535 on the wire); a read-only parameter is not changed ("Param
        write denied" and its value).
        """
        name = msg.get_text("param_id")
        index = -1
        frames: list[bytes] = []
        with self.state.lock:
            if msg.name == "PARAM_REQUEST_READ" and msg.get_int("param_index") >= 0:
                index = msg.get_int("param_index")
                if index >= len(self.state.names):
                    return []
                name = self.state.names[index]
            if name not in self.state.params:
                return []
            if msg.name == "PARAM_SET":
                value = msg.get_float("param_value")
                if not math.isfinite(value):
                    return []
                if name in READ_ONLY:
                    text = f"Param write denied ({name})"
                    frames += self.telemetry.text_frames([(p.MAV_SEVERITY_WARNING, text)])
                else:
                    self.state.params[name] = self.state.stored(name, value)
                    self._persist()
            frames.insert(0, self.telemetry.param_value(name, index))
        return frames

    def _persist(self) -> None:
        if self.state.params_file is None:
            return
        try:
            save_param_file(self.state.params_file, self.state.params, self.state.ptypes)
        except OSError as err:
            logger.error(
                "%s: cannot write parameters to %s: %s",
                self.state.name,
                self.state.params_file,
                err,
            )

    def _guided_item(self, msg: Message) -> list[bytes]:
        """MISSION_ITEM(_INT) with current=2 (guided: fly there) or 3 (change altitude)."""
        item = MissionItem.from_message(msg)
        with self.state.lock:
            if item.current == 2:
                result = self.flight.reposition(
                    item.lat, item.lon, item.z, amsl=not item.relative, change_mode=False
                )
            elif (
                self.state.mode == "GUIDED"
                and self.state.airborne
                and self.state.target is not None
            ):
                up = (
                    self.state.home_up() + item.z
                    if item.relative
                    else item.z - self.state.origin[2]
                )
                self.state.target = [self.state.target[0], self.state.target[1], max(up, 0.5)]
                result = p.MAV_RESULT_ACCEPTED
            else:
                result = p.MAV_RESULT_FAILED
        verdict = p.MAV_MISSION_ACCEPTED if result == p.MAV_RESULT_ACCEPTED else p.MAV_MISSION_ERROR
        return [
            self.state.codec.encode(
                "MISSION_ACK",
                target_system=msg.src_system,
                target_component=msg.src_component,
                type=verdict,
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
        ]

    def _request_data_stream(self, msg: Message) -> None:
        """REQUEST_DATA_STREAM: set the rate of a stream group (ArduPilot's SRx_* groups)."""
        start_stop = msg.get_int("start_stop")
        if start_stop not in (0, 1):
            return
        hz = float(msg.get_int("req_message_rate")) if start_stop == 1 else 0.0
        stream = msg.get_int("req_stream_id")
        if stream == p.MAV_DATA_STREAM_ALL:
            names = [n for group in STREAM_GROUPS.values() for n in group]
        else:
            names = list(STREAM_GROUPS.get(stream, ()))
        with self.state.lock:
            self.telemetry.set_group_rate(names, hz)

    def _ftp(self, msg: Message) -> list[bytes]:
        """MAVLink FTP: this vehicle has no files; every request is NAKed (sessions ACKed)."""
        payload = bytes(int(b) & 0xFF for b in msg.fields.get("payload", []))
        if len(payload) < 12:
            return []
        seq = payload[0] | payload[1] << 8
        session, opcode = payload[2], payload[3]
        if opcode in (p.FTP_OP_TERMINATE_SESSION, p.FTP_OP_RESET_SESSIONS):
            reply, data = p.FTP_OP_ACK, b""
        elif opcode in _FTP_SESSION_OPS:
            reply, data = p.FTP_OP_NAK, bytes([p.FTP_ERR_INVALID_SESSION])
        else:
            reply, data = p.FTP_OP_NAK, bytes([p.FTP_ERR_FILE_NOT_FOUND])
        header = bytes(
            [(seq + 1) & 0xFF, ((seq + 1) >> 8) & 0xFF, session, reply, len(data), opcode, 0, 0]
        )
        body = header + bytes(4) + data  # the 4-byte offset is 0
        return [
            self.state.codec.encode(
                "FILE_TRANSFER_PROTOCOL",
                target_network=0,
                target_system=msg.src_system,
                target_component=msg.src_component,
                payload=list(body + bytes(251 - len(body))),
            )
        ]

    def _command(self, msg: Message, cmd: int) -> tuple[int, list[bytes]]:
        """Carry out one command (lock held): its MAV_RESULT and any frames to send after."""
        prm = [msg.get_float(f"param{i}") for i in range(1, 5)]
        if msg.name == "COMMAND_LONG":
            prm += [msg.get_float("param5"), msg.get_float("param6"), msg.get_float("param7")]
        else:
            prm += [msg.get_int("x") / 1e7, msg.get_int("y") / 1e7, msg.get_float("z")]
        now = self.state.clock.monotonic()
        if cmd == p.MAV_CMD_COMPONENT_ARM_DISARM:
            return (
                self.flight.arm() if prm[0] == 1.0 else self.flight.disarm(prm[1] == _FORCE_DISARM)
            ), []
        if cmd == p.MAV_CMD_DO_SET_MODE:
            if not int(prm[0]) & p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return p.MAV_RESULT_UNSUPPORTED, []
            return self.flight.set_mode(p.mode_name(int(prm[1]))), []
        if cmd == p.MAV_CMD_NAV_TAKEOFF:
            return self.flight.takeoff(prm[6]), []
        if cmd == p.MAV_CMD_NAV_LAND:
            return self.flight.set_mode("LAND"), []
        if cmd == p.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.flight.set_mode("RTL"), []
        if cmd == p.MAV_CMD_DO_REPOSITION:
            amsl = msg.name == "COMMAND_LONG" or msg.get_int("frame") in (
                p.MAV_FRAME_GLOBAL,
                p.MAV_FRAME_GLOBAL_INT,
            )
            return self.flight.reposition(prm[4], prm[5], prm[6], amsl=amsl, change_mode=True), []
        if cmd == p.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self.telemetry.set_interval(int(prm[0]), prm[1]), []
        if cmd == p.MAV_CMD_REQUEST_MESSAGE:
            frame = self.telemetry.one_message(int(prm[0]))
            return (p.MAV_RESULT_ACCEPTED, [frame]) if frame else (p.MAV_RESULT_DENIED, [])
        if cmd == p.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            frame = self.telemetry.one_message(p.MSG_ID["AUTOPILOT_VERSION"])
            return p.MAV_RESULT_ACCEPTED, [frame] if frame else []
        if cmd == p.MAV_CMD_GET_HOME_POSITION:
            return p.MAV_RESULT_ACCEPTED, [self.telemetry.frame("HOME_POSITION", now)]
        if cmd == p.MAV_CMD_DO_SET_HOME:
            relative = msg.name == "COMMAND_INT" and msg.get_int("frame") not in (
                p.MAV_FRAME_GLOBAL,
                p.MAV_FRAME_GLOBAL_INT,
            )
            if prm[0] not in (0.0, 1.0):
                return p.MAV_RESULT_FAILED, []  # ArduCopter: param1 is 1 (here) or 0
            result = self.flight.set_home(prm[0] == 1.0, prm[4], prm[5], prm[6], relative=relative)
            extra = (
                [self.telemetry.frame("HOME_POSITION", now)]
                if result == p.MAV_RESULT_ACCEPTED
                else []
            )
            return result, extra
        if cmd == p.MAV_CMD_DO_CHANGE_SPEED:
            if not (math.isfinite(prm[1]) and prm[1] > 0) or not 0 <= prm[0] < 4:
                return p.MAV_RESULT_DENIED, []
            if self.state.mode not in ("AUTO", "GUIDED"):
                return p.MAV_RESULT_FAILED, []  # modes without a speed to change
            return self.auto.change_speed(prm[0], prm[1]), []
        if cmd == p.MAV_CMD_MISSION_START:  # ArduCopter: AUTO, then start a stopped mission
            if prm[0] != 0 or prm[1] != 0:
                return p.MAV_RESULT_DENIED, []  # first/last item: not supported
            result = self.flight.set_mode("AUTO")
            if result == p.MAV_RESULT_ACCEPTED:
                self.state.auto_armed = True  # GCS_MAVLINK_Copter: as if the throttle was raised
                if self.state.mis_state != p.MISSION_STATE_ACTIVE:
                    self.auto.start_or_resume()
            return result, []
        if cmd == p.MAV_CMD_DO_SET_MISSION_CURRENT:
            result = self.auto.set_current(int(prm[0]), reset=prm[1] == 1.0)
            frames, self.state.outbox = self.state.outbox, []
            return result, frames
        return p.MAV_RESULT_UNSUPPORTED, []
