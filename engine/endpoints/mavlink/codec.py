"""MAVLink messages as plain dicts and back: the conversion edge of the MAVLink endpoint.

``build_message`` turns a sink mapping's object into a message, rejecting (permanently, with the
field named) what the message type cannot carry; ``message_fields`` gives a received message's
fields. Both use pymavlink's ``common`` dialect tables, MAVLink 2.

A field is never guessed: one the sink mapping sets to null (``null``, or a path the message
lacks, which JMESPath evaluates to null) is refused (:func:`refuse_nulls`), because a null
written as 0 can be the opposite of what was meant (COMMAND_LONG ``param1`` 0 of
MAV_CMD_COMPONENT_ARM_DISARM disarms). Only a field the mapping does not name at all takes the
message's default: the sink's ``target_system``/``target_component`` options for those fields,
else 0 (empty for strings, zeros for arrays), the value every MAVLink implementation gives an
unset field. Where MAVLink defines NaN as "unset" (float command parameters such as
MAV_CMD_DO_REPOSITION's yaw) the mapping says so with ``nan()``.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from engine.common.suggest import did_you_mean
from engine.endpoints.base import MessageRejected
from engine.endpoints.mavlink.dialect import mavlink2
from engine.endpoints.mavlink.enums import mav_enum_value

MESSAGES: dict[str, type[mavlink2.MAVLink_message]] = {cls.msgname: cls for cls in mavlink2.mavlink_map.values()}
ADDED_FIELDS: dict[str, tuple[str, ...]] = {"MISSION_ACK": ("ref_id",)}
"""Fields a source adds to a message's own: MISSION_ACK carries no reference, so the source
gives ``ref_id``, the id of the message whose mission the engine last uploaded to that vehicle."""
RADIO_STATUS = mavlink2.MAVLINK_MSG_ID_RADIO_STATUS
TUNNEL = mavlink2.MAVLINK_MSG_ID_TUNNEL
_INT_RANGES = {
    "int8_t": (-(2**7), 2**7 - 1), "uint8_t": (0, 2**8 - 1),
    "int16_t": (-(2**15), 2**15 - 1), "uint16_t": (0, 2**16 - 1),
    "int32_t": (-(2**31), 2**31 - 1), "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1), "uint64_t": (0, 2**64 - 1),
}



FLOAT32_MAX = 3.4028234663852886e38


@dataclass(frozen=True, slots=True)
class FieldSpec:
    type: str
    length: int
    """Array length; 0 for a scalar."""


def field_specs(cls: type[mavlink2.MAVLink_message]) -> dict[str, FieldSpec]:
    """``fieldtypes`` follows ``fieldnames`` but ``array_lengths`` follows wire order."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    return {name: FieldSpec(ftype, lengths[name]) for name, ftype in zip(cls.fieldnames, cls.fieldtypes)}


def _scalar(name: str, ftype: str, value: Any) -> int | float:
    if isinstance(value, str) or not isinstance(value, (int, float)):
        raise MessageRejected(f"field {name!r}: expected a number, got {type(value).__name__}")
    if ftype in ("float", "double"):
        try:
            number = float(value)
        except OverflowError:
            raise MessageRejected(f"field {name!r}: {value} is too large for {ftype}") from None
        if ftype == "float" and math.isfinite(number) and abs(number) > FLOAT32_MAX:
            raise MessageRejected(f"field {name!r}: {value} is too large for float (32 bits)")
        return number
    if isinstance(value, float):
        if not math.isfinite(value):
            raise MessageRejected(f"field {name!r}: {value} is not an integer")
        value = round(value)
    low, high = _INT_RANGES[ftype]
    if not low <= value <= high:
        raise MessageRejected(f"field {name!r}: {value} is outside {ftype} ({low}..{high})")
    return int(value)


def _coerce(name: str, spec: FieldSpec, value: Any) -> Any:
    if spec.type == "char":
        raw = value.encode() if isinstance(value, str) else value
        if not isinstance(raw, (bytes, bytearray)):
            raise MessageRejected(f"field {name!r}: expected a string")
        if len(raw) > max(spec.length, 1):
            raise MessageRejected(f"field {name!r}: {len(raw)} bytes exceed char[{spec.length}]")
        return bytes(raw)
    if not spec.length:
        return _scalar(name, spec.type, value)
    zero = 0.0 if spec.type in ("float", "double") else 0
    if isinstance(value, (bytes, bytearray)) and spec.type == "uint8_t":
        items: list[Any] = list(value)
    elif isinstance(value, (list, tuple)):
        items = [_scalar(name, spec.type, v) for v in value]
    else:
        raise MessageRejected(f"field {name!r}: expected an array of {spec.length}")
    if len(items) > spec.length:
        raise MessageRejected(f"field {name!r}: {len(items)} items exceed [{spec.length}]")
    return items + [zero] * (spec.length - len(items))


def _unset(spec: FieldSpec) -> Any:
    """The value of a field nobody set, as every MAVLink implementation gives it."""
    if spec.type == "char":
        return b""
    zero = 0.0 if spec.type in ("float", "double") else 0
    return [zero] * spec.length if spec.length else zero


def null_fields(fields: Mapping[str, Any]) -> list[str]:
    """The fields set to null, in the mapping's order (a null item of an array as ``name[i]``)."""
    nulls = []
    for name, value in fields.items():
        if value is None:
            nulls.append(str(name))
        elif isinstance(value, (list, tuple)):
            nulls.extend(f"{name}[{index}]" for index, item in enumerate(value) if item is None)
    return nulls


NEVER_GUESSED = ("a MAVLink field is never guessed: map it to a value (default(x, value) only where that "
                 "value is safe), or to nan() where MAVLink defines NaN as unset")


def null_problem(what: str, nulls: list[str]) -> str:
    """The error for fields set to null, naming each (``what``: the message, or where in a mission)."""
    names = ", ".join(map(repr, nulls))
    subject = f"field {names} is" if len(nulls) == 1 else f"fields {names} are"
    return f"{what}: {subject} null (the sink mapping gave null, or a path the message lacks); {NEVER_GUESSED}"


def refuse_nulls(msgname: str, fields: Any) -> None:
    """MessageRejected (stage ``sink mapping``) naming every field of ``fields`` set to null:
    what the pipeline runs on a MAVLink message sink's mapping output (the sink's field check),
    and :func:`build_message` again before encoding."""
    if isinstance(fields, Mapping):
        nulls = null_fields(fields)
        if nulls:
            raise MessageRejected(null_problem(msgname, nulls), stage="sink mapping")


def build_message(cls: type[mavlink2.MAVLink_message], fields: Any,
                  defaults: Mapping[str, Any] | None = None) -> mavlink2.MAVLink_message:
    """A message from a dict of fields. A field the dict leaves out takes ``defaults`` (the sink's
    target options) or 0 (empty for strings and arrays); a field set to null is refused, never
    guessed. An enum field (``command``, ``frame``, ...) may be given by name
    (``'MAV_CMD_COMPONENT_ARM_DISARM'``, or without the enum's prefix)."""
    if not isinstance(fields, Mapping):
        raise MessageRejected(f"{cls.msgname}: the sink mapping must produce an object of fields, got {type(fields).__name__}")
    specs = field_specs(cls)
    unknown = [name for name in fields if name not in specs]
    if unknown:
        raise MessageRejected(f"{cls.msgname} has no field(s) " + ", ".join(
            f"{name!r}{did_you_mean(str(name), specs)}" for name in unknown))
    refuse_nulls(cls.msgname, fields)
    defaults = defaults or {}
    enums = cls.fieldenums_by_name
    values = {}
    for name, spec in specs.items():
        if name in fields:
            value = fields[name]
            if isinstance(value, str) and name in enums:
                try:
                    value = mav_enum_value(value, enums[name])
                except ValueError as exc:
                    raise MessageRejected(f"field {name!r}: {exc}") from None
            values[name] = _coerce(name, spec, value)
        elif defaults.get(name) is not None:
            values[name] = _coerce(name, spec, defaults[name])
        else:
            values[name] = _unset(spec)
    return cls(**values)


def received_nan(cls: type[mavlink2.MAVLink_message], fields: Mapping[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`message_fields` for nulls: a null float (or float array item) is the
    NaN it stood for on the wire. For a route test's source message; a sink never does this."""
    specs = field_specs(cls)
    wire = dict(fields)
    for name, value in fields.items():
        spec = specs.get(name)
        if spec is None or spec.type not in ("float", "double"):
            continue
        if value is None:
            wire[name] = math.nan
        elif isinstance(value, (list, tuple)):
            wire[name] = [math.nan if item is None else item for item in value]
    return wire


def message_fields(msg: mavlink2.MAVLink_message) -> dict[str, Any]:
    """``to_dict()`` without ``mavpackettype``: strings decoded, arrays as lists, and NaN or
    infinite floats (MAVLink's "unknown", e.g. HIL or GPS fields) as None, as rosbridge does,
    so the message can become JSON. Integer fields are read in one C call (the telemetry hot
    path); only strings, floats and arrays are looked at one by one."""
    names = msg.get_fieldnames()
    plan = _READ_PLANS.get(type(msg))
    if plan is None or plan[0] is not names:
        plan = _READ_PLANS[type(msg)] = _read_plan(type(msg), names)
    _, read, checked = plan
    values = read(msg)
    fields = dict(zip(names, values)) if len(names) != 1 else {names[0]: values}
    for name in checked:
        value = fields[name]
        if isinstance(value, bytes):
            fields[name] = value.decode(errors="backslashreplace").rstrip("\x00")
        elif isinstance(value, float) and not math.isfinite(value):
            fields[name] = None
        elif isinstance(value, list) and any(isinstance(v, float) and not math.isfinite(v) for v in value):
            fields[name] = [None if isinstance(v, float) and not math.isfinite(v) else v for v in value]
    return fields


_READ_PLANS: dict[type, tuple[list[str], Callable[[Any], Any], tuple[str, ...]]] = {}


def _read_plan(cls: type, names: list[str]) -> tuple[list[str], Callable[[Any], Any], tuple[str, ...]]:
    """How :func:`message_fields` reads ``cls``: every field at once, then the fields that
    may need care (anything but a plain integer: strings, floats, arrays) one by one."""
    kinds = dict(zip(getattr(cls, "ordered_fieldnames", ()), zip(getattr(cls, "fieldtypes", ()),
                                                                 getattr(cls, "array_lengths", ()))))
    checked = tuple(name for name in names
                    if kinds.get(name, ("", 1))[1] or kinds.get(name, ("", 1))[0] not in _INT_RANGES)
    return names, operator.attrgetter(*names) if names else (lambda msg: ()), checked
