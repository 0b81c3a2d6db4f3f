"""A key's share of N, the same in every process and on every run: which worker of
``run --workers N`` runs a route (engine/running/placement.py) and which worker follows a
discovered stream of a route every worker runs (a ROS 2 topic pattern's agents). Python's
``hash()`` of a str is salted per process, so it cannot say this."""

from __future__ import annotations

import hashlib


def share_of(key: str, count: int) -> int:
    """The share (0..count-1) ``key`` falls in."""
    return int.from_bytes(hashlib.blake2b(key.encode(), digest_size=8).digest(), "big") % count
