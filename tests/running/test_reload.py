"""Hot reload under a steady stream: nothing lost, duplicates counted, one generation per copy."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.support.reload_harness import run_reloads


@pytest.mark.soak
def test_fifty_rewrites_under_500_msg_per_s_lose_nothing(amqp_url: str, tmp_path: Path):
    """AMQP->AMQP, AMQP->ROS 2 and ROS 2->AMQP at 500 msg/s each while farm.yaml is rewritten
    50 times: mapping changes, a route added and removed, atomic renames, an invalid file
    written and then fixed."""
    run = asyncio.run(run_reloads(amqp_url, tmp_path, rewrites=50, rate=500.0, min_sent=5000))
    print(run.summary())
    written = {0, *run.written_generations}
    for name, flow in run.flows.items():
        assert flow.sent >= 5000, name
        missing = set(range(flow.sent)) - set(flow.copies)
        assert not missing, f"{name}: {len(missing)} messages lost, e.g. {sorted(missing)[:10]}"
        seen = {gen for gens in flow.copies.values() for gen in gens}
        assert seen <= written, name
        assert len(seen) >= 40, f"{name}: mappings were not swapped live"
        assert max(seen) == run.written_generations[-1], f"{name}: the last configuration is not live"
    assert run.rejected_reported, "the invalid file was not reported with file:line"
    reloads = run.status["reloads"]
    assert reloads["rejected"] == 5
    assert reloads["succeeded"] >= 40, "saves close together may share a reload, not most of them"
    assert run.status["generation"] == reloads["succeeded"] + 1


def test_sighup_reloads_and_status_names_the_live_config(amqp_url: str, tmp_path: Path):
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.support.repo import REPO
    from tests.support.engine_process import EngineProcess
    from tests.support.waiting import wait_for_sync

    routes = tmp_path / "routes"
    routes.mkdir()
    route = "routes:\n  - {{name: {name}, source: {{amqp: {{queue: hup-{name}}}}}, schema: raw_json, sink: {{amqp: {{exchange: hup-out}}}}}}\n"
    (routes / "a.yaml").write_text(route.format(name="first"))
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--no-watch")
    try:
        before = engine.wait_started()
        (routes / "b.yaml").write_text(route.format(name="second"))
        time.sleep(0.5)  # quiet window: no reload may happen without SIGHUP (the behaviour under test)
        assert engine.current_status()["generation"] == 1, "reloaded without SIGHUP despite --no-watch"
        os.killpg(engine.process.pid, signal.SIGHUP)
        wait_for_sync(lambda: (engine.status() or {}).get("generation", 0) >= 2, 20, "generation 2 after SIGHUP", engine.status)
        after = engine.current_status()
        shown = subprocess.run(
            [sys.executable, "-m", "engine", "status", "--status-file", str(engine.status_file)],
            capture_output=True, text=True, timeout=30, cwd=REPO,
        )
    finally:
        assert engine.stop() == 0
    assert after["generation"] == 2
    assert after["config_hash"] != before["config_hash"]
    assert set(after["routes"]) == {"first", "second"}
    assert after["routes"]["first"]["generation"] == 1, "an unchanged route was restarted"
    assert json.loads(shown.stdout)["config_hash"] == after["config_hash"]
