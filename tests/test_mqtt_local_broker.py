"""``run --local-broker`` asks each protocol for its private broker: routes with an MQTT
connection that names no url get a private mosquitto (its own port and data directory), which
stops with the engine; the AMQP node starts as always."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import aiomqtt

REPO = Path(__file__).resolve().parents[1]
ROUTES = """
routes:
  - {name: relay, source: {mqtt: {topic: "farm/+/weather", qos: 1}}, schema: raw_json, sink: {mqtt: {topic: farm/weather, qos: 1}}}
"""


def test_run_local_broker_starts_a_private_mosquitto_for_an_mqtt_connection_without_url(tmp_path: Path):
    url_file, status_file, routes = tmp_path / "broker-url", tmp_path / "status.json", tmp_path / "routes"
    routes.mkdir()
    (routes / "field.yaml").write_text(ROUTES)
    env = {k: v for k, v in os.environ.items() if k not in ("RABBITROS_MQTT_URL", "RABBITROS_AMQP_URL")}
    process = subprocess.Popen(
        ["timeout", "-s", "KILL", "180", sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", "schemas",
         "--local-broker", "--broker-url-file", str(url_file), "--status-file", str(status_file), "--log-format", "json"],
        cwd=REPO, stderr=subprocess.PIPE, text=True, start_new_session=True, env={**env, "PYTHONPATH": str(REPO)},
    )
    try:
        deadline = time.monotonic() + 120
        while not status_file.exists() and time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.2)
        assert status_file.exists(), "engine did not start"
        urls = url_file.read_text().split()
        mqtt_url = next(url for url in urls if url.startswith("mqtt://"))
        host, port = urlsplit(mqtt_url).hostname, urlsplit(mqtt_url).port
        assert port != 1883  # its own port, not a system broker's

        async def roundtrip() -> bytes:
            async with aiomqtt.Client(host, port, identifier="test-reader") as reader:
                await reader.subscribe("farm/weather", qos=1)
                async with aiomqtt.Client(host, port, identifier="test-writer") as writer:
                    async def publish_until_answered() -> None:
                        while True:  # the route subscribes once its connection is up
                            await writer.publish("farm/station1/weather", b'{"t": 21.5}', qos=1)
                            await asyncio.sleep(0.5)
                    publishing = asyncio.create_task(publish_until_answered())
                    try:
                        async with asyncio.timeout(30):
                            async for message in reader.messages:
                                return bytes(message.payload)
                    finally:
                        publishing.cancel()
            raise AssertionError("no message")

        assert json.loads(asyncio.run(roundtrip())) == {"t": 21.5}
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
        started = next(json.loads(line) for line in stderr.splitlines() if line.startswith("{") and "local broker started" in line)
        assert any("mosquitto" in node for node in started["nodes"]), started
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    with socket.socket() as probe:
        assert probe.connect_ex((host, port)) != 0, "the private mosquitto outlived the engine"
