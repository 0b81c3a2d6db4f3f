"""MQTT over TLS (issue 21): mqtts:// with the same ``tls`` options as AMQP (engine/common/tls.py),
against a private mosquitto whose TLS listener requires a client certificate."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiomqtt

from engine.common.processes import listening_port
from engine.endpoints.mqtt.broker import LocalMosquitto
from tests.support.engine_process import EngineProcess
from tests.support.tls_helpers import make_pki
from tests.support.waiting import wait_for


def test_mqtts_with_a_client_certificate_carries_and_names_failed_checks(tmp_path: Path):
    pki = make_pki(tmp_path / "pki")
    tls_port = listening_port()
    broker = LocalMosquitto(tmp_path / "mosquitto", extra=[
        f"listener {tls_port} 127.0.0.1", f"cafile {pki.ca}", f"certfile {pki.server_cert}", f"keyfile {pki.server_key}",
        "require_certificate true"])
    routes = tmp_path / "routes"
    routes.mkdir()
    good = f"{{ca_file: {pki.ca}, cert_file: {pki.client_cert}, key_file: {pki.client_key}}}"
    (routes / "r.yaml").write_text(
        "connections:\n"
        f"  secure: {{mqtt: {{url: \"mqtts://localhost:{tls_port}\", tls: {good}}}}}\n"
        f"  bad_ca: {{mqtt: {{url: \"mqtts://localhost:{tls_port}\", tls: {{ca_file: {pki.other_ca}, cert_file: {pki.client_cert}, key_file: {pki.client_key}}}}}}}\n"
        f"  no_cert: {{mqtt: {{url: \"mqtts://localhost:{tls_port}\", tls: {{ca_file: {pki.ca}}}}}}}\n"
        "routes:\n"
        "  - name: relay\n    source: {mqtt: {connection: secure, topic: tls/in}}\n    schema: raw_json\n"
        "    sink: {mqtt: {connection: secure, topic: tls/out}}\n"
        "  - name: a\n    source: {mqtt: {connection: bad_ca, topic: tls/a}}\n    schema: raw_json\n"
        "    sink: {mqtt: {connection: bad_ca, topic: tls/a-out}}\n"
        "  - name: c\n    source: {mqtt: {connection: no_cert, topic: tls/c}}\n    schema: raw_json\n"
        "    sink: {mqtt: {connection: no_cert, topic: tls/c-out}}\n")
    expected = {"bad_ca": "unknown CA: the broker's certificate is not signed by a CA in tls.ca_file",
                "no_cert": "no client certificate: the broker requires one"}

    async def scenario() -> list[dict[str, object]]:
        got: list[dict[str, object]] = []
        async with aiomqtt.Client("127.0.0.1", broker.port) as client:  # the test's client: the plain listener
            await client.subscribe("tls/out", qos=1)

            async def carried() -> bool:
                await client.publish("tls/in", json.dumps({"n": 1}), qos=1)
                try:
                    async with asyncio.timeout(1.0):
                        async for message in client.messages:
                            got.append(json.loads(bytes(message.payload)))
                            break
                except TimeoutError:
                    pass
                return bool(got)

            await wait_for(carried, 30, "a message through the mqtts route", lambda: engine.log()[-3000:])
        # a refused attempt ends in paho's connect timeout
        await wait_for(named, 45, "both TLS failures named in the status", lambda: (engine.status() or {}).get("connections"))
        return got

    try:
        broker.start()
        engine = EngineProcess(routes, tmp_path / "status.json", {})

        def named() -> dict[str, str] | None:
            connections = (engine.status() or {}).get("connections", {})
            found = {name: str(connections.get(name, {}).get("last_error")) for name in expected}
            return found if all(expected[name] in found[name] for name in expected) else None

        got, status = engine.run(scenario)
        found = {name: str(status["connections"][name]["last_error"]) for name in expected}
    finally:
        broker.stop()
    assert got == [{"n": 1}], engine.log_file.read_text()[-3000:]
    assert status["connections"]["secure"]["healthy"], status["connections"]
    assert all(expected[name] in found[name] for name in expected), found
    assert not status["connections"]["bad_ca"]["healthy"] and not status["connections"]["no_cert"]["healthy"]
    print(f"\nmqtts: carried; failures named: {found}")
