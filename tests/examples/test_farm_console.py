"""The web console on the farm example (issue 33), in a real browser.

The farm runs as ``examples/farm_demo.py`` runs it (the simulated UAV on MAVLink 2 through the
emulated SiK radio, the ROS 2 ground robot, the engine with a private RabbitMQ node, the
AMQP-only supervisor), its admin on a port the test chose; Debian's chromium, headless, opens
the console at ``http://127.0.0.1:PORT/`` (loopback: no token). The page must list every route
of ``examples/farm_uav_gcs.yaml``, show a counter moving, show a dead letter with its stage and
reason (a command without its ``command`` field, published by the test to the farm's broker:
the ``command`` schema refuses it), and draw the UAV and the ground robot on the map. With
``CONSOLE_SCREENSHOT=docs/console-farm.png`` the test saves its screenshot there (the one in
docs/operations.md).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import aio_pika
import pytest
import yaml
from selenium.webdriver.common.by import By

from engine.common.processes import listening_port
from tests.support.browser import PAGE_SNAPSHOT, browser
from tests.support.repo import REPO
from tests.support.waiting import wait_for_sync
from tests.support.workers import ros_domain

DURATION = 45
"""Seconds the supervisor watches: the browser's checks take 10-20 s once the engine is up."""
ROUTES = sorted(route["name"] for route in yaml.safe_load((REPO / "examples" / "farm_uav_gcs.yaml").read_text())["routes"])


async def publish_bad_command(url: str) -> None:
    connection = await aio_pika.connect(url)
    async with connection:
        channel = await connection.channel(publisher_confirms=True)
        exchange = await channel.declare_exchange("farm", aio_pika.ExchangeType.TOPIC, durable=True, passive=True)
        body = {"type": "command", "agent_id": "uav1", "id": "console-test-bad"}  # no "command": the schema requires it
        await exchange.publish(aio_pika.Message(json.dumps(body).encode(), content_type="application/json"), "command.uav1")


@pytest.mark.soak
@pytest.mark.timeout(400)
def test_the_console_shows_the_farm(tmp_path: Path) -> None:
    work, port = tmp_path / "farm", listening_port()
    log = open(tmp_path / "demo.log", "w")
    demo = subprocess.Popen(
        ["timeout", "-s", "KILL", "300", sys.executable, "examples/farm_demo.py", "--duration", str(DURATION),
         "--work", str(work), "--plain", "--admin", str(port),
         "--ros-domain", str(ros_domain(18))],
        cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    driver = None
    try:
        wait_for_sync(lambda: (work / "url").exists() and (work / "status.json").exists() or demo.poll() is not None, 150,
                      "the farm's engine to start", lambda: (tmp_path / "demo.log").read_text()[-2000:])
        assert demo.poll() is None, (tmp_path / "demo.log").read_text()[-3000:]
        driver = browser(tmp_path / "chromium-profile", window="1400,900")
        driver.get(f"http://127.0.0.1:{port}/")

        def seen() -> dict[str, Any]:
            return dict(driver.execute_script(PAGE_SNAPSHOT))

        def count(route: str, column: str = "delivered") -> int:
            return int(seen()["routes"].get(route, {}).get(column) or 0)

        wait_for_sync(lambda: sorted(seen()["routes"]) == ROUTES, 30, "the console to list every route of the farm",
                      lambda: sorted(seen()["routes"]))
        wait_for_sync(lambda: seen()["live"] == "live", 10, "the event stream", seen)
        first = wait_for_sync(lambda: count("uav1-position"), 60, "the UAV's positions to be delivered", lambda: seen()["routes"])
        wait_for_sync(lambda: count("uav1-position") > first, 20, "the counter to move", lambda: seen()["routes"])

        asyncio.run(publish_bad_command((work / "url").read_text().strip()))
        dead = wait_for_sync(lambda: seen()["dead"], 20, "the dead letter in the console", seen)
        assert [(d["route"], d["stage"]) for d in dead] == [("uav1-commands", "schema")], dead
        assert '"command" is a required property' in dead[0]["reason"], dead
        assert count("uav1-commands", "dead-lettered") == 1

        def both_on_the_map() -> dict[str, Any] | None:
            view = seen()
            return view if view and {"uav1", "robot1"} <= set(view["agents"]) else None

        page = wait_for_sync(both_on_the_map, 60, "the UAV and the ground robot on the map", seen)
        assert sorted(page["agents"]) == ["robot1", "uav1"] and sorted(page["labels"]) == ["robot1", "uav1"], page
        assert page["scale"].endswith("m"), page
        wait_for_sync(lambda: count("uav1-weeds") and count("robot-missions"), 60, "a weed detection and a mission",
                      lambda: seen()["routes"])  # the screenshot shows every flow at work
        driver.find_element(By.ID, "tap-route").send_keys("uav1-position")  # and a live tap of the UAV's positions
        driver.find_element(By.ID, "tap-toggle").click()
        wait_for_sync(lambda: len(seen()["tap"]) >= 3, 20, "the tapped positions", seen)

        shot = tmp_path / "console-farm.png"
        assert driver.save_screenshot(str(shot))
        if os.environ.get("CONSOLE_SCREENSHOT"):  # docs/console-farm.png is made this way (docs/operations.md)
            shutil.copyfile(shot, REPO / os.environ["CONSOLE_SCREENSHOT"])
        errors = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
        assert not errors, errors

        demo.wait(DURATION + 200)
        output = (tmp_path / "demo.log").read_text()
        # the demo counts a dead letter as a broken promise: the one the test made must be the only one
        assert demo.returncode == 1 and "farm: flows that dead-lettered messages: uav1-commands (1)" in output, output[-3000:]
        assert "flows that carried nothing" not in output and "the supervisor exited" not in output, output[-3000:]
    finally:
        if driver is not None:
            driver.quit()
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGINT)  # the demo stops its parts on the way out
            demo.wait(60)
        log.close()
