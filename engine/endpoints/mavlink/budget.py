"""The budget of a radio link: the bytes/s the routes' frames may take, following the radio.

A SiK radio takes serial input at 57,600 baud (5,760 B/s) but carries about 2.3-2.7 kB/s of
it one way over the air (a half-duplex TDM link: each side owns ~114 ms of a ~236 ms round),
and bytes that arrive while its 2 KB buffer is full are dropped without a word. With
``MAVLINK=1`` it injects RADIO_STATUS into its serial output about once a second, telling how
full that buffer is and how well both ends hear each other. The link's writer
(engine/endpoints/mavlink/port.py) paces every route's frame (message sinks and tunnel
fragments alike; commands, mission items, acknowledgements and heartbeats go unpaced) to
:meth:`RadioBudget.rate`, which follows those reports:

* **txbuf** (percent of the radio's buffer *free*; SiK's semantics, ``shared/research``
  MAVLink notes section 5): the buffer fills when we write faster than the air carries. Each
  report gives what the air carried since the previous one (what we wrote less what the
  buffer gained; a measure of the air's rate when the buffer stayed backlogged, averaged over
  reports), and the budget is that rate plus what brings the buffer to 40 % in use within two
  seconds (a proportional controller: above the target it drains, below it fills). A radio at
  90 % free or more is waiting for us: the budget climbs by a tenth of the ceiling per report
  (and to what was carried, if more), as it does before the air's rate is known. Never below
  a tenth of the ceiling. An interval in which the buffer ran dry cannot measure the air, but
  the air carried at least what left the buffer: the estimate moves halfway up to that. (It
  used to stay where the first, partial measurement put it while reports landed between
  the radio's transmit windows, at a few hundred bytes in use: the simulated vehicle's budget
  sat at 1,600-2,300 B/s with its frames queued and its radio's buffer empty a fifth of the
  time; bench/results/2026-11-23/goodput/.) ArduPilot slows its streams on the same field (down fast, up slowly);
  here the target keeps a backlog so that every transmit window leaves full.
* **rssi/noise, remrssi/remnoise** (both ends' signal and noise, in SiK units of about
  0.5 dB; the fade margin is ``(rssi - noise) / 2`` dB, the smaller of the two ends): a link
  designed for reliability keeps 10-20 dB of fade margin. Below 10 dB air packets start to be
  lost, each loss costs a retransmission (tunnel fragments, commands) that needs air time of
  its own, so the routes get at most half the ceiling; below 5 dB (the link is about to
  drop: the emulator reports rssi within 0-4 units of noise during an outage) a quarter.
  A side reporting 0/0 has not heard the other end yet and tells nothing.
* a report older than :data:`STALE_S` (no radio injects them, or it went away) no longer
  counts: the budget is the ceiling.

The ceiling is the link's ``bulk_rate`` (``tunnel.rate``, by default half the serial rate on
serial links: 2,880 B/s at 57,600 baud, just above what the air carries, so the buffer
report is what brings it down); networks have no ceiling and are not paced.

What does not fit the budget waits in the writer's queues, served by priority; a route
declared telemetry (``buffer: {latest_only: ...}``: only its newest message per key is worth
sending) has a queued frame replaced by a newer one with the same key, and the replaced one
is counted ``conflated`` by its route; every other route's frames wait their turn (events
must all arrive), counted as ``budget_queued`` on the link.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

STALE_S = 3.0
"""Seconds after which a RADIO_STATUS no longer describes the radio (SiK sends one a second)."""
TXBUF_IDLE = 90
"""Percent free of the radio's buffer at or above which the radio waits for us and the budget
climbs; below it, a buffer that grew measures the air's rate for the first time by what it
carried (at most the air's rate: the buffer was empty for part of the interval), so the first
sign of a backlog already steers (see the module docstring)."""
RADIO_BUFFER = 2048
"""Bytes of a SiK radio's serial buffer (the ArduPilot wiki's figure; Si1000 boards have
1,850 for input): what txbuf is a percentage of."""
TARGET_USED, DRAIN_S = 0.4, 2.0
"""Where a decrease aims: 40 % of the buffer in use (820 B), within two seconds. Enough
backlog that every transmit window leaves full (a window carries about 750 B; the flood
reference keeps 1,800 B waiting), little enough that a ``high`` frame waits at most ~0.3 s
for what the radio holds. Aiming at a quarter within one second cut the round trip's
goodput to 0.67 of the flood (the budget kept falling below the air's rate and climbed back
slowly); with this, see bench/results."""
INCREASE = 0.1
BACKLOG = 0.1
"""A buffer at least this full at two reports in a row was never empty between them: what
left it is what the air carried."""
FLOOR = 0.1
"""The budget never falls below this fraction of its ceiling: telemetry keeps trickling and
the next report (which needs the radio's buffer to drain) can raise it again."""
FADE_WEAK_DB, FADE_FAILING_DB = 10.0, 5.0
FADE_WEAK_CAP, FADE_FAILING_CAP = 0.5, 0.25


@dataclass(frozen=True, slots=True)
class RadioReport:
    """One RADIO_STATUS, with the loop time it arrived."""

    at: float
    txbuf: int
    rssi: int
    noise: int
    remrssi: int
    remnoise: int
    rxerrors: int = 0
    """The radio's count of packets received with errors (SiK: CRC failures and lost air packets)."""
    fixed: int = 0
    """The radio's count of packets its error correction repaired."""

    @classmethod
    def from_message(cls, msg: Any, at: float) -> RadioReport:
        return cls(at, int(msg.txbuf), int(msg.rssi), int(msg.noise), int(msg.remrssi), int(msg.remnoise),
                   int(msg.rxerrors), int(msg.fixed))

    @property
    def fade_margin_db(self) -> float | None:
        """The smaller fade margin of the two ends, in dB; None when neither end tells."""
        margins = [(signal - noise) / 2 for signal, noise in ((self.rssi, self.noise), (self.remrssi, self.remnoise))
                   if signal or noise]
        return min(margins) if margins else None


class RadioBudget:
    """Bytes/s the routes' frames may take on one link (see the module docstring)."""

    def __init__(self, ceiling: float) -> None:
        self.ceiling = ceiling
        """0: not paced (a network link)."""
        self.last: RadioReport | None = None
        self._rate = ceiling
        self._sent = 0
        """Bytes of route frames written since the last report."""
        self._air: float | None = None
        """What the air carries, bytes/s, measured while the radio's buffer stayed backlogged."""
        self.decreases = 0
        """Reports that brought the budget down (the status and the tests read it)."""

    def sent(self, size: int) -> None:
        """A route frame of ``size`` bytes was written (the writer's hot path: one addition)."""
        self._sent += size

    def report(self, msg: Any, now: float) -> None:
        """A RADIO_STATUS from our radio: steer the rate by its ``txbuf`` (module docstring)."""
        report = RadioReport.from_message(msg, now)
        previous, self.last = self.last, report
        sent, self._sent = self._sent, 0
        if previous is None or now - previous.at > STALE_S or not self.ceiling:
            self._rate = self.ceiling  # a fresh start: the previous reports say nothing now
            return
        used, used_before = ((100 - r.txbuf) * RADIO_BUFFER / 100 for r in (report, previous))
        carried = max(0.0, sent - (used - used_before)) / max(now - previous.at, 0.1)
        if min(used, used_before) >= BACKLOG * RADIO_BUFFER:  # backlogged throughout: the air's own rate
            self._air = carried if self._air is None else 0.5 * (self._air + carried)
        elif self._air is None and report.txbuf < TXBUF_IDLE and used > used_before:
            self._air = carried  # a backlog begins: the air carried at least this (the buffer was empty for a while)
        elif self._air is not None and carried > self._air:  # the buffer ran dry meanwhile: the air carries at least this
            self._air = 0.5 * (self._air + carried)  # halfway: bytes a stalled radio left in the serial line count as carried
        if self._air is None or report.txbuf >= TXBUF_IDLE:  # the radio waits for us: climb
            rate = max(self._rate, carried) + INCREASE * self.ceiling
        else:
            rate = self._air + (TARGET_USED * RADIO_BUFFER - used) / DRAIN_S
        rate = min(self.ceiling, max(FLOOR * self.ceiling, rate))
        self.decreases += rate < self._rate
        self._rate = rate

    def rate(self, now: float) -> float:
        """The budget now, bytes/s (0: unpaced)."""
        last = self.last
        if not self.ceiling or last is None or now - last.at > STALE_S:
            return self.ceiling
        rate = self._rate
        margin = last.fade_margin_db
        if margin is not None and margin < FADE_WEAK_DB:
            rate = min(rate, self.ceiling * (FADE_FAILING_CAP if margin < FADE_FAILING_DB else FADE_WEAK_CAP))
        return rate

    def status(self, now: float) -> dict[str, Any]:
        """For the connection's health: the budget and what the radio said last."""
        last = self.last
        fresh = last is not None and now - last.at <= STALE_S
        return {
            "bytes_per_s": round(self.rate(now)), "ceiling": round(self.ceiling), "decreases": self.decreases,
            "air_bytes_per_s": None if self._air is None else round(self._air),
            "radio": None if last is None else {
                "txbuf_free_percent": last.txbuf, "fade_margin_db": last.fade_margin_db,
                "age_s": round(now - last.at, 1), "counts": fresh},
        }
