"""The radio's budget (issue 22): the link's rate follows RADIO_STATUS, and what does not fit is
conflated (telemetry) or queued (events), counted either way.

Real parts: the engine in this process with an AMQP source (the session's private RabbitMQ
node) and a MAVLink sink on the emulated SiK radio (rabbitros_sim/sik_radio.py: 57,600 baud,
TDM, a 2 KB radio buffer that drops what overflows it), a MAVLink peer on the far radio.

Two routes share the link: ``positions`` (telemetry: ``buffer: {latest_only: {per: agent}}``)
sends VISION_POSITION_ESTIMATE (an external position estimate, 129-byte frames) for 12 agents at
3.9 kB/s, more than the air carries (~2.7 kB/s of such frames) but less than the budget's
ceiling (5,000 B/s, the connection's ``budget``);
``events`` sends STATUSTEXT twice a second, each of which must arrive.

* With the radio reporting (RADIO_STATUS every 0.5 s), its buffer fills, txbuf falls below
  50 % free, the budget comes down below the offered load, and positions are conflated:
  counted ``conflated`` by the route (engine/running/observe.py); no byte is lost in the radio; every
  event arrives, none conflated.
* The control: the same load with a radio that sends no RADIO_STATUS. The budget stays at its
  ceiling, nothing is conflated, and the radio silently drops what overflows its buffer.
"""

from __future__ import annotations

import asyncio
import json
import os
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aio_pika
import pytest

os.environ.setdefault("MAVLINK20", "1")

from engine.endpoints import mavlink  # noqa: E402
from engine.running.runtime import Engine  # noqa: E402
from tests.support.udp_vehicle import mavlink_connection  # noqa: E402
from rabbitros_sim import sik_radio  # noqa: E402
from tests.support.amqp_helpers import started_with_client  # noqa: E402
from tests.support.waiting import wait_for

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  radio: {{mavlink: "{link}", baud: 57600, budget: {budget}}}
routes:
  - name: positions
    source: {{amqp: {{connection: gcs, exchange: {exchange}, binding_key: pos, queue: {exchange}-pos}}}}
    schema: raw_json
    buffer: {{latest_only: {{per: agent}}}}
    sink:
      mavlink: {{connection: radio, message: VISION_POSITION_ESTIMATE}}
      mapping: "{{usec: seq, x: agent, y: `2.5`, z: `-10.0`, roll: `0.1`, pitch: `0.2`, yaw: `0.3`, covariance: covariance, reset_counter: `1`}}"
  - name: events
    source: {{amqp: {{connection: gcs, exchange: {exchange}, binding_key: event, queue: {exchange}-event}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: radio, message: STATUSTEXT}}
      mapping: "{{severity: `6`, text: text}}"
"""
BUDGET = 5000
POSITION_RATE = 30.0
"""VISION_POSITION_ESTIMATE frames (with their covariance) are 129 bytes: 3,870 B/s, above
what the air carries of them (one per air packet, ~2.7 kB/s), below the ceiling."""
AGENTS = 12
"""Each agent's position comes every 0.4 s: one waits for a newer one with its key only once
the budget holds the queue back (not for the AMQP source's bursts)."""
SECONDS = 6.0
EVENT_EVERY = 0.5


def run(tmp_path: Path, schemas_dir: Path, amqp_url: str, radio_status: float | None) -> dict[str, Any]:
    """Offer the load for SECONDS; the routes' counters, what arrived, and the radio's."""
    tag = uuid.uuid4().hex[:8]
    exchange = f"budget-{tag}"
    directory = tmp_path / f"routes-{tag}"
    directory.mkdir()

    async def scenario() -> dict[str, Any]:
        async with sik_radio.SikRadioPair(seed=5, radio_status_interval=radio_status) as pair:
            (directory / "radio.yaml").write_text(ROUTES.format(url=amqp_url, link=pair.link_a, budget=BUDGET,
                                                                exchange=exchange))
            uav = mavlink.TRANSPORT.connect("uav", {"url": pair.link_b, "baud": 57600, "source_system": 1,
                                                    "source_component": 1, "mav_type": 2})
            arrived: Counter[str] = Counter()
            uav.listen(None, lambda msg: arrived.update([msg.get_type()]))
            await uav.open()
            engine = Engine(directory, schemas_dir)
            try:
                async with started_with_client(engine, amqp_url) as connection:
                    channel = await connection.channel()
                    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
                    await offer(target)

                    def drained() -> bool:  # the queued frames drain; every event arrives
                        routes = engine.status()["routes"]
                        lost = pair.stats()["a"].serial_rx_dropped  # without reports: some events never arrive
                        return bool((lost or arrived["STATUSTEXT"] >= events_sent()) and all(
                            settled(routes[name]) for name in ("positions", "events")))

                    await wait_for(drained, 20, "the queued frames drained and every event arrived",
                                   lambda: (dict(arrived), engine.status()["routes"]))
                    link = mavlink_connection(engine, "radio")
                    return {"routes": engine.status()["routes"], "arrived": dict(arrived),
                            "link": dict(link.stats), "decreases": link.port.budget.decreases,
                            "budget": link.health()["budget"],
                            "radio": pair.stats()["a"]}
            finally:
                await uav.close()

    return asyncio.run(asyncio.wait_for(scenario(), 60))


def events_sent() -> int:
    return int(SECONDS / EVENT_EVERY)


def settled(route: dict[str, Any]) -> bool:
    return route["received"] > 0 and route["received"] == route["delivered"] + route["conflated"] + route["failed"]


async def offer(target: Any) -> None:
    """Positions at POSITION_RATE (round-robin over the agents) and an event every EVENT_EVERY."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    sent = events = 0
    while (now := loop.time()) < start + SECONDS:
        while sent < (now - start) * POSITION_RATE:
            body = {"agent": sent % AGENTS, "seq": sent, "covariance": [0.5] * 21}
            await target.publish(aio_pika.Message(json.dumps(body).encode()), "pos")
            sent += 1
        while events < min(events_sent(), (now - start) / EVENT_EVERY):
            await target.publish(aio_pika.Message(json.dumps({"text": f"event {events}"}).encode()), "event")
            events += 1
        await asyncio.sleep(0.01)  # pacing: the offered load's tick
    while events < events_sent():
        await target.publish(aio_pika.Message(json.dumps({"text": f"event {events}"}).encode()), "event")
        events += 1


@pytest.mark.alone  # the emulated radio's buffer against the engine's pace
def test_the_budget_conflates_telemetry_when_radio_status_reports_a_filling_buffer(
        tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    got = run(tmp_path, schemas_dir, amqp_url, radio_status=0.5)
    positions, events = got["routes"]["positions"], got["routes"]["events"]
    print(f"\nwith RADIO_STATUS: positions {positions['received']} received, {positions['delivered']} sent, "
          f"{positions['conflated']} conflated; events {events['delivered']}/{events['received']}; "
          f"budget decreases {got['decreases']}; link {got['link']['budget_queued']} queued, "
          f"{got['link']['budget_conflated']} conflated; radio dropped {got['radio'].serial_rx_dropped} B; "
          f"budget at the end {got['budget']}")
    assert got["decreases"] > 0, "the radio never reported a filling buffer: the load did not exceed the air"
    assert positions["conflated"] > 0, positions
    assert positions["conflated"] == got["link"]["budget_conflated"], (positions, got["link"])
    assert positions["delivered"] + positions["conflated"] == positions["received"], positions
    assert got["radio"].serial_rx_dropped == 0, "the radio's buffer overflowed: the budget did not follow it"
    assert events["received"] == events["delivered"] == events_sent() and events["conflated"] == 0, events
    assert got["arrived"].get("STATUSTEXT", 0) >= events_sent(), got["arrived"]
    assert got["link"]["budget_queued"] > 0, got["link"]


@pytest.mark.alone  # the emulated radio's buffer against the engine's pace
def test_without_radio_status_the_budget_stays_at_its_ceiling_and_the_radio_drops(
        tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    """The control: the conflation above is the reports' doing, and without them the radio
    loses bytes (what the budget exists to prevent)."""
    got = run(tmp_path, schemas_dir, amqp_url, radio_status=None)
    positions = got["routes"]["positions"]
    print(f"\nwithout RADIO_STATUS: positions {positions['received']} received, {positions['conflated']} conflated; "
          f"radio dropped {got['radio'].serial_rx_dropped} B")
    assert got["decreases"] == 0
    assert positions["conflated"] <= positions["received"] // 20, positions
    assert got["radio"].serial_rx_dropped > 0, "the load never overflowed the radio: the first test proves nothing"


def radio_status(txbuf: int, rssi: int = 190, noise: int = 40, remrssi: int = 188, remnoise: int = 41) -> Any:
    from engine.endpoints.mavlink.codec import mavlink2

    return mavlink2.MAVLink_radio_status_message(rssi, remrssi, txbuf, noise, remnoise, 0, 0)


def test_the_budget_follows_txbuf_and_the_fade_margin() -> None:
    """The rules of engine/endpoints/mavlink/budget.py on RADIO_STATUS messages. A radio whose
    air carries 2,000 B/s, fed at the budget once a second: the buffer never overflows, settles
    near 40 % in use, and the budget near the air's rate. A fading link (either end's rssi
    within 10 dB, 20 units, of its noise) caps it at half, within 5 dB at a quarter; a report
    older than 3 s no longer counts."""
    from engine.endpoints.mavlink.budget import RadioBudget

    budget = RadioBudget(2880.0)
    assert budget.rate(0.0) == 2880.0, "no report: the ceiling"
    used, air, levels = 0.0, 2000.0, []
    budget.report(radio_status(100), 0.0)
    for t in range(1, 31):
        sent = budget.rate(float(t))
        budget.sent(round(sent))
        used = max(0.0, used + sent - air)
        assert used < 2048, f"the radio's buffer overflowed at {t} s"
        budget.report(radio_status(round(100 - used * 100 / 2048)), float(t))
        levels.append(used)
    assert all(500 < level < 1200 for level in levels[-10:]), levels
    assert 1800 < budget.rate(30.0) < 2300, budget.rate(30.0)
    budget.report(radio_status(100), 31.0)
    budget.report(radio_status(100), 32.0)
    assert budget.rate(32.0) > 2300, "an idle radio: the budget climbs"
    budget.report(radio_status(100, remrssi=70, remnoise=45), 33.0)  # the far end hears us 12.5 dB over noise
    healthy = budget.rate(33.0)
    budget.report(radio_status(100, rssi=55, noise=40), 34.0)  # 7.5 dB: fading
    assert healthy > 1440.0 and budget.rate(34.0) == 1440.0
    budget.report(radio_status(100, rssi=45, noise=42), 35.0)  # 1.5 dB: the link is about to drop
    assert budget.rate(35.0) == 720.0
    assert budget.rate(38.5) == 2880.0, "a report older than 3 s no longer counts"
    assert RadioBudget(0.0).rate(1.0) == 0.0, "a network link is not paced"


def test_a_low_first_estimate_of_the_air_does_not_hold_the_budget_down() -> None:
    """The first sign of a backlog measures the air by what it carried, a lower bound (the
    buffer was empty for part of the interval). Reports that then land between the radio's
    transmit windows alternate between an empty buffer and a few hundred bytes, so no
    interval is backlogged throughout and that estimate was never measured again: the budget
    stayed at 550-1,150 B/s on a radio carrying 2,300 (on the emulated radio, the simulated
    vehicle's sat at 1,600-2,300 B/s with its frames queued). What left a buffer that ran dry
    is a lower bound too, and the estimate moves up to it."""
    from engine.endpoints.mavlink.budget import RadioBudget

    budget = RadioBudget(2880.0)
    budget.report(radio_status(100), 0.0)
    budget.sent(600)
    budget.report(radio_status(85), 1.0)  # 307 B in use: the air "carried 300 B/s"
    used, air, rates = 307.0, 2300.0, []
    for t in range(2, 14):
        sent = budget.rate(float(t))
        budget.sent(round(sent))
        used = max(0.0, used + sent - air)
        assert used < 2048, f"the radio's buffer overflowed at {t} s"
        at_report = used + (300 if t % 2 else 0)  # between the transmit windows: what the other side's window left
        budget.report(radio_status(round(100 - at_report * 100 / 2048)), float(t))
        rates.append(budget.rate(float(t)))
    assert min(rates[-4:]) > 2000, rates
