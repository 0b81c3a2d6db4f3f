"""The web console of ``run --workers 2``, served by the supervisor's admin, in a real browser.

Debian's chromium, headless, driven by selenium through the system chromedriver (nothing is
downloaded: tests/support/browser.py). A real RabbitMQ (tests/conftest.py); the engine as an
operator runs it: the supervisor and its two worker processes. One route consumes a queue, so
both workers compete for its messages. The supervisor's admin has a token and TLS, as on a
field machine; the browser sends the token as HTTP Basic. The page must show both workers (pid,
up, CPU, memory), the route's counts summed over both (each worker's own count read from the
supervisor's ``/status``), the dead letter one of them made, every agent on the map whichever
worker carried its position, and a live tap through the supervisor. With
``CONSOLE_SCREENSHOT=docs/console-workers.png`` the test saves its screenshot there."""

from __future__ import annotations

import asyncio
import base64
import json
import math
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import aio_pika
from selenium.webdriver.common.by import By

from engine.common.processes import listening_port
from tests.support.amqp_helpers import publish
from tests.support.browser import PAGE_SNAPSHOT, browser
from tests.support.engine_process import EngineProcess
from tests.support.repo import REPO
from tests.support.tls_helpers import make_pki
from tests.support.admin_http import fetch
from tests.support.waiting import wait_for_sync

TOKEN = "workers-console-token-0123456789abcdef"
ROUTES = """
routes:
  - name: positions
    source: {{amqp: {{exchange: {tag}, binding_key: "pos.#", queue: {tag}-positions}}}}
    mapping: "{{type: 'position', agent_id: agent, lat: lat, lon: lon}}"
    schema: position
    sink: {{amqp: {{exchange: {tag}, routing_key: "out.{{agent_id}}"}}}}
"""
AGENTS = 12
MESSAGES = 240
FIELD = (48.15, 11.58)


async def sink_queue(url: str, tag: str) -> None:
    """A queue bound to what the route sends (its sink publishes mandatory: the messages must
    be routed somewhere), left to fill: the test reads the engine's counters, not the messages."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    exchange = await channel.declare_exchange(tag, aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(f"{tag}-out", durable=False, auto_delete=False)
    await queue.bind(exchange, "out.#")
    await connection.close()


async def send(url: str, tag: str, bodies: list[dict[str, Any]]) -> None:
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    await publish(channel, tag, "pos.x", [json.dumps(body).encode() for body in bodies])
    await connection.close()


def test_the_supervisors_console_shows_both_workers_and_the_engine_as_a_whole(amqp_url: str, tmp_path: Path) -> None:
    tag = "wcon" + uuid.uuid4().hex[:8]
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "positions.yaml").write_text(ROUTES.format(tag=tag))
    token_file = tmp_path / "admin-token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    pki = make_pki(tmp_path / "pki")
    port = listening_port()
    base = f"https://127.0.0.1:{port}"
    bearer = f"Bearer {TOKEN}"
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                           "--workers", "2", "--admin", f"127.0.0.1:{port}", "--admin-token-file", str(token_file),
                           "--admin-tls-cert", str(pki.server_cert), "--admin-tls-key", str(pki.server_key))

    def status() -> dict[str, Any]:
        code, _, body = fetch(base + "/status", bearer)
        assert code == 200, body
        return dict(json.loads(body))

    def per_worker(document: dict[str, Any], counter: str) -> list[int]:
        return [((w.get("status") or {}).get("routes", {}).get("positions") or {}).get(counter, 0) for w in document["workers"]]

    driver = None
    try:
        engine.wait_started()
        asyncio.run(sink_queue(amqp_url, tag))
        # the console sits behind the supervisor admin's token like every other path
        for path in ("/", "/console.js", "/console/events", "/console/state"):
            assert fetch(base + path)[0] == 401, path
        code, _, page = fetch(base + "/", "Basic " + base64.b64encode(f"anyone:{TOKEN}".encode()).decode())
        assert code == 200 and 'id="workers-panel"' in page

        driver = browser(tmp_path / "chromium-profile")
        driver.get(base.replace("https://", f"https://console:{TOKEN}@") + "/")

        def seen() -> dict[str, Any]:
            return dict(driver.execute_script(PAGE_SNAPSHOT))

        pids = [w["pid"] for w in status()["workers"]]
        page_workers = wait_for_sync(lambda: len((view := seen())["workers"]) == 2 and view["live"] == "live" and view["workers"],
                                     30, "both workers in the page", lambda: (seen(), engine.log()[-1500:]))
        assert [int(w["pid"]) for w in page_workers] == pids and [w["state"] for w in page_workers] == ["up", "up"], page_workers
        assert all(float(w["rss"]) > 10 and w["cpu-s"] and w["routes"] == "positions" for w in page_workers), page_workers
        assert "2/2 workers up" in seen()["summary"]

        lat, lon = FIELD
        # the agents on a circle of some 100 m around the field, each moving a little with every message
        bodies = [{"agent": f"agent{seq % AGENTS}", "lat": lat + 0.0009 * math.cos(seq % AGENTS * math.tau / AGENTS) + seq * 1e-7,
                   "lon": lon + 0.00135 * math.sin(seq % AGENTS * math.tau / AGENTS), "seq": seq} for seq in range(MESSAGES)]
        asyncio.run(send(amqp_url, tag, [*bodies, {"agent": "broken", "lat": 500.0, "lon": lon}]))

        def all_carried() -> dict[str, Any] | None:
            document = status()
            carried = sum(per_worker(document, "delivered")) == MESSAGES and sum(per_worker(document, "received")) == MESSAGES + 1
            return document if carried else None

        settled = wait_for_sync(all_carried, 60, "every message carried", lambda: per_worker(status(), "received"))
        received = per_worker(settled, "received")
        assert all(count > 0 for count in received), f"one worker carried everything: {received}"

        def row() -> dict[str, str]:
            return dict(seen()["routes"].get("positions") or {})

        wait_for_sync(lambda: row().get("received") == str(MESSAGES + 1), 20, "the route's counts summed from both workers", row)
        assert row()["delivered"] == str(MESSAGES) and row()["dead-lettered"] == "1" and row()["workers"] == "0, 1", row()
        dead = wait_for_sync(lambda: seen()["dead"], 10, "the dead letter in the console", seen)
        assert [(d["route"], d["stage"]) for d in dead] == [("positions", "schema")], dead
        agents = wait_for_sync(lambda: len(view := seen()["agents"]) == AGENTS and view, 20, "every agent on the map",
                               lambda: seen()["agents"])
        assert sorted(agents) == sorted(f"agent{n}" for n in range(AGENTS))
        # each agent's latest position over the workers: what each worker's own console document says
        fleets = [json.loads(fetch(f"http://127.0.0.1:{w['admin_port']}/console/state", bearer)[2])["fleet"] for w in status()["workers"]]
        latest: dict[str, tuple[float, int]] = {}
        for index, fleet in enumerate(fleets):
            for agent in fleet:
                if agent["at"] > latest.get(agent["agent_id"], (0.0, -1))[0]:
                    latest[agent["agent_id"]] = (agent["at"], index)
        merged = json.loads(fetch(base + "/console/state", bearer)[2])["fleet"]
        assert {a["agent_id"]: (a["at"], a["worker"]) for a in merged} == latest

        # a live tap through the supervisor: both workers' taps attached, lines from either
        driver.find_element(By.ID, "tap-route").send_keys("positions")
        driver.find_element(By.ID, "tap-toggle").click()
        wait_for_sync(lambda: status()["routes"]["positions"]["taps"] == 2, 15, "the tap attached on both workers")
        asyncio.run(send(amqp_url, tag, bodies[:20]))
        lines = wait_for_sync(lambda: len(tapped := seen()["tap"]) == 20 and tapped, 20, "the tapped messages", seen)
        assert all("delivered" in line for line in lines), lines
        shot = tmp_path / "console-workers.png"
        assert driver.save_screenshot(str(shot))
        if os.environ.get("CONSOLE_SCREENSHOT"):  # docs/console-workers.png is made this way (docs/operations.md)
            shutil.copyfile(shot, REPO / os.environ["CONSOLE_SCREENSHOT"])
        errors = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
        assert not errors, errors  # no script error, nothing the page's content security policy refused
    finally:
        if driver is not None:
            driver.quit()
        assert engine.stop(60) == 0, engine.log()
