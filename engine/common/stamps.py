"""The one canonical form of a time stamp, ``{sec, nanosec}``, and conversions into it.

Why this form (see ``schemas/envelope.v1.json``): it is exact in every JSON parser (both
integers stay far below 2**53, where UNIX seconds as a float lose sub-microsecond precision
and nanoseconds as one integer do not fit a double), and it is what ROS 2's
``builtin_interfaces/Time`` is in rosbridge's JSON, so a header stamp maps without
conversion.

A protocol's own time fields (MAVLink's ``time_usec`` and ``time_boot_ms``) are converted by
its package (engine/endpoints/mavlink/functions.py), into this form.
"""

from __future__ import annotations

import datetime
import math
import time
from typing import Any

NS = 1_000_000_000


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
