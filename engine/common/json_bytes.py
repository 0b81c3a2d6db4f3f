"""JSON bytes of what a route carried, for the operator's views (the status file, the taps,
the console's document): orjson, and the standard library where orjson refuses the value.

orjson refuses integers beyond 64 bits, which the engine carries exactly (engine/common/schemas.py
parses them with the standard library, and ``canonical_bytes`` writes them so), and strings with
a lone surrogate (a JSON ``\\ud800`` escape the standard library parses). One such value where a
view was written raised ``TypeError``: the status file's reporter ended (the file never written
again), a tapped route failed each batch after its sink took it (the source redelivered it, the
sink took it again, without end), the console's document failed (a position's ``alt_msl`` is
unbounded). The standard library is ten times slower but runs only for such a value.
"""

from __future__ import annotations

import json
from typing import Any

import orjson


def json_bytes(value: Any, option: int = 0) -> bytes:
    """``orjson.dumps(value, default=str, option=option)``; where orjson refuses ``value``,
    ``json.dumps`` of it, honouring ``OPT_INDENT_2`` and ``OPT_APPEND_NEWLINE`` (non-string keys
    as strings as orjson's ``OPT_NON_STR_KEYS``; numpy arrays as their ``str``)."""
    try:
        return orjson.dumps(value, default=str, option=option)
    except TypeError:  # orjson.JSONEncodeError is one
        indented = bool(option & orjson.OPT_INDENT_2)
        text = json.dumps(value, default=str, indent=2 if indented else None, separators=None if indented else (",", ":"))
        return (text + ("\n" if option & orjson.OPT_APPEND_NEWLINE else "")).encode()
