"""MAVLink's functions for mappings: its time fields as stamps, and its enums by name.

``time_usec`` is UNIX time or time since boot, told apart by magnitude (as the MAVLink spec
says); ``time_boot_ms`` is always since boot. A boot-relative time cannot be placed on the
UNIX time line without a clock offset (MAVROS learns it from TIMESYNC), so such stamps are
the reception time, as MAVROS does before it is synchronised; the vehicle's own clock stays
available in the message (``time_boot_ms``). Enum names come from pymavlink's dialect tables
(:mod:`.enums`).

engine/language/mapping.py adds :class:`Functions` to a mapping's functions only when the mapping
calls one of the names the registry lists for it (engine/endpoints/__init__.py), so a route
file without MAVLink functions does not import pymavlink.
"""

from __future__ import annotations

from typing import Any

from jmespath import functions

from engine.common import stamps
from engine.endpoints.mavlink import enums

UNIX_USEC_FROM = 1_000_000_000_000_000
"""``time_usec`` at or above this (September 2001 as UNIX time, 31 years as time since boot)
is UNIX time."""


def from_time_usec(time_usec: Any) -> dict[str, int]:
    """MAVLink ``time_usec``: exact when it is UNIX time, the reception time when since boot."""
    if isinstance(time_usec, bool) or not isinstance(time_usec, (int, float)) or time_usec < 0:
        raise stamps.StampError(f"stamp_usec: {time_usec!r} is not a MAVLink time_usec")
    if time_usec >= UNIX_USEC_FROM:
        return stamps.from_ns(int(time_usec) * 1000)
    return stamps.now()


def from_time_boot_ms(time_boot_ms: Any) -> dict[str, int]:
    """MAVLink ``time_boot_ms``: the reception time (no clock offset without TIMESYNC)."""
    if isinstance(time_boot_ms, bool) or not isinstance(time_boot_ms, (int, float)) or time_boot_ms < 0:
        raise stamps.StampError(f"stamp_boot_ms: {time_boot_ms!r} is not a MAVLink time_boot_ms")
    return stamps.now()


class Functions(functions.Functions):
    UNREPEATABLE = ("stamp_usec", "stamp_boot_ms")
    """Functions whose value may be the reception time (see above): ``replay`` does not compare
    what they make (engine/language/mapping.py ``unrepeatable_keys``)."""

    @functions.signature({"types": ["number"]})
    def _func_stamp_usec(self, time_usec: int) -> dict[str, int]:
        return from_time_usec(time_usec)

    @functions.signature({"types": ["number"]})
    def _func_stamp_boot_ms(self, time_boot_ms: int) -> dict[str, int]:
        return from_time_boot_ms(time_boot_ms)

    @functions.signature({"types": ["number"]}, {"types": ["string"]})
    def _func_mav_enum(self, value: int, enum: str) -> str | None:
        return enums.mav_enum(value, enum)

    @functions.signature({"types": ["string"]}, {"types": ["string"]})
    def _func_mav_enum_value(self, name: str, enum: str) -> int:
        return enums.mav_enum_value(name, enum)

    @functions.signature({"types": ["number"]}, {"types": ["string"]})
    def _func_mav_flags(self, value: int, enum: str) -> list[str]:
        return enums.mav_flags(value, enum)
