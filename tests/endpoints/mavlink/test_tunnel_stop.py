"""An engine stops on time while its JSON tunnel has batches in flight to a vehicle that never
answers (issue 22's batches in flight, found by the radio latency bench: a stop hung for
minutes after its drain timeout).

The AMQP source hands the tunnel several batches at once (``Sink.batches_in_flight``). When
the engine's drain timeout and grace are over it cancels the source; the batches still in
the tunnel must be given up with it (unsettled, so the broker keeps them for the next run),
not awaited until a vehicle that stays silent acknowledges them.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from pathlib import Path

import aio_pika
from pymavlink.dialects.v20 import common as mavlink2

from engine.running.runtime import Engine
from engine.running.shutdown import STOP_GRACE
from tests.support.amqp_helpers import message_count
from tests.support.repo import REPO
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

DRAIN_TIMEOUT = 1.0


class SilentVehicle(threading.Thread):
    """Heartbeats to the engine's udpin port (so the link has a peer and the sink is ready),
    and never an answer to anything it receives."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.stop = threading.Event()
        self.received = 0

    def run(self) -> None:
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(0.2)
            while not self.stop.is_set():
                sock.sendto(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav), ("127.0.0.1", self.port))
                try:
                    while True:
                        sock.recvfrom(4096)
                        self.received += 1
                except OSError:
                    pass


def test_a_stop_with_tunnel_batches_in_flight_to_a_silent_vehicle_ends_on_time(tmp_path: Path, amqp_url: str) -> None:
    port = free_udp_port()
    queue = f"tunnel-stop-{port}"
    (tmp_path / "tunnel.yaml").write_text(f"""\
connections:
  gcs: {{amqp: "{amqp_url}"}}
  radio: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 1}}
routes:
  - name: to-vehicle
    source: {{amqp: {{connection: gcs, queue: {queue}, prefetch: 8}}}}
    schema: raw_json
    sink: {{mavlink: {{connection: radio, json_tunnel: true, target_system: 1, target_component: 191}}}}
""")
    vehicle = SilentVehicle(port)
    vehicle.start()

    async def scenario() -> tuple[float, int, int]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            for index in range(40):
                await channel.default_exchange.publish(aio_pika.Message(b'{"n": %d}' % index), routing_key=queue)
            await wait_for(lambda: vehicle.received >= 3, 30, "the tunnel busy (3 frames at the vehicle)")
            began = time.monotonic()
            await asyncio.wait_for(engine.stop(drain_timeout=DRAIN_TIMEOUT), 60)
            took = time.monotonic() - began
            kept = message_count(await channel.declare_queue(queue, passive=True))
            return took, kept, vehicle.received
        finally:
            await connection.close()

    try:
        took, kept, received = asyncio.run(scenario())
    finally:
        vehicle.stop.set()
        vehicle.join(5)
    print(f"\nstopped in {took:.2f} s with the tunnel busy ({received} frames to the silent vehicle); {kept} of 40 kept in the queue")
    assert took < DRAIN_TIMEOUT + STOP_GRACE + 5, f"the stop took {took:.1f} s"
    assert kept == 40, f"{kept} of 40 messages are back in the queue: an unacknowledged one was lost or acked"
