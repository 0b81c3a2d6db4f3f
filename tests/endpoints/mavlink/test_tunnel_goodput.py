"""The radio is not left idle between a route's batches (issue 22, tunnel goodput).

A JSON tunnel sink accepts a message only once the vehicle acknowledged it over the radio (a
TDM round and more). With one batch in flight the AMQP source handed the next batch only
after that, so the radio stood idle for a round trip after every batch; with small batches
(a prefetch of 8: batches of 4 messages, one bundle of 10 fragments) the way to the vehicle
carried 0.52 of what the radio's constants allow. The tunnel sink now lets four batches be in flight
(``Sink.batches_in_flight``), the source still acknowledging them in order.

The way to the vehicle alone is measured (first publish -> last message stored by the
simulated vehicle), against the payload the emulated radio's constants allow
(bench/sections.py ``link_payload_capacity``). Measured on a quiet machine: 0.74 with four
batches in flight, 0.52 with one (``TunnelSink.batches_in_flight = 1``: this test then
fails). The figures against the flood reference are bench/goodput.py's.
"""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import pytest

from bench.roundtrip_mavlink import Settings, run_experiment
from bench.sections import link_payload_capacity

COUNT, SIZE = 64, 250
FLOOR = 0.6
"""Of the constants' capacity (2,716 B/s): one batch in flight measured 0.52, four 0.74."""


@pytest.mark.alone  # goodput over the emulated radio is wall time
def test_small_batches_keep_the_radio_busy(tmp_path: Path, amqp_url: str) -> None:
    config = Settings(runs=1, count=COUNT, rate=500.0, sizes=(SIZE,), prefetch=8, seed=3,
                      exchange=f"goodput-{uuid.uuid4().hex[:8]}", out=tmp_path / "results")
    summary = asyncio.run(asyncio.wait_for(run_experiment(config, amqp_url), 120))

    batch = summary["batches"][0]
    assert batch["identical"] == COUNT, batch
    assert batch["forward_seconds"] is not None, "every message must reach the vehicle's store"
    forward = COUNT * SIZE / batch["forward_seconds"]
    print(f"forward {forward:.0f} B/s in {batch['forward_seconds']:.1f} s, round trip {batch['seconds']:.1f} s")
    capacity = link_payload_capacity()["payload_bytes_per_s"]
    assert forward >= FLOOR * capacity, (
        f"{forward:.0f} B/s to the vehicle is {forward / capacity:.2f} of the radio's {capacity:.0f} B/s: "
        "the radio idles between batches")
    for radio in summary["radio"].values():
        assert radio["serial_rx_dropped"] == 0, "a radio buffer overflowed"
    route = summary["engine_routes"]["gcs-to-uav"]
    assert (route["received"], route["delivered"], route["failed"]) == (COUNT + 1, COUNT + 1, 0)  # and the probe
