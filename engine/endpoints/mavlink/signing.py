"""MAVLink 2 signing: a timestamp clock that never goes back (across restarts), and the check
of incoming signatures.

Incoming signatures are verified here rather than by pymavlink because pymavlink records a
stream's timestamp before checking the signature, so one forged frame with a far-future
timestamp would make every genuine frame of that stream look replayed.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import time
from collections.abc import Callable
from pathlib import Path

from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.settings import SigningConfig

SIGNING_EPOCH = 1_420_070_400
"""Signing timestamps count 10 us units since 2015-01-01 UTC."""
STREAM_WINDOW = 6_000_000
"""A new signed stream may lag our timestamp by at most 60 s (MAVLink spec, pymavlink)."""
TIMESTAMP_RESERVE = 6_000_000
"""How far ahead of the last used timestamp the file is written, so a crash never reuses one."""


def signing_now() -> int:
    return int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 100_000)


class SigningClock:
    """Keeps the outgoing signing timestamp at or after wall clock and after every value used
    before, across restarts: the file holds a value reserved ahead of use, rewritten (atomically)
    when half of the reserve is spent."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.reserved = 0

    def start(self) -> int:
        stored = 0
        if self.path is not None:
            with contextlib.suppress(OSError, ValueError):
                stored = int(self.path.read_text().strip() or 0)
        start = max(signing_now(), stored)
        self._persist(start + TIMESTAMP_RESERVE)
        return start

    def advance(self, current: int) -> int:
        stamp = max(current, signing_now())
        if stamp + TIMESTAMP_RESERVE // 2 >= self.reserved:
            self._persist(stamp + TIMESTAMP_RESERVE)
        return stamp

    def _persist(self, value: int) -> None:
        self.reserved = value
        if self.path is None:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, f"{value}\n".encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)


class SignatureCheck:
    """Verifies incoming frames; returns the stats key of the rejection, or None to accept."""

    def __init__(self, config: SigningConfig, local_timestamp: Callable[[], int],
                 clock: Callable[[], float] = time.time) -> None:
        self.config = config
        self.clock = clock
        self.local_timestamp = local_timestamp
        self.streams: dict[tuple[int, int, int], int] = {}
        self.newest = 0

    def __call__(self, buf: bytes | bytearray) -> str | None:
        if buf[0] != mavlink2.PROTOCOL_MARKER_V2 or not buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
            msg_id = buf[5] if buf[0] != mavlink2.PROTOCOL_MARKER_V2 else buf[7] | buf[8] << 8 | buf[9] << 16
            return None if msg_id in self.config.allow_unsigned else "unsigned_rejected"
        link_id = buf[-13]
        stamp = int.from_bytes(buf[-12:-6], "little")
        signed = bytes(buf[:-6])
        if hashlib.sha256(self.config.key + signed).digest()[:6] != bytes(buf[-6:]) and not self._old_key_signed(signed, bytes(buf[-6:])):
            return "bad_signature"
        stream = (link_id, buf[5], buf[6])
        last = self.streams.get(stream)
        if last is not None and stamp <= last:
            return "replayed"
        if last is None and stamp + STREAM_WINDOW < max(self.local_timestamp(), self.newest):
            return "replayed"
        self.streams[stream] = stamp
        self.newest = max(self.newest, stamp)
        return None

    def _old_key_signed(self, signed: bytes, signature: bytes) -> bool:
        """A key rotation: a frame signed with an old key is accepted until that key's deadline
        (wall clock; the frame's own timestamp is the sender's to choose)."""
        now = self.clock()
        return any(now < until and hashlib.sha256(key + signed).digest()[:6] == signature
                   for key, until in self.config.accepted)

