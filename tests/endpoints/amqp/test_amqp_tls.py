"""AMQP over TLS (issue 21) against a private RabbitMQ node with a TLS listener that asks for
and insists on a client certificate (``verify_peer``, ``fail_if_no_peer_cert``), with
certificates made by ``openssl`` for the test (tests/support/tls_helpers.py)."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Iterator

import aio_pika
import aio_pika.abc
import pytest

from engine.common.processes import listening_port
from engine.endpoints.amqp.broker import BrokerTls, LocalBroker
from tests.support.amqp_helpers import Collector
from tests.support.engine_process import EngineProcess
from tests.support.tls_helpers import Pki, make_pki, renew_client
from tests.support.waiting import wait_for, wait_for_sync

CERT_USER = "guest"
"""The client certificate's common name: EXTERNAL logs in as the user of that name, and the
node's guest user (loopback only) spares two rabbitmqctl calls (several seconds each)."""


@pytest.fixture(scope="module")
def tls_broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LocalBroker, Pki]]:
    pki = make_pki(tmp_path_factory.mktemp("pki"), client_name=CERT_USER)
    broker = LocalBroker(tls=BrokerTls(pki.ca, pki.server_cert, pki.server_key, external_auth=True))
    try:
        broker.start()
        yield broker, pki
    finally:
        broker.stop()


def tls_block(ca: Path, cert: Path | None = None, key: Path | None = None, hostname: str | None = None) -> str:
    parts = [f"ca_file: {ca}"]
    if cert is not None:
        parts += [f"cert_file: {cert}", f"key_file: {key}"]
    if hostname is not None:
        parts.append(f"server_hostname: {hostname}")
    return "{" + ", ".join(parts) + "}"


def route(name: str, connection: str) -> str:
    return (f"  - name: {name}\n    source: {{amqp: {{connection: {connection}, exchange: tls-in, binding_key: {name}, queue: tls-{name}}}}}\n"
            f"    schema: raw_json\n    sink: {{amqp: {{connection: {connection}, exchange: tls-out, routing_key: {name}}}}}\n")


def test_right_ca_and_client_certificate_carry_messages(tls_broker: tuple[LocalBroker, Pki], tmp_path: Path):
    """Password login over TLS with a client certificate, and certificate login (EXTERNAL)."""
    broker, pki = tls_broker
    port = broker.tls_port
    client_cert, client_key = tmp_path / "client.pem", tmp_path / "client.key"
    client_cert.write_bytes(pki.client_cert.read_bytes())
    client_key.write_bytes(pki.client_key.read_bytes())
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(
        "connections:\n"
        f"  secure: {{amqp: {{url: \"amqps://guest:guest@localhost:{port}/\", tls: {tls_block(pki.ca, client_cert, client_key)}}}}}\n"
        # a user and password PLAIN would refuse: only the certificate (EXTERNAL) can log this one in
        f"  by_cert: {{amqp: {{url: \"amqps://nobody:wrong@localhost:{port}/\", auth: external, tls: {tls_block(pki.ca, pki.client_cert, pki.client_key)}}}}}\n"
        "dead_letters: {connection: secure}\n"
        "routes:\n" + route("pw", "secure") + route("cert", "by_cert"))
    engine = EngineProcess(routes, tmp_path / "status.json", {})
    figures: dict[str, float] = {}

    async def scenario() -> dict[str, list[bytes]]:
        connection = await aio_pika.connect(broker.url)  # the test's own client: the node's plain port
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, "tls-out")
            inbox = await channel.declare_exchange("tls-in", aio_pika.ExchangeType.TOPIC, durable=True)
            got: dict[str, list[bytes]] = {"pw": [], "cert": []}

            def collected() -> dict[str, list[bytes]]:
                for key in got:
                    got[key] = [m.body for m in out.messages if m.routing_key == key]
                return got

            for key in ("pw", "cert"):
                await inbox.publish(aio_pika.Message(json.dumps({"via": key}).encode()), key)
            await wait_for(lambda: collected()["pw"] and got["cert"], 30, "a message through each connection (password, certificate)",
                           lambda: got)

            # the client certificate renewed in place: a reload reopens the connection with it
            before = (engine.status() or {}).get("reloads", {}).get("succeeded", 0)
            began = time.monotonic()
            await asyncio.to_thread(renew_client, pki, client_cert, client_key, CERT_USER)
            await wait_for(lambda: (engine.status() or {}).get("reloads", {}).get("succeeded", 0) > before, 30,
                           "the reload after the client certificate's renewal", lambda: (engine.status() or {}).get("reloads"))
            figures["renewal_reload_s"] = time.monotonic() - began
            await inbox.publish(aio_pika.Message(b'{"via": "renewed"}'), "pw")
            await wait_for(lambda: len(collected()["pw"]) >= 2, 30, "a message through the renewed connection", lambda: got)
            return collected()
        finally:
            await connection.close()

    began = time.monotonic()
    got, status = engine.run(scenario)
    assert [json.loads(b) for b in got["pw"]] == [{"via": "pw"}, {"via": "renewed"}] and [json.loads(b) for b in got["cert"]] == [{"via": "cert"}], (got, engine.log_file.read_text()[-3000:])
    assert status["connections"]["secure"]["healthy"] and status["connections"]["by_cert"]["healthy"]
    assert status["reloads"]["succeeded"] >= 1, status["reloads"]
    log = engine.log_file.read_text()
    assert log.count("\"msg\": \"routes applied\"") >= 2, log[-2000:]  # the start, and the reload of the renewal
    print(f"\nengine over TLS: started, 3 messages carried (one after a client certificate renewal, reloaded "
          f"{figures['renewal_reload_s']:.1f}s after the write) and stopped in {time.monotonic() - began:.1f}s")


def test_each_failed_check_is_named_and_a_renewed_ca_file_reconnects(tls_broker: tuple[LocalBroker, Pki], tmp_path: Path):
    """Wrong CA, wrong host name, no client certificate: each connection stays down (never
    plain TCP), its error in the status, /healthz and the log names the check. Then the
    wrong CA file is replaced by the right one: the connection comes up, no restart."""
    broker, pki = tls_broker
    port = broker.tls_port
    ca_file = tmp_path / "ca.pem"
    ca_file.write_bytes(pki.other_ca.read_bytes())
    routes = tmp_path / "routes"
    routes.mkdir()
    url = f"amqps://guest:guest@localhost:{port}/"
    (routes / "r.yaml").write_text(
        "connections:\n"
        f"  bad_ca: {{amqp: {{url: \"{url}\", tls: {tls_block(ca_file, pki.client_cert, pki.client_key)}}}}}\n"
        f"  bad_host: {{amqp: {{url: \"{url}\", tls: {tls_block(pki.ca, pki.client_cert, pki.client_key, 'gcs.example')}}}}}\n"
        f"  no_cert: {{amqp: {{url: \"{url}\", tls: {tls_block(pki.ca)}}}}}\n"
        "dead_letters: {connection: bad_ca}\n"
        "routes:\n" + route("a", "bad_ca") + route("b", "bad_host") + route("c", "no_cert"))
    admin = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--admin", str(admin))
    expected = {
        "bad_ca": "unknown CA: the broker's certificate is not signed by a CA in tls.ca_file",
        "bad_host": "hostname mismatch: the broker's certificate is not valid for gcs.example",
        "no_cert": "no client certificate: the broker requires one",
    }
    started = time.monotonic()
    try:
        def errors() -> dict[str, str] | None:
            connections = (engine.status() or {}).get("connections", {})
            found = {name: str(connections.get(name, {}).get("last_error")) for name in expected}
            return found if all(expected[name] in found[name] for name in expected) else None

        found = wait_for_sync(errors, 60, f"the three TLS failures named in the status: {engine.log()}")
        assert all(not engine.current_status()["connections"][name]["healthy"] for name in expected)
        named_s = time.monotonic() - started
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"http://127.0.0.1:{admin}/healthz", timeout=10)
        health = json.loads(refused.value.read())
        assert refused.value.code == 503 and sorted(health["down"]) == sorted(expected), health
        for name, meaning in expected.items():
            assert meaning in str(health["connections"][name]["last_error"]), health
        # the log is written by the logging thread: a line may come a moment after the status named the error
        wait_for_sync(lambda: all(meaning in engine.log_file.read_text() for meaning in expected.values()), 30,
                      "the three TLS failures named in the log", lambda: engine.log_file.read_text()[-3000:])

        began = time.monotonic()
        ca_file.write_bytes(pki.ca.read_bytes())  # the renewed CA bundle
        wait_for_sync(lambda: (engine.status() or {}).get("connections", {}).get("bad_ca", {}).get("healthy"), 60,
                 f"bad_ca to come up after its CA file was replaced: {engine.log()}")
        renewed_s = time.monotonic() - began
        assert engine.process.poll() is None
    finally:
        engine.stop()
    print(f"\nTLS failures named in the status {named_s:.1f}s after the engine started: {found}; CA file replaced -> connected in {renewed_s:.1f}s without restart")
