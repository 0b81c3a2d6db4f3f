"""The command line: check, --version/--help, and run --local-broker end to end."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import signal
import socket
import ssl
import subprocess
import sys
from pathlib import Path

import aio_pika
import pytest

from engine import __version__
from engine.common.processes import listening_port
from engine.ops.cli_parser import COMMANDS, build_parser
from tests.support.amqp_helpers import Collector, publish
from tests.support.repo import REPO
from tests.support.waiting import wait_for_sync

LINE = re.compile(r"^(?P<file>[^:]+):(?P<line>\d+): (?P<message>.+)$")


def cli(*args: str, env: dict[str, str] | None = None, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "engine", *args],
        capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env,
    )


@pytest.mark.fast
def test_shipped_routes_check_clean():
    result = cli("check", "--routes", "routes/")
    assert result.returncode == 0, result.stderr
    assert "ok" in result.stdout


@pytest.mark.fast
def test_version_and_help():
    assert cli("--version").stdout.strip() == f"rabbitros-engine {__version__}"
    help_text = cli("--help").stdout
    assert "check" in help_text and "run" in help_text


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _options(parser: argparse.ArgumentParser) -> list[str]:
    """The operator's options: hidden ones (``--worker``, which the supervisor of ``run
    --workers N`` gives its workers) are not for the help nor the docs."""
    return [option for action in parser._actions for option in action.option_strings
            if option not in ("-h", "--help") and action.help != argparse.SUPPRESS]


@pytest.mark.fast
def test_top_level_help_shows_how_to_run():
    """``rabbitros-engine --help`` lists every command and every run option (run is the default
    command, so hiding its options hid how to run)."""
    result = cli("--help")
    assert result.returncode == 0
    commands = _commands()
    assert set(commands) == set(COMMANDS)
    for command in COMMANDS:
        assert re.search(rf"^\s+{command}\s+\S", result.stdout, re.M), command
    run_options = result.stdout.split("run options", 1)[1]
    for option in _options(commands["run"]):
        assert re.search(rf"^\s+{re.escape(option)}\b", run_options, re.M), option
    assert "--local-broker" in result.stdout.splitlines()[0]  # the usage line


@pytest.mark.fast
def test_operations_documents_every_option_of_every_command():
    """docs/operations.md names every option engine/ops/cli.py accepts: the run options in its
    Running table, the other commands' in its Commands block."""
    text = (REPO / "docs" / "operations.md").read_text()
    running = text.split("## Running", 1)[1].split("\n## ", 1)[0]
    for option in _options(_commands()["run"]):
        assert f"| `{option}" in running, f"run option {option} is not in docs/operations.md#running"
    commands = text.split("## Commands", 1)[1]
    for name, parser in _commands().items():
        if name != "run":
            for option in _options(parser):
                assert f"rabbitros-engine {name} " in commands and option in commands, f"{name} {option}"


BROKEN = {
    "bad_yaml.yaml": "routes:\n  - name: [unclosed\n",
    "unknown_key.yaml": """
routes:
  - name: typo
    source: {amqp: {queue: q, prefetchh: 10}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
""",
    "bad_jmespath.yaml": """
routes:
  - name: bad-path
    source: {amqp: {queue: q2}}
    mapping: "{a: b"
    schema: raw_json
    sink: {amqp: {exchange: out}}
""",
    "unknown_schema.yaml": """
routes:
  - name: no-schema
    source: {amqp: {queue: q3}}
    schema: weed_detektion
    sink: {amqp: {exchange: out}}
""",
    "unset_env.yaml": """
connections:
  gcs: {amqp: "amqp://guest:${SURELY_UNSET_PASSWORD_VAR}@localhost/"}
""",
}


@pytest.mark.fast
def test_check_reports_every_broken_file_with_file_and_line(tmp_path: Path):
    for name, text in BROKEN.items():
        (tmp_path / name).write_text(text)
    env = {k: v for k, v in os.environ.items() if k != "SURELY_UNSET_PASSWORD_VAR"}
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"), env=env)
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    parsed = [match for line in lines if (match := LINE.match(line))]
    assert len(parsed) == len(lines), lines
    by_file = {Path(m["file"]).name: (int(m["line"]), m["message"]) for m in parsed}
    assert len(lines) == len(BROKEN) == len(by_file)
    assert by_file["bad_yaml.yaml"][1].startswith("invalid YAML")
    assert by_file["unknown_key.yaml"] == (4, by_file["unknown_key.yaml"][1])
    assert "'prefetchh'" in by_file["unknown_key.yaml"][1]
    assert by_file["bad_jmespath.yaml"][0] == 5 and "bad-path" in by_file["bad_jmespath.yaml"][1]
    assert by_file["unknown_schema.yaml"][0] == 5 and "weed_detektion" in by_file["unknown_schema.yaml"][1]
    assert by_file["unset_env.yaml"][0] == 3 and "SURELY_UNSET_PASSWORD_VAR" in by_file["unset_env.yaml"][1]


@pytest.mark.fast
def test_duplicate_route_names_and_unknown_connection(tmp_path: Path):
    route = "  - {{name: same, source: {{amqp: {{queue: q, connection: {conn}}}}}, schema: raw_json, sink: {{amqp: {{exchange: e}}}}}}\n"
    (tmp_path / "a.yaml").write_text("connections:\n  gcs: {amqp: 'amqp://localhost/'}\nroutes:\n" + route.format(conn="gcs"))
    (tmp_path / "b.yaml").write_text("routes:\n" + route.format(conn="nope"))
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode != 0
    assert "already defined at" in result.stderr and "unknown connection 'nope'" in result.stderr


ELSEWHERE = """# a connection that names its own broker: --local-broker's node does not serve it
connections:
  own: {{amqp: "amqp://guest:guest@127.0.0.1:{port}/"}}
dead_letters: {{connection: gcs}}
routes:
  - name: elsewhere
    source: {{amqp: {{queue: q-elsewhere, connection: own}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: e, connection: own}}}}
"""


@pytest.mark.fast
def test_check_local_broker_names_connections_that_go_elsewhere(tmp_path: Path):
    (tmp_path / "gcs.yaml").write_text((REPO / "routes" / "gcs.yaml").read_text())
    (tmp_path / "own.yaml").write_text(ELSEWHERE.format(port=5999))
    plain = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert plain.returncode == 0 and plain.stderr == "", plain.stderr
    result = cli("check", "--local-broker", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines() == [
        f"{tmp_path}/own.yaml:3: warning: connection 'own' names its own broker (amqp://guest:***@127.0.0.1:5999/), "
        "so --local-broker's private node does not serve it and its routes use that broker; to use the private node, "
        "write the URL as \"${RABBITROS_AMQP_URL:-<the URL>}\", or leave the connection out"]


def test_run_with_local_broker_routes_and_stops_cleanly(tmp_path: Path):
    """routes/ (whose connection is ``${RABBITROS_AMQP_URL:-...}``) beside a file whose connection
    names its own URL: the first goes to the private node, the second is named in a warning at
    start, with the private node, and the others keep running."""
    url_file = tmp_path / "broker-url"
    status_file = tmp_path / "status.json"
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "gcs.yaml").write_text((REPO / "routes" / "gcs.yaml").read_text())
    (routes / "own.yaml").write_text(ELSEWHERE.format(port=listening_port()))
    process = subprocess.Popen(
        [sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", "schemas", "--local-broker",
         "--broker-url-file", str(url_file), "--status-file", str(status_file), "--log-format", "json"],
        cwd=REPO, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        wait_for_sync(lambda: status_file.exists() or process.poll() is not None, 90, "the engine to start or exit")
        assert status_file.exists(), "engine did not start"
        url = url_file.read_text().strip()

        async def roundtrip() -> list[bytes]:
            connection = await aio_pika.connect(url)
            channel = await connection.channel()
            output = await Collector.bind(channel, "farm", "canonical.weeds.#")
            body = {"agent": "uav1", "id": "d1", "stamp": 1.5, "detections": [{"lat": 1.0, "lon": 2.0, "confidence": 0.9}]}
            await publish(channel, "farm", "weeds.uav1", [json.dumps(body).encode()])
            received = await output.wait_for(1)
            await connection.close()
            return [m.body for m in received]

        bodies = asyncio.run(roundtrip())
        assert bodies == [b'{"agent_id":"uav1","id":"d1","points":[{"lat":1.0,"lon":2.0,"p":0.9}],"stamp":{"nanosec":500000000,"sec":1},"type":"weed_detection"}']
        status = json.loads(status_file.read_text())
        assert status["generation"] == 1 and set(status["routes"]) == {"uav-weeds", "gcs-commands", "elsewhere"}
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
        records = [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]
        started = next(r for r in records if r["msg"] == "local broker started")
        warnings = [r["problem"] for r in records if r["msg"] == "route warning"]
        assert len(warnings) == 1 and "own.yaml:3: connection 'own' names its own broker" in warnings[0] \
            and f"--local-broker's private node ({started['nodes'][0]}) does not serve it" in warnings[0], warnings
        assert "guest:guest" not in stderr, "a password reached the log"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    port = int(url.rsplit(":", 1)[1].strip("/"))
    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", port)) != 0, "the private broker outlived the engine"


TLS_ROUTE = """# endpoints that name no connection: the default one, the private node over amqps://
routes:
  - name: over-tls
    source: {amqp: {exchange: farm, binding_key: "plain.#", queue: tls-in}}
    schema: raw_json
    sink: {amqp: {exchange: farm, routing_key: carried.one}}
"""


def test_run_with_local_broker_tls_carries_a_message_over_amqps(tmp_path: Path):
    """``--local-broker --local-broker-tls``: the URL file names an amqps:// URL, a plain
    AMQP client cannot talk to that port, and a client verifying the run's throwaway CA
    publishes a message that a route carries back (the engine verified the same CA)."""
    url_file, status_file, routes = tmp_path / "broker-url", tmp_path / "status.json", tmp_path / "routes"
    routes.mkdir()
    (routes / "tls.yaml").write_text(TLS_ROUTE)
    process = subprocess.Popen(
        [sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", "schemas", "--local-broker",
         "--local-broker-tls", "--broker-url-file", str(url_file), "--status-file", str(status_file), "--log-format", "json"],
        cwd=REPO, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        wait_for_sync(lambda: status_file.exists() or process.poll() is not None, 90, "the engine to start or exit")
        assert status_file.exists(), "engine did not start"
        url = url_file.read_text().strip()
        assert url.startswith("amqps://guest:guest@localhost:"), url
        started = None
        assert process.stderr is not None, "the engine's stderr is a pipe"
        while started is None and process.poll() is None:
            line = process.stderr.readline()
            if line.startswith("{") and json.loads(line)["msg"] == "local broker started":
                started = json.loads(line)
        assert started is not None, "no 'local broker started' line"
        ca_file = Path(started["environment"]["RABBITROS_AMQP_CA_FILE"])
        plain = url.replace("amqps://", "amqp://", 1)

        async def roundtrip() -> list[bytes]:
            try:  # the node resets the connection: an AMQP header is no TLS ClientHello
                await asyncio.wait_for(aio_pika.connect(plain), 15)
            except (aio_pika.exceptions.AMQPConnectionError, ConnectionError, TimeoutError):
                pass
            else:
                raise AssertionError("a plain AMQP client talked to the TLS port")
            context = ssl.create_default_context(cafile=str(ca_file))
            connection = await aio_pika.connect(url, ssl_context=context)
            channel = await connection.channel()
            output = await Collector.bind(channel, "farm", "carried.#")
            await publish(channel, "farm", "plain.one", [b'{"n": 1}'])
            received = await output.wait_for(1)
            await connection.close()
            return [m.body for m in received]

        assert asyncio.run(roundtrip()) == [b'{"n": 1}']
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
        assert "guest:guest" not in stderr, "a password reached the log"
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert not ca_file.exists(), "the throwaway CA outlived the private node"


@pytest.mark.fast
def test_local_broker_tls_refused_without_local_broker_or_with_a_cluster(tmp_path: Path):
    """Exit 2 and a line saying why, before any node starts."""
    (tmp_path / "tls.yaml").write_text(TLS_ROUTE)
    alone = cli("--routes", str(tmp_path), "--schemas", "schemas", "--local-broker-tls")
    assert alone.returncode == 2 and "--local-broker-tls needs --local-broker" in alone.stderr, alone.stderr
    cluster = cli("--routes", str(tmp_path), "--schemas", "schemas", "--local-broker", "--local-broker-tls", "--cluster", "2")
    assert cluster.returncode == 2 and "leave out --cluster" in cluster.stderr, cluster.stderr


@pytest.mark.fast
def test_a_routes_directory_given_as_a_bare_word_is_pointed_to_routes() -> None:
    """``check --workers 2 examples/``: argparse's 'unrecognized arguments' says how to give it."""
    result = cli("check", "--workers", "2", "examples/")
    assert result.returncode == 2
    assert "unrecognized arguments: examples/ (give the routes directory as --routes DIR)" in result.stderr
    assert "--routes DIR)" not in cli("check", "--no-such-option").stderr
