"""The autopilot side of the MAVLink mission and command protocols, for the simulated vehicle.

Missions (devguide ``services/mission.md``): MISSION_COUNT starts an upload; the autopilot asks
for each item in order with MISSION_REQUEST_INT (or the legacy MISSION_REQUEST), asks again for
the expected item when one is lost or comes out of order, re-requests after ``request_timeout``
(at most ``retries`` times), and answers the last item with MISSION_ACK; a repeated last item
(our ACK was lost) gets the ACK again. ``mission_result`` other than MAV_MISSION_ACCEPTED rejects
the upload with that result at its start; ``silent`` never answers.

Commands (``services/command.md``): every COMMAND_LONG/COMMAND_INT for this system is answered
with the next of ``command_results`` (the last repeats); MAV_RESULT_IN_PROGRESS is followed by
the next result after ``progress_delay`` (it takes its place in the list); ``silent`` never answers.

Flying (with ``item_seconds``): an accepted mission starts at once (AUTO) and each item is
reached ``item_seconds`` after the previous one (MISSION_ITEM_REACHED), PX4's numbering (the
first uploaded item is seq 0); an accepted MAV_CMD_DO_PAUSE_CONTINUE 0 holds (the time spent on
the item is kept), 1 continues. :meth:`mission_current` is the MISSION_CURRENT the vehicle
streams (seq, total, mission_state). The position streams do not follow the mission.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from engine.endpoints.mavlink.codec import mavlink2, message_fields
from engine.endpoints.mavlink.port import MavlinkPort

SILENT = "silent"


def _enum_value(enum: str, name: str) -> int:
    for value, entry in mavlink2.enums[enum].items():
        if entry.name == name:
            return value
    raise ValueError(f"{name!r} is not a {enum} name (or {SILENT!r})")


@dataclass
class _Upload:
    peer: tuple[int, int]
    count: int
    mission_type: int
    items: list[dict[str, Any]] = field(default_factory=list)
    deadline: float = 0.0
    tries: int = 0


class Autopilot:
    """Answers mission uploads and commands on ``port`` as system/component ``system_id``/``component_id``."""

    def __init__(self, port: MavlinkPort, system_id: int, component_id: int, *,
                 mission_result: str = "MAV_MISSION_ACCEPTED", command_results: Sequence[str] = ("MAV_RESULT_ACCEPTED",),
                 legacy_requests: bool = False, request_timeout: float = 1.5, retries: int = 5,
                 progress_delay: float = 0.5, item_seconds: float | None = None) -> None:
        self.port = port
        self.system_id, self.component_id = system_id, component_id
        self.mission_result = None if mission_result == SILENT else _enum_value("MAV_MISSION_RESULT", mission_result)
        self.command_results = [None if r == SILENT else _enum_value("MAV_RESULT", r) for r in command_results]
        if not self.command_results:
            raise ValueError("command_results must name at least one result")
        self.legacy_requests = legacy_requests
        self.request_timeout, self.retries, self.progress_delay = request_timeout, retries, progress_delay
        self.mission: list[dict[str, Any]] = []
        """The items of the last accepted upload, as field dicts, in order."""
        self.commands: list[dict[str, Any]] = []
        """Every command received (repeats included), as field dicts with ``message``."""
        self.armed = False
        self.stats = {"missions_accepted": 0, "mission_items_received": 0, "mission_requests_sent": 0,
                      "commands_received": 0}
        self._upload: _Upload | None = None
        self._finished: tuple[tuple[int, int], int, int, int] | None = None
        """(peer, count, result, mission_type) of the last upload answered, to repeat its ACK."""
        self._wake = asyncio.Event()
        self._result_index = 0
        self.item_seconds = item_seconds
        self.current = 0
        """The mission item being flown to (MISSION_CURRENT.seq)."""
        self.mission_state = mavlink2.MISSION_STATE_NO_MISSION
        self._on_item = 0.0
        """Seconds spent flying to ``current`` (kept while paused)."""
        self._last_advance: float | None = None

    def _for_us(self, msg: Any) -> bool:
        return msg.target_system in (0, self.system_id) and msg.target_component in (0, self.component_id)

    def handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind in ("MISSION_COUNT", "MISSION_ITEM_INT", "COMMAND_LONG", "COMMAND_INT") and self._for_us(msg):
            getattr(self, "_" + kind.lower())(msg)

    # missions

    def _mission_count(self, msg: Any) -> None:
        if self.mission_result is None:
            return
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        upload = self._upload
        if upload is not None and upload.peer == peer and upload.count == msg.count and not upload.items:
            self._request(upload)  # our first request was lost: the GCS repeated its count
            return
        if self.mission_result != mavlink2.MAV_MISSION_ACCEPTED or msg.count == 0:
            self._upload = None
            result = self.mission_result
            if msg.count == 0 and result == mavlink2.MAV_MISSION_ACCEPTED:
                self.mission = []
            self._ack(peer, result, msg.mission_type, msg.count)
            return
        self._upload = _Upload(peer, msg.count, msg.mission_type)
        self._request(self._upload)

    def _mission_item_int(self, msg: Any) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        upload = self._upload
        if upload is None or upload.peer != peer:
            done = self._finished
            if done is not None and done[0] == peer and msg.seq == done[1] - 1:
                self._ack(peer, done[2], done[3], done[1])  # our ACK was lost: the GCS repeated the last item
            return
        if msg.seq == len(upload.items):
            upload.items.append(message_fields(msg))
            self.stats["mission_items_received"] += 1
            upload.tries = 0
        if len(upload.items) == upload.count:
            self._upload = None
            self.mission = upload.items
            self.stats["missions_accepted"] += 1
            self.current, self._on_item = 0, 0.0
            self.mission_state = mavlink2.MISSION_STATE_ACTIVE
            self._ack(peer, mavlink2.MAV_MISSION_ACCEPTED, upload.mission_type, upload.count)
        else:
            self._request(upload)

    def _request(self, upload: _Upload) -> None:
        seq = len(upload.items)
        cls = mavlink2.MAVLink_mission_request_message if self.legacy_requests else mavlink2.MAVLink_mission_request_int_message
        self.port.post(cls(upload.peer[0], upload.peer[1], seq, upload.mission_type))
        self.stats["mission_requests_sent"] += 1
        upload.deadline = asyncio.get_running_loop().time() + self.request_timeout
        self._wake.set()

    def _ack(self, peer: tuple[int, int], result: int, mission_type: int, count: int) -> None:
        self._finished = (peer, count, result, mission_type)
        self.port.post(mavlink2.MAVLink_mission_ack_message(peer[0], peer[1], result, mission_type))

    # commands

    def _command_long(self, msg: Any) -> None:
        self._command(msg)

    def _command_int(self, msg: Any) -> None:
        self._command(msg)

    def _command(self, msg: Any) -> None:
        self.commands.append({"message": msg.get_type(), **message_fields(msg)})
        self.stats["commands_received"] += 1
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        result = self._next_result()
        if result is None:
            return
        self._command_ack(peer, msg, result)
        if result == mavlink2.MAV_RESULT_IN_PROGRESS:
            final = self._next_result()
            if final is not None:
                asyncio.get_running_loop().call_later(self.progress_delay, self._command_ack, peer, msg, final)

    def _next_result(self) -> int | None:
        result = self.command_results[min(self._result_index, len(self.command_results) - 1)]
        self._result_index += 1
        return result

    def _command_ack(self, peer: tuple[int, int], msg: Any, result: int) -> None:
        if result == mavlink2.MAV_RESULT_ACCEPTED and msg.command == mavlink2.MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = msg.param1 == 1
        if result == mavlink2.MAV_RESULT_ACCEPTED and msg.command == mavlink2.MAV_CMD_DO_PAUSE_CONTINUE:
            if msg.param1 == 0 and self.mission_state == mavlink2.MISSION_STATE_ACTIVE:
                self.mission_state = mavlink2.MISSION_STATE_PAUSED
            elif msg.param1 == 1 and self.mission_state == mavlink2.MISSION_STATE_PAUSED:
                self.mission_state = mavlink2.MISSION_STATE_ACTIVE
        progress = 50 if result == mavlink2.MAV_RESULT_IN_PROGRESS else 0
        self.port.post(mavlink2.MAVLink_command_ack_message(msg.command, result, progress, 0, peer[0], peer[1]))

    # flying

    def advance(self, now: float) -> None:
        """Fly the mission up to ``now`` (loop seconds): MISSION_ITEM_REACHED for each item reached."""
        last, self._last_advance = self._last_advance, now
        if self.item_seconds is None or last is None or self.mission_state != mavlink2.MISSION_STATE_ACTIVE:
            return
        self._on_item += now - last
        if self._on_item < self.item_seconds:
            return
        self.port.post(mavlink2.MAVLink_mission_item_reached_message(self.current))
        self._on_item = 0.0
        if self.current + 1 < len(self.mission):
            self.current += 1
        else:
            self.mission_state = mavlink2.MISSION_STATE_COMPLETE

    def mission_current(self) -> Any:
        return mavlink2.MAVLink_mission_current_message(self.current, len(self.mission), self.mission_state, 0)

    async def run(self) -> None:
        """Re-request the expected item of an upload that went quiet; give up after ``retries``."""
        loop = asyncio.get_running_loop()
        while True:
            upload = self._upload
            if upload is None:
                self._wake.clear()
                await self._wake.wait()
                continue
            delay = upload.deadline - loop.time()
            if delay > 0:
                self._wake.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), delay)
                continue
            upload.tries += 1
            if upload.tries > self.retries:
                self._upload = None
            else:
                self._request(upload)
