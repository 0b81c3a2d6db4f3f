"""A canonical field named ``a.b``, and the key a message has under it.

A throttle's slots, a buffer's ``latest_only``, a store's ``remember`` and a MAVLink link's
conflation all group messages by the value of one canonical field; they name it with one
pattern and read it with one function, kept here so the protocol packages and the route
language can use them without importing the running engine.
"""

from __future__ import annotations

from typing import Any

FIELD_PATH = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$"
"""A canonical field named as ``a.b`` (``throttle.per``, ``buffer.latest_only.per``)."""


def slot_key(canonical: Any, per: tuple[str, ...] | None) -> Any:
    """The value of the canonical field ``per`` that groups messages (a throttle's slot, the
    buffer's ``latest_only`` key); None for every message without ``per``."""
    if per is None:
        return None
    value = canonical
    for part in per:
        value = value.get(part) if isinstance(value, dict) else None
    return value if isinstance(value, (str, int, float, bool)) or value is None else repr(value)
