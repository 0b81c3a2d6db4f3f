"""The web console (``GET /`` on the admin port) in a real browser against a real engine.

Debian's chromium, headless, driven by selenium through the system chromedriver (nothing is
downloaded: the driver's and the browser's paths are given, so selenium-manager is never run).
The engine runs three routes with real brokers: the UAV's positions from MQTT (a private
mosquitto), the robot's from AMQP and weed detections from AMQP, one of which fails its schema
and is dead-lettered; the canonical messages go to MQTT. The admin has a token and TLS, as on a field machine: the browser opens
``https://console:TOKEN@127.0.0.1:PORT/`` and sends the token as HTTP Basic from then on, to the
event stream and the tap too. The page must list every route, show a counter moving, the dead
letter with its stage and reason, the two agents on the map, and the tapped messages. With
``CONSOLE_SCREENSHOT=docs/console.png`` the test saves its screenshot there (the one in the docs).
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import shutil
from pathlib import Path
from typing import Any, Iterator

import aio_pika
import pytest
from selenium.webdriver.common.by import By

from engine.common.processes import listening_port
from engine.endpoints.mqtt.broker import LocalMosquitto
from tests.endpoints.mqtt.test_mqtt import publish as mqtt_publish
from tests.support.amqp_helpers import publish as amqp_publish
from tests.support.browser import PAGE_SNAPSHOT, browser
from tests.support.engine_process import EngineProcess
from tests.support.repo import REPO
from tests.support.tls_helpers import make_pki
from tests.support.admin_http import fetch
from tests.support.waiting import wait_for_sync

TOKEN = "console-test-token-0123456789abcdef"
ROUTES = """
connections:
  field: {mqtt: {url: "${CONSOLE_MQTT_URL}"}}
routes:
  - name: uav-position
    source: {mqtt: {topic: "fleet/+/position", qos: 1}}
    mapping: "{type: 'position', agent_id: agent, lat: lat, lon: lon, alt_rel: alt}"
    schema: position
    sink: {mqtt: {topic: "canonical/{agent_id}/position"}}
  - name: robot-position
    source: {amqp: {exchange: console-test, binding_key: "robot.position", queue: console-robot}}
    mapping: "{type: 'position', agent_id: agent, lat: lat, lon: lon}"
    schema: position
    sink: {mqtt: {topic: "canonical/{agent_id}/position"}}
  - name: weeds
    source: {amqp: {exchange: console-test, binding_key: "weeds", queue: console-weeds}}
    mapping: "{agent_id: agent, type: 'weed_detection', points: detections[].{lat: lat, lon: lon, p: confidence}}"
    schema: weed_detection
    sink: {mqtt: {topic: "canonical/{agent_id}/weeds"}}
"""
FIELD = (48.1500, 11.5800)
"""A field near Munich: the UAV and the robot are about 180 m apart."""


async def amqp_send(url: str, routing_key: str, bodies: list[dict[str, Any]]) -> None:
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    await amqp_publish(channel, "console-test", routing_key, [json.dumps(body).encode() for body in bodies])
    await connection.close()


@pytest.fixture
def console(amqp_url: str, mosquitto: LocalMosquitto, tmp_path: Path) -> Iterator[tuple[EngineProcess, str]]:
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "console.yaml").write_text(ROUTES)
    token_file = tmp_path / "admin-token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    pki = make_pki(tmp_path / "pki")
    port = listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json",
                           {"RABBITROS_AMQP_URL": amqp_url, "CONSOLE_MQTT_URL": mosquitto.url},
                           "--admin", f"127.0.0.1:{port}", "--admin-token-file", str(token_file),
                           "--admin-tls-cert", str(pki.server_cert), "--admin-tls-key", str(pki.server_key))
    try:
        engine.wait_started()
        yield engine, f"https://127.0.0.1:{port}"
    finally:
        engine.stop()


def test_the_console_shows_routes_counters_dead_letters_and_the_fleet(console: tuple[EngineProcess, str], amqp_url: str,
                                                                      mosquitto: LocalMosquitto, tmp_path: Path):
    engine, base = console
    # the token applies to the console as to every admin path; a browser may send it as Basic
    for path in ("/", "/console.js", "/console/events"):
        status, headers, _ = fetch(base + path)
        assert status == 401 and 'Basic realm="rabbitros"' in headers["WWW-Authenticate"], (path, status, headers)
    wrong = "Basic " + base64.b64encode(b"console:not-the-token").decode()
    assert fetch(base + "/", wrong)[0] == 401
    status, headers, page = fetch(base + "/", "Basic " + base64.b64encode(f"anyone:{TOKEN}".encode()).decode())
    assert status == 200 and "<svg id=\"map\"" in page and headers["Content-Type"].startswith("text/html")

    driver = browser(tmp_path / "chromium-profile")
    try:
        driver.get(base.replace("https://", f"https://console:{TOKEN}@") + "/")

        def seen() -> dict[str, Any]:
            return dict(driver.execute_script(PAGE_SNAPSHOT))

        def cell(route: str, column: str) -> str:
            return str(seen()["routes"].get(route, {}).get(column))

        wait_for_sync(lambda: list(seen()["routes"]) == ["robot-position", "uav-position", "weeds"], 30,
                      "the console to list every route", lambda: (seen(), engine.log()[-1500:]))
        assert cell("weeds", "received") == "0" and cell("weeds", "state") == "running"
        assert seen()["workers"] == [] and "workers" not in seen()["summary"]  # one engine: no workers table
        wait_for_sync(lambda: seen()["live"] == "live", 10, "the event stream", seen)

        # a live tap of the weeds route, opened before anything is sent
        driver.find_element(By.ID, "tap-route").send_keys("weeds")
        driver.find_element(By.ID, "tap-toggle").click()
        bearer = f"Bearer {TOKEN}"
        wait_for_sync(lambda: json.loads(fetch(base + "/status", bearer)[2] or "{}")["routes"]["weeds"]["taps"] == 1, 10,
                      "the tap to attach")

        lat, lon = FIELD
        good = [{"agent": "robot1", "detections": [{"lat": lat, "lon": lon, "confidence": 0.9}]}] * 3
        bad = {"agent": "robot1", "detections": [{"lat": lat, "lon": lon, "confidence": 7}]}
        asyncio.run(amqp_send(amqp_url, "weeds", [*good, bad]))
        asyncio.run(amqp_send(amqp_url, "robot.position", [{"agent": "robot1", "lat": lat + 0.0010, "lon": lon + 0.0015}]))
        asyncio.run(mqtt_publish(mosquitto, [("fleet/uav1/position", {"agent": "uav1", "lat": lat - 0.0005, "lon": lon - 0.0005,
                                                                       "alt": 30.0})]))

        wait_for_sync(lambda: (cell("weeds", "received"), cell("weeds", "delivered"), cell("weeds", "dead-lettered")) == ("4", "3", "1"),
                      30, "the weeds route's counters to move", lambda: seen()["routes"])
        assert "schema" in cell("weeds", "error")
        dead = wait_for_sync(lambda: seen()["dead"], 10, "the dead letter in the console", seen)
        assert [(d["route"], d["stage"]) for d in dead] == [("weeds", "schema")] and "7" in dead[0]["reason"], dead

        def both_on_the_map() -> dict[str, Any] | None:
            view = seen()
            return view if view and len(view["agents"]) == 2 else None

        snapshot = wait_for_sync(both_on_the_map, 30, "the UAV and the robot on the map", seen)
        (ux, uy), (rx, ry) = snapshot["agents"]["uav1"], snapshot["agents"]["robot1"]
        assert rx > ux and ry < uy, snapshot["agents"]  # the robot is north-east of the UAV: right and up
        assert sorted(snapshot["labels"]) == ["robot1", "uav1"] and snapshot["scale"].endswith("m"), snapshot
        assert cell("uav-position", "delivered") == "1" and cell("robot-position", "delivered") == "1"

        lines = wait_for_sync(lambda: len(tapped := seen()["tap"]) == 4 and tapped, 20, "the tapped messages", seen)
        assert sum("delivered" in line for line in lines) == 3 and sum("dead_lettered" in line for line in lines) == 1, lines

        shot = tmp_path / "console.png"
        assert driver.save_screenshot(str(shot))
        if os.environ.get("CONSOLE_SCREENSHOT"):  # docs/console.png is made this way (docs/operations.md)
            shutil.copyfile(shot, REPO / os.environ["CONSOLE_SCREENSHOT"])
        errors = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
        assert not errors, errors  # no script error, nothing the page's content security policy refused

        # the engine stops at once with the event stream and the tap open; the page says it is offline
        assert engine.stop(30) == 0, engine.log()
        wait_for_sync(lambda: seen()["live"] == "reconnecting", 10, "the page to notice", seen)
    finally:
        driver.quit()
