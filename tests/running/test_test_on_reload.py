"""``run --test-on-reload`` (issue 32), against a real RabbitMQ node: every load and reload runs
the directory's route tests first. A reload whose tests fail is refused, as a syntax error is:
the old generation keeps carrying messages, and the status and the log name the failing case;
once the tests pass the generation goes live. An engine whose tests fail at start does not start."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

import aio_pika

from tests.running.test_reload_edits import write_atomically
from tests.support.amqp_helpers import Collector, publish
from tests.support.engine_process import EngineProcess
from tests.support.repo import REPO
from tests.support.waiting import wait_for

ROUTE = """routes:
  - name: scale
    source: {{amqp: {{exchange: {inbox}, binding_key: "s.#", queue: {queue}}}}}
    schema: raw_json
    mapping: "{{value: mul(value, `{factor}`)}}"
    sink: {{amqp: {{exchange: {outbox}, routing_key: scaled}}}}
"""
TESTS = """tests:
  - name: doubles
    route: scale
    input: {{value: 21}}
    expect: {{value: {expected}}}
"""


def names() -> dict[str, str]:
    tag = uuid.uuid4().hex[:8]
    return {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}


def test_a_reload_whose_route_tests_fail_is_refused_and_the_old_generation_keeps_carrying(amqp_url: str, tmp_path: Path):
    n = names()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "scale.yaml").write_text(ROUTE.format(factor=2, **n))
    (routes / "scale.test.yaml").write_text(TESTS.format(expected=42))
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--test-on-reload")

    def status() -> dict[str, Any]:
        return engine.status() or {}

    async def scaled(channel: Any, out: Collector, count: int) -> float:
        await publish(channel, n["inbox"], "s.x", [b'{"value": 5}'])
        messages = await out.wait_for(count)
        assert len(messages) == count, f"the route stopped carrying: {engine.log()}"
        return json.loads(messages[-1].body)["value"]

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            assert await scaled(channel, out, 1) == 10

            # valid YAML, a clean check, but the route no longer does what its test says
            write_atomically(routes / "scale.yaml", ROUTE.format(factor=3, **n))
            await wait_for(lambda: status().get("reloads", {}).get("rejected") == 1, 20, f"not refused: {engine.log()}")
            test_file = routes / "scale.test.yaml"
            assert status()["reloads"]["last_error"] == [
                f"{test_file}:2: route test 'scale: doubles' fails: canonical message differs "
                "(--test-on-reload refuses a generation whose route tests fail)"], status()
            # the log line is written by the engine's reload, the status file by another task: either may come first
            await wait_for(lambda: "route test 'scale: doubles' fails" in engine.log(), 10, "the log to name the failing case")
            assert status()["generation"] == 1
            assert await scaled(channel, out, 2) == 10, "the refused generation runs"

            # the test brought in line: the same route file goes live
            write_atomically(test_file, TESTS.format(expected=63))
            await wait_for(lambda: status().get("generation") == 2, 20, f"not applied: {engine.log()}")
            assert status()["reloads"]["last_error"] == [] and status()["reloads"]["rejected"] == 1
            assert await scaled(channel, out, 3) == 15
        finally:
            await connection.close()

    _, final = engine.run(scenario)
    assert final["routes"]["scale"]["generation"] == 2


def test_an_engine_whose_route_tests_fail_does_not_start(tmp_path: Path):
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "scale.yaml").write_text(ROUTE.format(factor=3, **names()))
    (routes / "scale.test.yaml").write_text(TESTS.format(expected=42))
    run = [sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", str(REPO / "schemas"), "--no-watch"]
    result = subprocess.run([*run, "--test-on-reload"], cwd=REPO, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "RABBITROS_AMQP_URL": "amqp://guest:guest@127.0.0.1:1/"})
    assert result.returncode == 2, result.stderr
    assert f"{routes}/scale.test.yaml:2: route test 'scale: doubles' fails: canonical message differs" in result.stderr
