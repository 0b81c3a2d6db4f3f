"""Mission upload sink: a canonical ``mission`` (or explicit items) uploaded with the MAVLink
mission protocol, acknowledged only when the vehicle accepts it.

    sink: {mavlink: {connection: radio, mission: upload, target_system: 1, target_component: 1}}

Each canonical waypoint becomes a MISSION_ITEM_INT ``MAV_CMD_NAV_WAYPOINT``: x, y = degrees x 1e7
rounded, z = its one altitude in metres in the frame that says what it is measured from
(``alt_msl``: ``MAV_FRAME_GLOBAL_INT``, above mean sea level; ``alt_rel``:
``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT``, above home), param1 = ``hold_s``, in list order. A waypoint
with neither altitude, or both, is refused naming it: the same number is 20 m above the field or
372 m below it at a field 392 m above sea level, so the reference is never guessed. A
``sink.mapping`` producing ``{items: [{command, frame, x, y, z, param1..param4, autocontinue}]}``
gives full control (command and frame by name or number, both required: a frame is never
guessed either). ``home_placeholder: true`` puts
ArduPilot's seq-0 home item first.

Protocol (devguide ``services/mission.md``): MISSION_COUNT; every MISSION_REQUEST_INT or legacy
MISSION_REQUEST is answered with the item asked for, repeats included; silence for the answer
timeout sends the last message again (``retries`` times; a SiK link needs ~1.5 s, not the
protocol's 250 ms); a vehicle that answered and then fell silent that long gave the transfer up,
and it starts again from MISSION_COUNT while within ``command_timeout``. MISSION_ACK ``MAV_MISSION_ACCEPTED`` completes the upload; any other result
is permanent (:class:`MessageRejected` naming it), except ArduPilot's non-terminal
``MAV_MISSION_INVALID_SEQUENCE`` during a transfer. No answer after the retries, or for
``command_timeout`` seconds (from when the route received the message, then from the vehicle's
last answer: transaction.py), cancels the upload on the vehicle and is permanent too, naming the
vehicle and when it was last heard: the route does not upload a stale mission later. One upload
at a time per target.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

from engine.common.suggest import did_you_mean
from engine.endpoints.base import MessageRejected, Outbound, Sink
from engine.endpoints.mavlink.codec import build_message, mavlink2, null_fields, null_problem
from engine.endpoints.mavlink.contract import SharedLink
from engine.endpoints.mavlink.enums import enum_name, enum_or_number
from engine.endpoints.mavlink.transaction import Conversation, TransactionOptions, deadline, heard_in_time, per_target

ITEM = mavlink2.MAVLink_mission_item_int_message
Targets = Callable[..., dict[str, int]]
"""``targets(outbound)``: the ``{field}`` targets of one message (messages.message_targets)."""
_ANSWERS = (mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST_INT, mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST,
            mavlink2.MAVLINK_MSG_ID_MISSION_ACK)
_ITEM_KEYS = {"command", "frame", "x", "y", "z", "param1", "param2", "param3", "param4", "autocontinue", "current"}
_MAX_ITEMS = 65535
MISSION_ANSWER = ("kind", "result", "items")
"""The keys of what a mission upload answers a call (its reply mapping's input); ``check`` knows them."""
ALTITUDE_FRAMES = {"alt_msl": mavlink2.MAV_FRAME_GLOBAL_INT, "alt_rel": mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
"""The altitudes a canonical waypoint may carry (exactly one), with the frame that says their
reference: the names of the canonical position's altitudes."""
_ALTITUDE_CHOICE = ("set one of 'alt_msl' (metres above mean sea level, MAV_FRAME_GLOBAL_INT) or 'alt_rel' "
                    "(metres above home, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT); an altitude is never guessed")
_WAYPOINT_KEYS = ("lat", "lon", *ALTITUDE_FRAMES, "hold_s")
"""What the sink reads of a canonical waypoint (other keys, such as ``action``, it leaves alone)."""


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MessageRejected(f"{what}: expected a number, got {value!r}")
    return float(value)


def _objects(raw: Any, name: str) -> Iterator[tuple[str, Mapping[str, Any]]]:
    """(``name[i]``, object) for each entry of a non-empty list, or MessageRejected."""
    if not isinstance(raw, list) or not raw:
        raise MessageRejected(f"mission has no {name}" if raw in (None, []) else f"{name} must be a list")
    for index, entry in enumerate(raw):
        if not isinstance(entry, Mapping):
            raise MessageRejected(f"{name}[{index}]: expected an object")
        yield f"{name}[{index}]", entry


def waypoint_items(mission: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Canonical waypoints -> MISSION_ITEM_INT fields (without seq and targets); each waypoint
    has exactly one altitude (:func:`refuse_unguessed` ran first)."""
    items = []
    for where, point in _objects(mission.get("waypoints"), "waypoints"):
        altitude = "alt_msl" if "alt_msl" in point else "alt_rel"
        items.append({
            "command": mavlink2.MAV_CMD_NAV_WAYPOINT, "frame": ALTITUDE_FRAMES[altitude],
            "x": round(_number(point.get("lat"), f"{where}.lat") * 1e7),
            "y": round(_number(point.get("lon"), f"{where}.lon") * 1e7),
            "z": _number(point[altitude], f"{where}.{altitude}"),
            "param1": _number(point.get("hold_s", 0), f"{where}.hold_s"),
            "autocontinue": 1,
        })
    return items


def explicit_items(raw: Any) -> list[dict[str, Any]]:
    """``items`` from a sink mapping: MISSION_ITEM_INT fields, command and frame by name or number."""
    items = []
    for where, item in _objects(raw, "items"):
        unknown = sorted(set(item) - _ITEM_KEYS)
        if unknown:
            named = ", ".join(f"{key}{did_you_mean(key, _ITEM_KEYS)}" for key in unknown)
            raise MessageRejected(f"{where}: unknown field(s) {named} (fields: {', '.join(sorted(_ITEM_KEYS))})")
        if "command" not in item:
            raise MessageRejected(f"{where}: no command")
        if "frame" not in item:  # x, y, z mean nothing without it: metres above home or above sea level?
            raise MessageRejected(f"{where}: no frame: name it (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: z above home, "
                                  f"MAV_FRAME_GLOBAL_INT: above mean sea level, MAV_FRAME_MISSION: no position); "
                                  f"a frame is never guessed")
        fields = {"autocontinue": 1, **item}
        try:
            fields["command"] = enum_or_number(fields["command"], "MAV_CMD", f"{where}.command")
            fields["frame"] = enum_or_number(fields["frame"], "MAV_FRAME", f"{where}.frame")
        except ValueError as exc:
            raise MessageRejected(str(exc)) from None
        items.append(fields)
    return items


def mission_nulls(fields: Mapping[str, Any]) -> list[str]:
    """What the mission sets to null among what the sink reads: ``items[i].param1`` of explicit
    items, ``waypoints[i].alt_rel`` of a canonical mission (lat, lon, alt_msl, alt_rel, hold_s),
    or the list."""
    if "items" in fields:
        name, entries, read = "items", fields["items"], None
    else:
        name, entries, read = "waypoints", fields.get("waypoints"), _WAYPOINT_KEYS
    if entries is None:
        return [name] if name in fields else []
    if not isinstance(entries, list):
        return []
    nulls = []
    for index, entry in enumerate(entries):
        if entry is None:
            nulls.append(f"{name}[{index}]")
        elif isinstance(entry, Mapping):
            nulls.extend(f"{name}[{index}].{key}" for key in null_fields(entry) if read is None or key in read)
    return nulls


def altitude_problems(fields: Mapping[str, Any]) -> list[str]:
    """Each canonical waypoint that does not give exactly one altitude (see ``ALTITUDE_FRAMES``),
    named ``waypoints[i]``; a mission of explicit ``items`` says its frames itself."""
    waypoints = fields.get("waypoints")
    if "items" in fields or not isinstance(waypoints, list):
        return []
    problems = []
    for index, point in enumerate(waypoints):
        if not isinstance(point, Mapping):
            continue  # not a waypoint at all: waypoint_items says so
        given = [key for key in ALTITUDE_FRAMES if key in point]
        if len(given) == 2:
            problems.append(f"'waypoints[{index}]' gives both 'alt_msl' and 'alt_rel'")
        elif not given:
            unsaid = ", only 'alt', which does not say above what" if "alt" in point else ""
            problems.append(f"'waypoints[{index}]' gives no altitude{unsaid}")
    return problems


def refuse_unguessed(fields: Any) -> None:
    """MessageRejected (stage ``sink mapping``) naming every null the sink would read (see
    :func:`mission_nulls`) and every waypoint without exactly one altitude: a waypoint's altitude,
    its reference or an item's parameter is never guessed. The pipeline runs it as the sink's
    field check; :func:`mission_items` runs it again."""
    if not isinstance(fields, Mapping):
        return
    nulls = mission_nulls(fields)
    if nulls:
        raise MessageRejected(null_problem("mission", nulls), stage="sink mapping")
    problems = altitude_problems(fields)
    if problems:
        raise MessageRejected(f"mission: {'; '.join(problems)}: {_ALTITUDE_CHOICE}", stage="sink mapping")


def mission_items(fields: Any, options: TransactionOptions,
                  target: tuple[int, int] | None = None) -> list[mavlink2.MAVLink_message]:
    """The MISSION_ITEM_INT messages of one upload to ``target`` (default: the options'), in
    order; MessageRejected when the fields cannot make a mission (also what ``rabbitros-engine
    test`` runs as the sink's dry run)."""
    if not isinstance(fields, Mapping):
        raise MessageRejected(f"a mission sink needs an object, got {type(fields).__name__}")
    refuse_unguessed(fields)
    if "items" in fields:
        items = explicit_items(fields["items"])
    else:
        items = waypoint_items(fields)
    if options.home_placeholder:
        first = items[0]
        items.insert(0, {"command": mavlink2.MAV_CMD_NAV_WAYPOINT, "frame": mavlink2.MAV_FRAME_GLOBAL_INT,
                         "x": first.get("x", 0), "y": first.get("y", 0), "z": 0.0, "autocontinue": 1})
    if len(items) > _MAX_ITEMS:
        raise MessageRejected(f"{len(items)} items exceed the mission protocol's {_MAX_ITEMS}")
    target_system, target_component = target or options.target
    target_fields = {"target_system": target_system, "target_component": target_component, "mission_type": options.mission_type}
    return [build_message(ITEM, {**item, **target_fields, "seq": seq}) for seq, item in enumerate(items)]


def mission_target(options: TransactionOptions, targets: Targets | None, message: Outbound) -> tuple[int, int]:
    """The (system, component) one message's mission goes to: each ``{field}`` target read from
    its canonical message (MessageRejected if it names none), the options' numbers otherwise."""
    if targets is None:
        return options.target
    read = targets(message)
    return read.get("target_system", options.target_system), read.get("target_component", options.target_component)


_RESTART_AFTER = 3
"""Unanswered resends of an item after which the transfer starts again from MISSION_COUNT: a
vehicle that answered and then stays silent gave the transfer up (MAVSDK does after a few losses
on a SiK link), and resending the same item to it until the bound would only run the bound out."""

class MissionUploadSink(Sink):
    """Uploads each message's mission to its target; returns once the vehicle accepted it.
    A batch uploads to several targets at once, one upload at a time per target."""

    def __init__(self, connection: SharedLink, options: TransactionOptions, targets: Targets | None = None) -> None:
        self.connection = connection
        self.options = options
        self.targets = targets
        """Reads ``{field}`` targets from each message (messages.message_targets), or None."""

    def target(self, message: Outbound) -> tuple[int, int]:
        return mission_target(self.options, self.targets, message)

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        return await per_target(messages, self.target, self.send)

    async def send(self, message: Outbound) -> None:
        target = self.target(message)
        items = mission_items(message.fields, self.options, target)
        connection, options = self.connection, self.options
        loop = asyncio.get_running_loop()
        canonical = message.canonical if isinstance(message.canonical, Mapping) else {}
        bound = options.give_up_after(connection)
        give_up = deadline(message.received_ns, bound)
        async with connection.transaction_lock(("mission", target)):
            if not await heard_in_time(connection, target, options.vehicle_timeout, give_up):
                raise self._stale(target, len(items), bound, "not started: the vehicle was not heard")
            if loop.time() >= give_up:
                raise self._stale(target, len(items), bound, "not started: it waited for the previous upload")
            connection.mission_refs[target] = str(canonical.get("id") or message.message_id)
            async with Conversation(connection, target, _ANSWERS) as answers:
                await self._upload(answers, items, target, give_up, bound)
        if message.reply is not None:  # a call: the vehicle's MISSION_ACK is the answer
            await message.reply("result", {"kind": "result", "result": "MAV_MISSION_ACCEPTED", "items": len(items)})

    def _stale(self, target: tuple[int, int], items: int, bound: float, what: str) -> MessageRejected:
        """The upload given up at its bound: permanent, so a stale mission is never uploaded later."""
        connection = self.connection
        connection.stats["mission_timeouts"] = connection.stats.get("mission_timeouts", 0) + 1
        return MessageRejected(f"mavlink connection {connection.name!r}: {connection.last_heard_text(*target)}: the "
                               f"mission upload ({items} items) {what} within command_timeout {bound:g} s; not sent "
                               "again (a late vehicle must not fly a stale mission)")

    async def _upload(self, answers: Conversation, items: list[mavlink2.MAVLink_message],
                      target: tuple[int, int], give_up: float, bound: float) -> None:
        connection, options = self.connection, self.options
        stats = connection.stats
        target_system, target_component = target
        timeout = options.answer_timeout(connection)
        count = mavlink2.MAVLink_mission_count_message(target_system, target_component, len(items), options.mission_type)
        last: mavlink2.MAVLink_message = count
        await connection.send_message(last)
        loop = asyncio.get_running_loop()
        tries, highest = 0, -1
        wait_until = min(loop.time() + timeout, give_up)
        while True:
            answer = await answers.next(max(0.0, wait_until - loop.time()))
            if answer is None:
                tries += 1
                if tries > min(options.retries, _RESTART_AFTER) and last is not count and loop.time() < give_up:
                    # the vehicle answered this transfer, then fell silent: it gave the transfer up
                    # (MAVSDK does after a few losses on a SiK link): start it again, within the bound
                    stats["mission_restarts"] = stats.get("mission_restarts", 0) + 1
                    tries, highest, last = 0, -1, count
                    await connection.send_message(last)
                    wait_until = min(loop.time() + timeout, give_up)
                    continue
                if tries > options.retries or loop.time() >= give_up:
                    connection.post(mavlink2.MAVLink_mission_ack_message(
                        target_system, target_component, mavlink2.MAV_MISSION_OPERATION_CANCELLED, options.mission_type))
                    raise self._stale(target, len(items), bound, f"got no answer to {last.get_type()} after {tries} "
                                                                 f"send{'s' if tries > 1 else ''}")
                stats["mission_resends"] = stats.get("mission_resends", 0) + 1
                await connection.send_message(last)
                wait_until = min(loop.time() + timeout, give_up)
                continue
            if getattr(answer, "mission_type", options.mission_type) != options.mission_type:
                continue
            if answer.get_type() == "MISSION_ACK":
                if answer.type == mavlink2.MAV_MISSION_ACCEPTED:
                    if highest < len(items) - 1:
                        continue  # a late repeat of the previous upload's ACK: this one is not done
                    stats["missions_uploaded"] = stats.get("missions_uploaded", 0) + 1
                    return
                if answer.type == mavlink2.MAV_MISSION_INVALID_SEQUENCE and 0 <= highest < len(items) - 1:
                    continue  # ArduPilot: not terminal during a transfer; it asks again
                stats["missions_rejected"] = stats.get("missions_rejected", 0) + 1
                raise MessageRejected(f"vehicle {target_system}/{target_component} rejected the mission: "
                                      f"{enum_name('MAV_MISSION_RESULT', answer.type)}")
            seq = answer.seq
            if not 0 <= seq < len(items):
                continue  # a request for an item we never announced: the vehicle will time out or re-ask
            if seq > highest:
                highest, tries = seq, 0
            give_up = loop.time() + bound  # it answers: the upload progresses, it is not stale
            last = items[seq]
            stats["mission_items_sent"] = stats.get("mission_items_sent", 0) + 1
            await connection.send_message(last)
            wait_until = min(loop.time() + timeout, give_up)
