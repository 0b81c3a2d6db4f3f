"""MAVLink enums by name, from pymavlink's dialect tables (``common``), for mappings and sinks.

``mav_enum(4, 'MAV_STATE')`` -> ``'MAV_STATE_ACTIVE'``; ``mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM',
'MAV_CMD')`` -> 400; ``mav_flags(209, 'MAV_MODE_FLAG')`` -> the names of the bits set. No
hand-kept lists: a dialect upgrade brings its new names with it.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from engine.common.suggest import closest, did_you_mean
from engine.endpoints.mavlink.dialect import mavlink2


def _table(enum: str) -> dict[int, Any]:  # pymavlink's EnumEntry (untyped)
    table = mavlink2.enums.get(enum)
    if table is None:
        raise ValueError(f"unknown MAVLink enum {enum!r} (dialect: common){did_you_mean(enum, mavlink2.enums)}")
    return table


@cache
def _by_name(enum: str) -> dict[str, int]:
    return {entry.name: value for value, entry in _table(enum).items() if not entry.name.endswith("_ENUM_END")}


def mav_enum(value: int, enum: str) -> str | None:
    """The name of ``value`` in ``enum``; None for a value the dialect does not define."""
    entry = _table(enum).get(int(value))
    return None if entry is None or entry.name.endswith("_ENUM_END") else entry.name


def mav_enum_value(name: str, enum: str) -> int:
    """The value of ``name`` in ``enum`` (the enum's prefix may be left out: 'ACTIVE' in MAV_STATE)."""
    names = _by_name(enum)
    value = names.get(name, names.get(f"{enum}_{name}"))
    if value is None:
        raise ValueError(f"{name!r} is not a {enum} name{_suggestion(str(name), enum)}")
    return value


def _suggestion(name: str, enum: str) -> str:
    """Did-you-mean over the names without the enum's prefix, which every name shares and which
    would make any short guess look close (``ARM`` is not like ``MAV_CMD_NAV_ROI``)."""
    prefix = f"{enum}_"
    short = {full[len(prefix):] if full.startswith(prefix) else full: full for full in _by_name(enum)}
    match = closest(name[len(prefix):] if name.startswith(prefix) else name, short)
    return f"; did you mean {short[match]!r}?" if match is not None else ""


def mav_flags(value: int, enum: str) -> list[str]:
    """The names of the bits of ``value`` that ``enum`` (a bitmask enum) defines, lowest first."""
    value = int(value)
    return [name for name, bit in sorted(_by_name(enum).items(), key=lambda item: item[1])
            if bit and bit & (bit - 1) == 0 and value & bit]


def enum_name(enum: str, value: int) -> str:
    """For messages and logs: the name, or ``'ENUM value'`` for one the dialect lacks."""
    return mav_enum(value, enum) or f"{enum} {value}"


def enum_or_number(value: object, enum: str, what: str) -> int:
    """A sink field given by name or number."""
    if isinstance(value, str):
        return mav_enum_value(value, enum)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what}: expected a {enum} name or number, got {value!r}")
    return int(value)
