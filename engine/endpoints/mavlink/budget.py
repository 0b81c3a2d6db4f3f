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
  MAVLink notes section 5): the buffer fills when we write faster than the air carries, so
  the budget is additive-increase / multiplicative-decrease on it, like ArduPilot's stream
  slow-down on the same field. Below 25 % free (1.5 KB waiting: at the budget's ceiling the
  rest fills in well under a report interval) the rate halves; below 50 % it drops by a
  fifth; at 90 % or more free (the radio is waiting for us) it climbs back by a tenth of the
  ceiling per report, so from half it is back at the ceiling in five seconds; in between it
  holds. Never below a tenth of the ceiling.
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
TXBUF_HALF, TXBUF_IDLE = 50, 90
"""Percent free of the radio's buffer: below HALF the budget comes down to drain it, at IDLE
or above it climbs back (see the module docstring)."""
RADIO_BUFFER = 2048
"""Bytes of a SiK radio's serial buffer (the ArduPilot wiki's figure; Si1000 boards have
1,850 for input): what txbuf is a percentage of."""
TARGET_USED, DRAIN_S = 0.25, 1.0
"""Where a decrease aims: a quarter of the buffer in use within a second, enough backlog to
fill every transmit window, room for a second of the air's rate above it."""
INCREASE = 0.1
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

    @classmethod
    def from_message(cls, msg: Any, at: float) -> RadioReport:
        return cls(at, int(msg.txbuf), int(msg.rssi), int(msg.noise), int(msg.remrssi), int(msg.remnoise))

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
        self.decreases = 0

    def sent(self, size: int) -> None:
        """A route frame of ``size`` bytes was written (the writer's hot path: one addition)."""
        self._sent += size

    def report(self, msg: Any, now: float) -> None:
        """A RADIO_STATUS from our radio: move the rate by its ``txbuf`` (module docstring)."""
        report = RadioReport.from_message(msg, now)
        previous, self.last = self.last, report
        sent, self._sent = self._sent, 0
        if previous is None or now - previous.at > STALE_S:
            self._rate = self.ceiling  # a fresh start: the previous reports say nothing now
            return
        if not self.ceiling:
            return
        if report.txbuf < TXBUF_HALF:
            self.decreases += 1
            self._rate = max(FLOOR * self.ceiling, min(self._rate, self._drain_rate(previous, report, sent)))
        elif report.txbuf >= TXBUF_IDLE:
            self._rate = min(self.ceiling, self._rate + INCREASE * self.ceiling)

    @staticmethod
    def _drain_rate(previous: RadioReport, report: RadioReport, sent: int) -> float:
        """The rate that brings the radio's buffer back to TARGET_USED within DRAIN_S: what the
        air carried since the previous report (what we wrote less what the buffer gained; the
        buffer was backlogged, so that is the air's rate) less the excess over DRAIN_S."""
        used, used_before = ((100 - r.txbuf) * RADIO_BUFFER / 100 for r in (report, previous))
        carried = max(0.0, sent - (used - used_before)) / max(report.at - previous.at, 0.1)
        return carried - (used - TARGET_USED * RADIO_BUFFER) / DRAIN_S

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
            "bytes_per_s": round(self.rate(now)), "ceiling": round(self.ceiling),
            "radio": None if last is None else {
                "txbuf_free_percent": last.txbuf, "fade_margin_db": last.fade_margin_db,
                "age_s": round(now - last.at, 1), "counts": fresh},
        }
