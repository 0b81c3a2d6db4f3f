"""MAVLink frames out of received bytes, so that noise costs only itself.

pymavlink's ``parse_buffer`` (with ``robust_parsing``) keeps one byte stream per parser: a
partial frame at the end of one chunk waits for the next chunk, and a frame that fails its CRC
is thrown away whole, with every byte its (possibly damaged) length byte claimed. Over UDP that
let a 2-byte datagram ``FD 1E`` (a start byte and a length) swallow the good frame in the next
datagram: 1 of 500 GLOBAL_POSITION_INT frames reached RabbitMQ with one such datagram after
each (issue 31). On a serial line, one damaged length byte in noise swallowed up to 280 bytes
of good frames after it. A frame of a message id the dialect does not know is not checked at
all (pymavlink cannot: the CRC needs the message's ``crc_extra``), so random bytes starting
``FD 00 00`` passed as an "unknown message" of whatever length they claimed.

Here framing is done by the engine and decoding (CRC, fields) by pymavlink's ``decode``:

* a **datagram** (:meth:`FrameReader.datagram`) is parsed on its own: a frame that does not end
  inside it is counted ``truncated`` and dropped, never joined to the next datagram (every
  MAVLink implementation sends whole frames per datagram: ArduPilot, PX4, mavlink-router,
  mavutil);
* a **stream** (serial, TCP: :meth:`FrameReader.stream`) keeps a partial frame for the next
  chunk, for a while: a frame that has not completed after :data:`.port.STALE_FRAME_S` is given
  up (:meth:`FrameReader.give_up_waiting`), so a false start byte cannot hold the frames
  behind it on a quiet link;
* in both, a candidate frame that is rejected (bad CRC, impossible header, unknown message id)
  costs only itself: parsing resumes at the next start byte *inside* the rejected bytes, so a
  good frame that a false start byte's length covered is still found. (The C library also
  restarts after the rejected frame, not inside it.)

Counting (keys of the connection's stats, see :data:`.port.PORT_STATS`): one count per region
of rejected bytes, whatever the resync tried inside it, so a damaged frame counts once:
``bad_crc`` (a whole frame whose CRC fails), ``bad_data`` (bytes that are no frame: no start
byte, or an impossible header), ``truncated`` (a datagram ending inside a frame, or a stream frame given up),
``unknown_message`` (a well-formed frame of an id the dialect does not have; its bytes are
searched for frames too, as they could not be checked). :data:`BAD_FRAME_REASONS` are the
bad frames ``/metrics`` exports per link.

Cost: a good frame is one regex search, a few header reads and pymavlink's ``decode`` (what
``parse_buffer`` ends in too), so it is no slower: 20,000 GLOBAL_POSITION_INT frames, one per
datagram, 151,000 frames/s against ``parse_buffer``'s 101,000 (93,000 against 73,000 with the
2-core machine loaded by other tests); from 4 KB stream chunks 176,000 against 148,000 (91,000
against 81,000). On a stream of 500 frames with 1-40 random bytes after each (and a lone
``FD 1E`` after every seventh) fed in 97-byte chunks, all 500 come out; ``parse_buffer``
gives 280.
"""

from __future__ import annotations

import re

from engine.endpoints.mavlink.dialect import mavlink2

BAD_FRAME_REASONS = ("bad_crc", "bad_data", "truncated")
"""Why received bytes were thrown away as a bad frame (stats keys, ``reason`` label in /metrics)."""

_START = re.compile(b"[\xfd\xfe]")
_V2 = mavlink2.PROTOCOL_MARKER_V2
_V2_HEADER = mavlink2.HEADER_LEN_V2
_V1_HEADER = mavlink2.HEADER_LEN_V1
_CHECKSUM = 2
_SIGNATURE = mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN
_SIGNED = mavlink2.MAVLINK_IFLAG_SIGNED
_UNKNOWN = mavlink2.MAVLink_unknown
_MAX_FRAME = _V2_HEADER + 255 + _CHECKSUM + _SIGNATURE


def frame_size(buf: bytes, at: int) -> int | None:
    """The length of the frame whose start byte is at ``buf[at]`` (at least 3 bytes there), by
    its header alone; None for a MAVLink 2 header with an incompatibility flag no frame has."""
    length = buf[at + 1]
    if buf[at] == _V2:
        flags = buf[at + 2]
        if flags & ~_SIGNED:
            return None
        return _V2_HEADER + length + _CHECKSUM + (_SIGNATURE if flags & _SIGNED else 0)
    return _V1_HEADER + length + _CHECKSUM


def frame_headers(data: bytes, checked: bool = False) -> list[tuple[int, int, int, int]]:
    """``(start, end, system id, message id)`` of each frame of a datagram, read from the
    headers without decoding (MAVLink 2: ``FD``, system id at byte 5, message id at 7-9; MAVLink
    1: ``FE``, system id at byte 3, message id at 5), for handing frames on by their sender
    (split.py); what is no frame is skipped, as a frame cut off at the end. The fields are the
    receiver's :class:`FrameReader`'s to check; the CRC too, unless ``checked``: then a frame
    whose CRC fails is no frame, and the scan goes on from the byte after its start byte, as
    the receiver's parser does (a false start byte in junk cannot swallow the frame after it)."""
    found: list[tuple[int, int, int, int]] = []
    end, at = len(data), 0
    while at < end:
        match = _START.search(data, at)
        if match is None:
            break
        at = match.start()
        size = frame_size(data, at) if end - at >= 3 else None
        header = _V2_HEADER if data[at] == _V2 else _V1_HEADER
        if size is None or end - at < max(size, header):
            at += 1
            continue
        if data[at] == _V2:
            frame = (at, at + size, data[at + 5], int.from_bytes(data[at + 7:at + 10], "little"))
        else:
            frame = (at, at + size, data[at + 3], data[at + 5])
        if checked and not crc_holds(data, *frame[:2], frame[3]):
            at += 1
            continue
        found.append(frame)
        at += size
    return found


def tiles(headers: list[tuple[int, int, int, int]], size: int) -> bool:
    """Whether the frames :func:`frame_headers` found cover a datagram of ``size`` bytes
    exactly, end to end (what a vehicle or a router sends): nothing beside them that a false
    start byte could have come from."""
    return bool(headers) and headers[0][0] == 0 and headers[-1][1] == size and all(
        before[1] == after[0] for before, after in zip(headers, headers[1:]))


def crc_holds(data: bytes, start: int, end: int, msg_id: int) -> bool:
    """Whether the frame ``data[start:end]`` (as :func:`frame_headers` found it) has a good
    CRC, without decoding its fields (the dialect's CRC, fastcrc where installed); a message id
    the dialect does not know cannot be checked: False."""
    known = mavlink2.mavlink_map.get(msg_id)
    if known is None:
        return False
    signed = data[start] == _V2 and data[start + 2] & _SIGNED
    crc_at = end - _CHECKSUM - (_SIGNATURE if signed else 0)
    crc = mavlink2.x25crc(data[start + 1:crc_at] + bytes((known.crc_extra,))).crc
    return bool(crc == int.from_bytes(data[crc_at:crc_at + _CHECKSUM], "little"))


class FrameReader:
    """Frames of one link (or one peer of a TCP server) as pymavlink messages; rejected bytes
    counted into ``stats`` (see the module docstring)."""

    __slots__ = ("stats", "_decoder", "_pending", "_counted", "_consumed")

    def __init__(self, stats: dict[str, int]) -> None:
        self.stats = stats
        for key in (*BAD_FRAME_REASONS, "unknown_message"):
            stats.setdefault(key, 0)
        self._decoder = mavlink2.MAVLink(None)
        """Decodes only (no signing key: the port checks signatures itself, see signing.py)."""
        self._pending = b""
        """A stream's bytes from the start of a frame that has not all arrived yet."""
        self._counted = 0
        """How many of ``_pending``'s bytes lie in a bad region already counted."""
        self._consumed = 0
        """Stream bytes before ``_pending``: :attr:`waiting_at` names the waiting frame by it."""

    @property
    def waiting_at(self) -> int | None:
        """Where in the stream the frame still arriving starts (None: nothing waits), so a
        caller can tell whether the frame that waits now is the one that waited before."""
        return self._consumed if self._pending else None

    def datagram(self, data: bytes) -> list[mavlink2.MAVLink_message]:
        """The frames of one datagram; a frame cut off at its end is ``truncated``."""
        frames, _, _ = self._scan(data, 0, final=True)
        return frames

    def stream(self, data: bytes) -> list[mavlink2.MAVLink_message]:
        """The frames completed by ``data``; a frame still arriving waits for the next chunk."""
        buf = self._pending + data if self._pending else data
        return self._continue(buf, 0, self._counted)

    def give_up_waiting(self) -> list[mavlink2.MAVLink_message]:
        """The frame still arriving is given up (counted ``truncated``) and its bytes are
        searched for frames, as a rejected frame's are. For a start byte in noise whose length
        claims up to 280 bytes: on a quiet link (a heartbeat a second) the frames behind it
        would wait for those bytes for many seconds (the port calls this once a frame waited
        :data:`.port.STALE_FRAME_S`)."""
        buf = self._pending
        if not buf:
            return []
        if self._counted == 0:
            self.stats["truncated"] += 1
        return self._continue(buf, 1, len(buf))

    def _continue(self, buf: bytes, at: int, counted_to: int) -> list[mavlink2.MAVLink_message]:
        frames, rest, counted_to = self._scan(buf, counted_to, final=False, at=at)
        self._pending = buf[rest:]
        self._counted = max(0, counted_to - rest)
        self._consumed += rest
        return frames

    def _scan(self, buf: bytes, counted_to: int, final: bool,
              at: int = 0) -> tuple[list[mavlink2.MAVLink_message], int, int]:
        """Frames in ``buf`` from ``at``, where the unparsed rest starts (``len(buf)`` when
        ``final``) and ``counted_to``: rejected bytes before it are counted already (one count
        per bad region)."""
        frames: list[mavlink2.MAVLink_message] = []
        stats = self.stats
        end = len(buf)
        while at < end:
            found = _START.search(buf, at)
            start = found.start() if found is not None else end
            if start > at:  # bytes that are no frame
                if at >= counted_to:
                    stats["bad_data"] += 1
                counted_to = max(counted_to, start)
                at = start
                continue
            if end - at < 3:
                if not final:
                    return frames, at, counted_to
                if at >= counted_to:
                    stats["truncated"] += 1
                counted_to = end
                at += 1
                continue
            size = frame_size(buf, at)
            if size is None:  # no MAVLink 2 frame has other incompatibility flags
                if at >= counted_to:
                    stats["bad_data"] += 1
                counted_to = max(counted_to, at + 3)
                at += 1
                continue
            if end - at < size:
                if not final:
                    return frames, at, counted_to
                if at >= counted_to:
                    stats["truncated"] += 1
                counted_to = end
                at += 1
                continue
            try:
                msg = self._decoder.decode(bytearray(buf[at:at + size]))
            except Exception:  # MAVError mostly; whatever hostile bytes make decode raise costs only them
                if at >= counted_to:
                    stats["bad_crc"] += 1
                counted_to = max(counted_to, at + size)
                at += 1
                continue
            if isinstance(msg, _UNKNOWN):
                if at >= counted_to:
                    stats["unknown_message"] += 1
                counted_to = max(counted_to, at + size)
                at += 1
                continue
            frames.append(msg)
            at += size
            counted_to = at
        return frames, end, counted_to
