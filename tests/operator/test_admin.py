"""The admin endpoint against a real engine and RabbitMQ: metrics, health, status, taps, throttling."""

from __future__ import annotations

import asyncio
import json
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any, Iterator

import aio_pika
import pytest

from engine.common.processes import listening_port
from engine.endpoints.amqp.broker import LocalBroker
from tests.support.amqp_helpers import Collector, publish
from tests.support.repo import REPO
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for, wait_for_sync

ROUTES = """
routes:
  - name: counted
    source: {amqp: {exchange: admin-test, binding_key: "counted.#", queue: admin-counted}}
    mapping: "{agent_id: agent, type: 'weed_detection', points: detections[].{lat: lat, lon: lon, p: confidence}}"
    schema: weed_detection
    sink: {amqp: {exchange: admin-test, routing_key: "out.counted.{agent_id}"}}
  - name: tapped
    source: {amqp: {exchange: admin-test, binding_key: "tapped.#", queue: admin-tapped, prefetch: 64}}
    mapping: "{agent_id: agent, seq: seq, pad: pad}"
    schema: raw_json
    sink: {amqp: {exchange: admin-test, routing_key: "out.tapped"}}
  - name: throttled
    source: {amqp: {exchange: admin-test, binding_key: "throttled.#", queue: admin-throttled}}
    mapping: "{agent_id: agent, seq: seq}"
    schema: raw_json
    throttle: {max_rate: 2, per: agent_id}
    sink: {amqp: {exchange: admin-test, routing_key: "out.throttled.{agent_id}"}}
"""


def get(port: int, path: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as response:
            return response.status, response.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def metrics(port: int) -> dict[str, float]:
    """``name{labels}`` -> value of every rabbitros sample."""
    status, text = get(port, "/metrics")
    assert status == 200
    out = {}
    for line in text.splitlines():
        if line.startswith("rabbitros_"):
            key, value = line.rsplit(" ", 1)
            out[key] = float(value)
    return out


class Admin:
    def __init__(self, engine: EngineProcess, port: int, url: str) -> None:
        self.engine, self.port, self.url = engine, port, url

    def status(self) -> dict[str, Any]:
        code, text = get(self.port, "/status")
        assert code == 200
        return json.loads(text)


@pytest.fixture(scope="module")
def admin(amqp_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Admin]:
    work = tmp_path_factory.mktemp("admin")
    (work / "routes").mkdir()
    (work / "routes" / "admin.yaml").write_text(ROUTES)
    port = listening_port()
    asyncio.run(_output_queue(amqp_url, delete=False))  # the sinks publish mandatory: something reads what they send
    engine = EngineProcess(work / "routes", work / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                           "--admin", str(port))
    try:
        engine.wait_started()
        yield Admin(engine, port, amqp_url)
    finally:
        engine.stop()
        asyncio.run(_output_queue(amqp_url, delete=True))


async def _output_queue(url: str, delete: bool) -> None:
    """The queue the routes' output goes to (``out.#``), bounded; deleted after the module."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    exchange = await channel.declare_exchange("admin-test", aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue("admin-test-out", durable=False, arguments={"x-max-length": 10000})
    if delete:
        await queue.delete(if_unused=False, if_empty=False)
    else:
        await queue.bind(exchange, "out.#")
    await connection.close()


async def _publish(url: str, routing_key: str, bodies: list[bytes]) -> None:
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    await publish(channel, "admin-test", routing_key, bodies)
    await connection.close()


def test_metrics_count_known_traffic(admin: Admin):
    valid = [json.dumps({"agent": f"uav{i % 3}", "detections": [{"lat": 1, "lon": 2, "confidence": 0.5}]}).encode()
             for i in range(20)]
    not_json = [b"{not json", b"\xff\xfe"]
    schema_invalid = [json.dumps({"agent": "uav1", "detections": [{"lat": 1, "lon": 2, "confidence": 7}]}).encode()] * 3
    asyncio.run(_publish(admin.url, "counted.x", valid + not_json + schema_invalid))
    route = 'route="counted"'
    # received is counted when the route takes a batch, its outcome once settled: wait for the outcomes
    settled = ("delivered", "dead_lettered")
    wait_for_sync(lambda: sum(metrics(admin.port).get(f'rabbitros_messages_total{{outcome="{outcome}",{route}}}', 0)
                           for outcome in settled) == 25, 30, "25 messages settled")
    sample = metrics(admin.port)
    assert sample[f'rabbitros_messages_total{{outcome="received",{route}}}'] == 25
    assert sample[f'rabbitros_messages_total{{outcome="delivered",{route}}}'] == 20
    assert sample[f'rabbitros_messages_total{{outcome="dead_lettered",{route}}}'] == 5
    assert sample[f'rabbitros_messages_total{{outcome="redelivered",{route}}}'] == 0
    assert sample[f'rabbitros_messages_total{{outcome="conflated",{route}}}'] == 0
    assert sample[f'rabbitros_dead_letters_total{{{route},stage="decode"}}'] == 2
    assert sample[f'rabbitros_dead_letters_total{{{route},stage="schema"}}'] == 3
    assert sample[f'rabbitros_route_latency_seconds_count{{{route}}}'] == 20
    assert sample[f'rabbitros_route_latency_seconds_bucket{{le="+Inf",{route}}}'] == 20
    assert 0 < sample[f'rabbitros_route_latency_seconds_sum{{{route}}}'] < 20 * 5
    assert sample["rabbitros_config_generation"] == 1
    assert sample['rabbitros_reloads_total{result="succeeded"}'] == 0
    assert sample['rabbitros_reloads_total{result="rejected"}'] == 0
    assert sample['rabbitros_connection_up{connection="default-amqp",protocol="amqp"}'] == 1
    status = admin.status()["routes"]["counted"]
    assert status["messages"]["delivered"] == 20 and status["dead_letters"] == {"decode": 2, "schema": 3}
    assert "confidence" not in json.dumps(status["last_canonical"]) and status["last_canonical"]["agent_id"].startswith("uav")
    assert "schema" in status["last_error"] and status["state"] == "running"


def _open_tap(port: int, route: str, receive_buffer: int | None = None) -> socket.socket:
    sock = socket.socket()
    if receive_buffer:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
    sock.settimeout(30)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET /tap/{route} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    return sock


def _read_tap(sock: socket.socket, count: int, timeout: float) -> list[dict[str, Any]]:
    """Read ``count`` JSON lines from a raw chunked HTTP response; fails naming how many came
    if fewer than ``count`` did within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    buffer = b""
    while buffer.count(b"\n{") < count and time.monotonic() < deadline:
        sock.settimeout(max(0.1, deadline - time.monotonic()))
        try:
            chunk = sock.recv(65536)
        except socket.timeout:
            break
        if not chunk:
            break
        buffer += chunk
    lines = [json.loads(line) for line in buffer.split(b"\n") if line.startswith(b"{")]
    assert len(lines) >= count, f"the tap sent {len(lines)} of {count} lines within {timeout:g} s"
    return lines


def test_tap_gets_every_canonical_message(admin: Admin):
    sock = _open_tap(admin.port, "tapped")
    try:
        wait_for_sync(lambda: admin.status()["routes"]["tapped"]["taps"] == 1, 10, "the tap to attach")
        bodies = [json.dumps({"agent": "uav1", "seq": i}).encode() for i in range(300)]
        asyncio.run(_publish(admin.url, "tapped.x", bodies))
        lines = _read_tap(sock, 300, 30)
    finally:
        sock.close()
    assert len(lines) == 300
    assert sorted(line["canonical"]["seq"] for line in lines) == list(range(300))
    first = next(line for line in lines if line["canonical"]["seq"] == 0)
    assert first["route"] == "tapped" and first["generation"] == 1 and first["outcome"] == "delivered"
    assert first["source"] == {"agent": "uav1", "seq": 0} and first["error"] is None
    assert first["canonical"] == {"agent_id": "uav1", "seq": 0, "pad": None} and isinstance(first["ts"], float)
    assert get(admin.port, "/tap/nope")[0] == 404


def test_a_tap_client_that_never_reads_does_not_slow_the_route(admin: Admin):
    count = 3000

    async def run(stuck: bool) -> float:
        connection = await aio_pika.connect(admin.url)
        channel = await connection.channel()
        output = await Collector.bind(channel, "admin-test", "out.tapped")
        bodies = [json.dumps({"agent": "uav1", "seq": i, "pad": "x" * 4000}).encode() for i in range(count)]
        began = time.monotonic()
        await publish(channel, "admin-test", "tapped.x", bodies)
        received = await output.wait_for(count, timeout=120)
        elapsed = time.monotonic() - began
        await connection.close()
        assert len(received) == count, f"{len(received)} of {count} delivered (stuck tap: {stuck})"
        return elapsed

    baseline = asyncio.run(run(stuck=False))
    sock = _open_tap(admin.port, "tapped", receive_buffer=4096)
    try:
        wait_for_sync(lambda: admin.status()["routes"]["tapped"]["taps"] == 1, 10, "the stuck tap to attach")
        with_stuck_tap = asyncio.run(run(stuck=True))
        dropped = admin.status()["routes"]["tapped"]["tap_dropped"]
    finally:
        sock.close()
    print(f"{count} messages: {baseline:.2f} s without a tap, {with_stuck_tap:.2f} s with a stuck tap "
          f"(ratio {with_stuck_tap / baseline:.2f}), {dropped} tap lines dropped")
    assert dropped > 0, "the stuck client's buffer never filled: the test proved nothing"
    assert with_stuck_tap < baseline * 3 + 2, "a stuck tap slowed the route"


def test_throttle_keeps_the_latest_per_agent(admin: Admin):
    def latest_of_both(output: Collector) -> bool:
        return sum(json.loads(m.body)["seq"] == 39 for m in output.messages) == 2

    async def run() -> tuple[list[aio_pika.abc.AbstractIncomingMessage], float]:
        connection = await aio_pika.connect(admin.url)
        channel = await connection.channel()
        output = await Collector.bind(channel, "admin-test", "out.throttled.#")
        target = await channel.declare_exchange("admin-test", aio_pika.ExchangeType.TOPIC, durable=True)
        began = time.monotonic()
        for seq in range(40):  # 20 msg/s per agent for 2 s, against max_rate 2
            for agent in ("uav1", "uav2"):
                await target.publish(aio_pika.Message(json.dumps({"agent": agent, "seq": seq}).encode()), f"throttled.{agent}")
            await asyncio.sleep(0.05)  # pacing: 20 msg/s per agent
        await wait_for(lambda: latest_of_both(output), 10, "seq 39 of both agents (the last slot opens within 0.5 s)",
                       detail=lambda: sorted(json.loads(m.body)["seq"] for m in output.messages))
        elapsed = time.monotonic() - began
        await connection.close()
        return output.messages, elapsed

    messages, elapsed = asyncio.run(run())
    by_agent: dict[str, list[int]] = {}
    for message in messages:
        body = json.loads(message.body)
        by_agent.setdefault(body["agent_id"], []).append(body["seq"])
    assert set(by_agent) == {"uav1", "uav2"}
    for agent, seqs in by_agent.items():
        assert seqs == sorted(seqs), seqs
        assert seqs[0] == 0 and seqs[-1] == 39, f"{agent}: the first goes at once and the latest is kept: {seqs}"
        # 2 a second while the stream lasted (~2.5 s: 7; longer when a loaded machine slowed the publisher)
        assert 3 <= len(seqs) <= 2 * elapsed + 2, f"{agent}: {len(seqs)} sent in {elapsed:.1f} s at max_rate 2: {seqs}"
    counts = admin.status()["routes"]["throttled"]["messages"]
    assert counts["received"] == 80
    assert counts["delivered"] == len(messages)
    assert counts["conflated"] == 80 - len(messages)


def test_status_and_tap_commands(admin: Admin):
    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "engine", *args], capture_output=True, text=True,
                              timeout=60, cwd=REPO)

    table = cli("status", "--admin", str(admin.port))
    assert table.returncode == 0, table.stderr
    assert "counted" in table.stdout and "running" in table.stdout and "generation 1" in table.stdout
    raw = json.loads(cli("status", "--admin", f"127.0.0.1:{admin.port}", "--json").stdout)
    assert raw["generation"] == 1 and "tapped" in raw["routes"]
    assert json.loads(cli("status", "--status-file", str(admin.engine.status_file)).stdout)["generation"] == 1

    missing = cli("tap", "nope", "--admin", str(admin.port))
    assert missing.returncode == 1 and "unknown route 'nope'" in missing.stderr
    nobody = cli("tap", "tapped", "--admin", str(listening_port()))
    assert nobody.returncode == 1 and "cannot reach the engine's admin endpoint" in nobody.stderr, nobody.stderr


class TapCommand:
    """``rabbitros-engine tap`` as a child process; its stderr read by a thread, so a test
    can wait for a line with a deadline."""

    def __init__(self, port: int, route: str, *extra: str) -> None:
        self.process = subprocess.Popen(
            ["timeout", "-s", "KILL", "120", sys.executable, "-m", "engine", "tap", route, "--admin", str(port), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
        self.errors: queue.Queue[str] = queue.Queue()
        self.stderr: list[str] = []
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()

    def _read_stderr(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.stderr.append(line)
            self.errors.put(line)

    def wait_for(self, text: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.errors.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"the tap never printed {text!r}: {''.join(self.stderr)!r}") from None
            if text in line:
                return line

    def finish(self, timeout: float = 30) -> tuple[int, str, str]:
        try:
            code = self.process.wait(timeout)  # its output fits the pipe: lines of a few messages
        finally:
            self.process.kill()
        assert self.process.stdout is not None
        out = self.process.stdout.read()
        self._reader.join(10)  # stderr to its end (communicate() would race the reader for it)
        return code, out, "".join(self.stderr)


def test_tap_command_says_when_it_listens_and_misses_nothing_after(admin: Admin):
    """The tutorial's ``tap ... &`` then publish: messages published as soon as the tap says
    ``listening`` all reach it (no wait on the engine's status)."""
    tap = TapCommand(admin.port, "tapped", "--count", "3")
    listening = tap.wait_for("listening", 20)
    assert listening.startswith("tap tapped: listening on http://127.0.0.1:") and "for 3 messages" in listening
    asyncio.run(_publish(admin.url, "tapped.x", [json.dumps({"agent": "cli", "seq": i}).encode() for i in range(3)]))
    code, out, _ = tap.finish()
    assert code == 0
    assert [json.loads(line)["canonical"]["seq"] for line in out.splitlines()] == [0, 1, 2]


@pytest.mark.parametrize("how", ["stopped", "killed"])
def test_tap_command_fails_clearly_when_the_engine_goes_away(amqp_url: str, tmp_path: Path, how: str):
    """Stopped (SIGTERM: the engine closes the stream) or killed (-9: the connection drops),
    the tap exits 1 and says what happened instead of exiting 0 in silence."""
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ROUTES.split("  - name: throttled")[0].replace("admin-", "gone-"))
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--admin", str(port))
    try:
        engine.wait_started()
        tap = TapCommand(port, "tapped")
        tap.wait_for("listening", 20)
        if how == "killed":
            os.killpg(engine.process.pid, signal.SIGKILL)
        else:
            engine.stop()
        code, out, err = tap.finish()
    finally:
        engine.stop()
    assert code == 1 and out == "", err
    assert re.search(r"^tap tapped: (the engine went away|lost the engine at \S+) after 0 messages", err, re.M), err


@pytest.mark.soak
def test_healthz_follows_the_broker(tmp_path: Path):
    broker = LocalBroker(keep_dir=True)
    broker.start()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(
        f"connections:\n  farm-broker: {{amqp: '{broker.url}'}}\n" + ROUTES.split("  - name: tapped")[0])
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--admin", str(port))
    try:
        engine.wait_started()
        code, body = get(port, "/healthz")
        assert code == 200 and json.loads(body)["status"] == "ok", body
        broker.stop(timeout=30)

        def unhealthy() -> tuple[int, str] | None:
            answer = get(port, "/healthz")
            return answer if answer[0] == 503 else None

        code, body = wait_for_sync(unhealthy, 30, "/healthz to turn 503")
        document = json.loads(body)
        assert document["down"] == ["farm-broker"] and document["connections"]["farm-broker"]["up"] is False
        assert metrics(port)['rabbitros_connection_up{connection="farm-broker",protocol="amqp"}'] == 0
        broker.start()
        wait_for_sync(lambda: get(port, "/healthz")[0] == 200, 60, "/healthz to turn 200 again")
        assert metrics(port)['rabbitros_connection_up{connection="farm-broker",protocol="amqp"}'] == 1
    finally:
        engine.stop()
        broker.keep_dir = False
        broker.stop()


def test_status_shows_why_the_last_reload_was_rejected_and_the_log_says_when_it_cleared(amqp_url: str, tmp_path: Path):
    """``status`` names each problem of a rejected reload as ``file:line: message`` (not just
    "1 rejected"); a later reload that applies says in the log that the error is gone, and the
    status stops showing it."""
    routes = tmp_path / "routes"
    routes.mkdir()
    good = ROUTES.split("  - name: throttled")[0].replace("admin-", "rejected-")
    (routes / "r.yaml").write_text(good)
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--admin", str(port))

    def status_table() -> str:
        shown = subprocess.run([sys.executable, "-m", "engine", "status", "--admin", str(port)], capture_output=True,
                               text=True, timeout=60, cwd=REPO)
        assert shown.returncode == 0, shown.stderr
        return shown.stdout

    try:
        engine.wait_started()
        (routes / "r.yaml").write_text(good.replace("schema: weed_detection", "schema: weed_detektion"))
        wait_for_sync(lambda: (engine.status() or {}).get("reloads", {}).get("rejected") == 1, 30, "the reload to be rejected")
        table = status_table()
        assert "0 ok / 1 rejected" in table and "last reload rejected (generation 1 keeps running):" in table, table
        problem = next(line.strip() for line in table.splitlines() if "weed_detektion" in line)
        assert re.fullmatch(rf"{re.escape(str(routes / 'r.yaml'))}:\d+: route 'counted': unknown schema 'weed_detektion'.*", problem), problem
        assert "reload error cleared" not in engine.log()

        (routes / "r.yaml").write_text(good.replace("prefetch: 64", "prefetch: 32"))
        wait_for_sync(lambda: (engine.status() or {}).get("generation") == 2, 30, "the fixed files to be applied")
        cleared = wait_for_sync(lambda: [json.loads(line) for line in engine.log().splitlines()
                                      if '"reload error cleared"' in line], 10, "the log to say the error cleared")
        assert cleared[0]["by"] == "a reload applied" and "weed_detektion" in cleared[0]["was"][0]
        table = status_table()
        assert "1 ok / 1 rejected" in table and "last reload rejected" not in table, table
    finally:
        engine.stop()
