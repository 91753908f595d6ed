"""MAVLink mission transfers of :class:`~temoto.drivers.mavlink.driver.MavlinkDriver`.

The mission microservice as a ground station speaks it: upload (``MISSION_COUNT`` → the
vehicle's ``MISSION_REQUEST_INT`` for each item → ``MISSION_ACK``), download, clear, and start
(``MAV_CMD_MISSION_START`` in GUIDED, armed), each step waiting ``mission_timeout`` and
resending ``mission_retries`` times; a refusal is a
:class:`~temoto.errors.MavlinkMissionError` naming the ``MAV_MISSION_RESULT``. Progress
(``MISSION_CURRENT``, ``MISSION_ITEM_REACHED``) reaches :attr:`mission_progress` and the
listeners. The wire form of each item is in :mod:`~temoto.drivers.mavlink.missions`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from temoto.drivers.capabilities import MissionItem, MissionProgress
from temoto.drivers.mavlink import missions
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink._parameters import ParameterClient
from temoto.drivers.mavlink.protocol import Message
from temoto.errors import (
    DriverOperationError,
    DriverTimeoutError,
    MavlinkMissionError,
)

__all__ = ["MissionClient"]

logger = logging.getLogger(__name__)


class MissionClient(ParameterClient):
    """Uploading, downloading, clearing and running missions (a layer of the MAVLink driver).

    Not used alone: :class:`~temoto.drivers.mavlink.driver.MavlinkDriver` is built on it.
    """

    # ---- missions -----------------------------------------------------------------------------
    def upload_mission(self, items: Sequence[MissionItem]) -> None:
        """Replace the vehicle's mission (the MAVLink mission protocol, MISSION_INT).

        Sends ``MISSION_COUNT`` and answers each ``MISSION_REQUEST_INT`` (and the older
        ``MISSION_REQUEST``) with the ``MISSION_ITEM_INT`` asked for, until the vehicle's
        ``MISSION_ACK``. ArduPilot keeps its home position as item 0, so the items go as
        1..n after a placeholder item 0 (the home position when known). Each step waits
        ``mission_timeout``; with nothing heard, the last message is sent again, up to
        ``mission_retries`` times; a request for an earlier item is answered again, and a
        ``MAV_MISSION_INVALID_SEQUENCE`` ack (ArduPilot's answer to a stray copy of an item)
        does not end the upload. Positions go in ``MAV_FRAME_GLOBAL_RELATIVE_ALT``
        (altitudes above home).

        Args:
            items: The mission (see :class:`~temoto.drivers.capabilities.MissionItem`).

        Raises:
            ValueError: No items, too many, or not MissionItems.
            StateError: The driver is not configured.
            MavlinkMissionError: The vehicle's MISSION_ACK refused it (the message names the
                ``MAV_MISSION_RESULT``, and the item the vehicle asked for last).
            DriverTimeoutError: A step went unanswered (the message names it).
        """
        mission = list(items)
        if not mission:
            raise ValueError(f"{self.name}: a mission needs at least one item")
        for index, item in enumerate(mission, 1):
            if not isinstance(item, MissionItem):
                raise ValueError(
                    f"{self.name}: mission item {index} is not a MissionItem: {type(item).__name__}"
                )
        if len(mission) >= 0xFFFF:
            raise ValueError(f"{self.name}: {len(mission)} items: too many for MAVLink")
        self._require_link("upload_mission")
        with self._mission_lock:
            target = self._target_ids()
            with self._cond:
                home = self._home
            frames = [self._item_frame(0, missions.home_fields(home), target)]
            frames += [
                self._item_frame(seq, missions.item_fields(item), target)
                for seq, item in enumerate(mission, 1)
            ]
            count = len(frames)
            last = self._codec.encode(
                "MISSION_COUNT",
                target_system=target[0],
                target_component=target[1],
                count=count,
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
            with self._cond:
                seen = self._mission_seq
                self._mission_total = 0
            self._write(last)
            step = "MISSION_REQUEST for item 0 after MISSION_COUNT"
            asked = -1  # the highest item the vehicle asked for
            tries = 0
            while True:
                got = self._await_mission(seen, missions.upload_answer)
                if got is None:
                    tries += 1
                    if tries > self.mission_retries:
                        raise DriverTimeoutError(
                            f"{self.name}: mission upload: no {step} in"
                            f" {1 + self.mission_retries} tries of {self.mission_timeout:g} s"
                        )
                    self._write(last)
                    continue
                seen, msg = got
                if msg.name == "MISSION_ACK":
                    result = msg.get_int("type")
                    if result == p.MAV_MISSION_INVALID_SEQUENCE:
                        # ArduPilot's answer to a copy of an item it did not ask for (ours
                        # after a lost or doubled request): the upload goes on.
                        logger.debug("driver %s: mission upload: %s", self.name, msg.fields)
                        continue
                    if result != p.MAV_MISSION_ACCEPTED:
                        where = f" at item {asked}" if asked >= 0 else ""
                        raise MavlinkMissionError(
                            f"{self.name}: mission upload refused{where}:"
                            f" {p.mission_result_name(result)}",
                            result=result,
                        )
                    if asked < count - 1:
                        raise DriverOperationError(
                            f"{self.name}: mission upload: the vehicle accepted after item"
                            f" {asked} of {count - 1}: it does not hold the whole mission"
                        )
                    break
                seq = msg.get_int("seq")
                if not 0 <= seq < count:
                    raise DriverOperationError(
                        f"{self.name}: mission upload: the vehicle asked for item {seq},"
                        f" the mission has 0..{count - 1}"
                    )
                tries = 0  # progress: each step has its own retries
                asked = max(asked, seq)
                last = frames[seq]
                self._write(last)
                step = (
                    "MISSION_ACK after the last item"
                    if seq == count - 1
                    else f"MISSION_REQUEST for item {seq + 1}"
                )
            with self._cond:
                self._mission_total = len(mission)
                self._progress = MissionProgress(total=len(mission))
        logger.info("driver %s: mission of %d items uploaded", self.name, len(mission))

    def download_mission(self) -> list[MissionItem]:
        """The vehicle's mission (``MISSION_REQUEST_LIST``, then each ``MISSION_REQUEST_INT``).

        Item 0, ArduPilot's home position, is left out. Each step waits ``mission_timeout``
        and is sent again up to ``mission_retries`` times; the transfer ends with a
        ``MISSION_ACK`` (accepted) to the vehicle.

        Returns:
            The items, first first.

        Raises:
            StateError: The driver is not configured.
            DriverOperationError: An item this driver cannot represent (its command or frame is
                named), or the vehicle refused the transfer.
            DriverTimeoutError: A step went unanswered (the message names it).
        """
        self._require_link("download_mission")
        with self._mission_lock:
            target = self._target_ids()
            ids = {"target_system": target[0], "target_component": target[1]}
            request = self._codec.encode(
                "MISSION_REQUEST_LIST", **ids, mission_type=p.MAV_MISSION_TYPE_MISSION
            )
            with self._cond:
                seen = self._mission_seq
            got = self._mission_step(request, seen, missions.count_answer, "MISSION_COUNT")
            seen, msg = got
            count = msg.get_int("count")
            raw: list[Message] = []
            for seq in range(count):
                request = self._codec.encode(
                    "MISSION_REQUEST_INT", **ids, seq=seq, mission_type=p.MAV_MISSION_TYPE_MISSION
                )
                seen, msg = self._mission_step(
                    request, seen, missions.item_answer(seq), f"MISSION_ITEM_INT {seq} of {count}"
                )
                raw.append(msg)
            self._write(
                self._codec.encode(
                    "MISSION_ACK",
                    **ids,
                    type=p.MAV_MISSION_ACCEPTED,
                    mission_type=p.MAV_MISSION_TYPE_MISSION,
                )
            )
            with self._cond:
                home = self._home
        items = [missions.decoded_item(self.name, msg, home) for msg in raw[1:]]
        with self._cond:
            self._mission_total = len(items)
        return items

    def clear_mission(self) -> None:
        """Delete the vehicle's mission (``MISSION_CLEAR_ALL`` → ``MISSION_ACK``).

        Raises:
            StateError: The driver is not configured.
            MavlinkMissionError: The vehicle refused (its ``MAV_MISSION_RESULT`` named).
            DriverTimeoutError: No MISSION_ACK.
        """
        self._require_link("clear_mission")
        with self._mission_lock:
            target = self._target_ids()
            request = self._codec.encode(
                "MISSION_CLEAR_ALL",
                target_system=target[0],
                target_component=target[1],
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
            with self._cond:
                seen = self._mission_seq
            _, msg = self._mission_step(
                request, seen, missions.ack_answer, "MISSION_ACK to MISSION_CLEAR_ALL"
            )
            result = msg.get_int("type")
            if result != p.MAV_MISSION_ACCEPTED:
                raise MavlinkMissionError(
                    f"{self.name}: mission clear refused: {p.mission_result_name(result)}",
                    result=result,
                )
            with self._cond:
                self._mission_total = 0
                self._progress = MissionProgress()

    @property
    def mission_progress(self) -> MissionProgress:
        """The newest mission progress (``MISSION_CURRENT``, ``MISSION_ITEM_REACHED``).

        Items are counted as :meth:`upload_mission` took them (1..n; ArduPilot's home item 0
        is not one).
        """
        with self._cond:
            return self._progress

    def add_mission_listener(self, listener: Callable[[MissionProgress], None]) -> None:
        """Call ``listener`` with each new mission progress (on the receive thread: be quick).

        Args:
            listener: Takes the :class:`~temoto.drivers.capabilities.MissionProgress`.
        """
        with self._cond:
            self._mission_listeners.append(listener)

    def _target_ids(self) -> tuple[int, int]:
        with self._cond:
            return (self._target or 1, self.component_id)

    def _item_frame(self, seq: int, fields: dict[str, Any], target: tuple[int, int]) -> bytes:
        return self._codec.encode(
            "MISSION_ITEM_INT",
            target_system=target[0],
            target_component=target[1],
            seq=seq,
            current=0,
            autocontinue=1,
            mission_type=p.MAV_MISSION_TYPE_MISSION,
            **fields,
        )

    def _mission_step(
        self, request: bytes, seen: int, accept: Callable[[Message], bool], step: str
    ) -> tuple[int, Message]:
        """Send ``request`` until an accepted answer (retries); a refusing MISSION_ACK raises."""
        for _ in range(1 + self.mission_retries):
            self._write(request)
            got = self._await_mission(seen, lambda msg: accept(msg) or msg.name == "MISSION_ACK")
            if got is None:
                continue
            if got[1].name == "MISSION_ACK" and not accept(got[1]):
                result = got[1].get_int("type")
                raise MavlinkMissionError(
                    f"{self.name}: the vehicle ended the transfer waiting for {step}:"
                    f" {p.mission_result_name(result)}",
                    result=result,
                )
            return got
        raise DriverTimeoutError(
            f"{self.name}: no {step} in {1 + self.mission_retries} tries of"
            f" {self.mission_timeout:g} s"
        )

    def _await_mission(
        self, after: int, accept: Callable[[Message], bool]
    ) -> tuple[int, Message] | None:
        """The first mission-transfer message newer than ``after`` that ``accept`` takes."""
        found: list[tuple[int, Message]] = []

        def arrived() -> bool:
            for number, msg in self._mission_rx:
                if number > after and accept(msg):
                    found.append((number, msg))
                    return True
            return False

        return found[0] if self._await(arrived, self.mission_timeout) else None
