"""The one canonical form of a time stamp, ``{sec, nanosec}``, and conversions into it.

Why this form (see ``schemas/envelope.v1.json``): it is exact in every JSON parser (both
integers stay far below 2**53, where UNIX seconds as a float lose sub-microsecond precision
and nanoseconds as one integer do not fit a double), and it is what ROS 2's
``builtin_interfaces/Time`` is in rosbridge's JSON, so a header stamp maps without
conversion.

MAVLink's ``time_usec`` is UNIX time or time since boot, told apart by magnitude (as the
MAVLink spec says); ``time_boot_ms`` is always since boot. A boot-relative time cannot be
placed on the UNIX time line without a clock offset (MAVROS learns it from TIMESYNC), so
such stamps are the reception time, as MAVROS does before it is synchronised; the vehicle's
own clock stays available in the message (``time_boot_ms``).
"""

from __future__ import annotations

import datetime
import math
import time
from typing import Any

NS = 1_000_000_000
UNIX_USEC_FROM = 1_000_000_000_000_000
"""``time_usec`` at or above this (September 2001 as UNIX time, 31 years as time since boot)
is UNIX time."""


class StampError(ValueError):
    pass


def from_ns(ns: int) -> dict[str, int]:
    return {"sec": ns // NS, "nanosec": ns % NS}


def now() -> dict[str, int]:
    return from_ns(time.time_ns())


def to_stamp(value: Any) -> dict[str, int]:
    """UNIX seconds (a number) or a ``{sec, nanosec}`` object -> ``{sec, nanosec}``."""
    if isinstance(value, dict):
        sec, nanosec = value.get("sec"), value.get("nanosec", 0)
        if type(sec) is not int or type(nanosec) is not int or sec < 0 or not 0 <= nanosec < NS:
            raise StampError(f"to_stamp: {value!r} is not {{sec, nanosec}} with integers, 0 <= nanosec < 1e9")
        return {"sec": sec, "nanosec": nanosec}
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise StampError(f"to_stamp: {value!r} is neither UNIX seconds nor {{sec, nanosec}}")
    if isinstance(value, int):
        return {"sec": value, "nanosec": 0}
    sec = math.floor(value)  # a double holds UNIX seconds to about 0.2 us: round to the microsecond
    return from_ns(sec * NS + round((value - sec) * 1_000_000) * 1000)


def to_iso8601(stamp: dict[str, int]) -> str:
    """``{sec, nanosec}`` -> ISO 8601 UTC with milliseconds, ``Z`` for UTC."""
    moment = datetime.datetime.fromtimestamp(stamp["sec"], datetime.timezone.utc)
    return moment.strftime("%Y-%m-%dT%H:%M:%S") + f".{stamp['nanosec'] // 1_000_000:03d}Z"


def from_time_usec(time_usec: Any) -> dict[str, int]:
    """MAVLink ``time_usec``: exact when it is UNIX time, the reception time when since boot."""
    if isinstance(time_usec, bool) or not isinstance(time_usec, (int, float)) or time_usec < 0:
        raise StampError(f"stamp_usec: {time_usec!r} is not a MAVLink time_usec")
    if time_usec >= UNIX_USEC_FROM:
        return from_ns(int(time_usec) * 1000)
    return now()


def from_time_boot_ms(time_boot_ms: Any) -> dict[str, int]:
    """MAVLink ``time_boot_ms``: the reception time (no clock offset without TIMESYNC)."""
    if isinstance(time_boot_ms, bool) or not isinstance(time_boot_ms, (int, float)) or time_boot_ms < 0:
        raise StampError(f"stamp_boot_ms: {time_boot_ms!r} is not a MAVLink time_boot_ms")
    return now()
