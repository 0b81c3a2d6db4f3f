"""Secrets from files (issue 21): ``${file:/run/credentials/amqp-password}`` wherever
``${VAR}`` works, its content shown as ``***`` everywhere it is printed."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

from engine.common.redaction import Secret, reveal
from engine.common.schemas import SchemaRegistry
from engine.language.route_yaml import substitute_env
from engine.language.routes import load_routes
from tests.support.repo import REPO
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for_sync

SECRET = "F1le-" + uuid.uuid4().hex[:12]


def _check(routes: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["timeout", "-s", "KILL", "60", sys.executable, "-m", "engine", "check", "--routes", str(routes),
         "--schemas", str(REPO / "schemas")],
        cwd=REPO, env=dict(os.environ), capture_output=True, text=True, timeout=70,
    )


def test_the_file_content_is_substituted_with_one_trailing_newline_stripped(tmp_path: Path):
    (tmp_path / "pw").write_text(SECRET + "\n\n")
    (tmp_path / "crlf").write_text(SECRET + "\r\n")
    assert substitute_env(f"a:${{file:{tmp_path}/pw}}:b", {}) == f"a:{SECRET}\n:b"
    assert substitute_env(f"${{file:{tmp_path}/crlf}}", {}) == SECRET
    (tmp_path / "pw").write_text(SECRET + "\n")
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "c.yaml").write_text(f'connections:\n  gcs: {{amqp: "amqp://farmer:${{file:{tmp_path}/pw}}@localhost/"}}\n')
    loaded = load_routes(routes, SchemaRegistry(REPO / "schemas"))
    assert [reveal(spec.settings["url"]) for spec in loaded.connections.values()] == [f"amqp://farmer:{SECRET}@localhost/"]
    assert [str(spec.settings["url"]) for spec in loaded.connections.values()] == ["amqp://farmer:***@localhost/"]
    assert str(Secret(SECRET, "***")) == "***"


def test_check_never_prints_a_file_secret_and_names_an_unreadable_file(tmp_path: Path):
    secret_file = tmp_path / "amqp-password"
    secret_file.write_text(SECRET + "\n")
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "a.yaml").write_text(
        "connections:\n"
        f'  good: {{amqp: {{url: "amqp://farmer:${{file:{secret_file}}}@localhost:5672/", heartbeat: x}}}}\n'
        f'  bad_url: {{amqp: {{url: "amqp://farmer:${{file:{secret_file}}}@/"}}}}\n'
        f'  plain: {{amqp: {{url: "amqp://localhost/", heartbeat: "${{file:{secret_file}}}"}}}}\n'
        f'  missing: {{amqp: "amqp://farmer:${{file:{tmp_path}/nope}}@localhost/"}}\n'
    )
    done = _check(routes)
    output = done.stdout + done.stderr
    assert done.returncode == 1, output
    assert SECRET not in output, output
    assert "amqp://farmer:***@localhost:5672/" in output, output
    assert f"a.yaml:5: secret file {tmp_path}/nope: cannot read it (No such file or directory)" in output, output
    secret_file.chmod(0)
    if os.geteuid() != 0:  # root reads a mode-0 file; the missing file above covers it there
        assert "Permission denied" in _check(routes).stdout + _check(routes).stderr


def test_logs_and_status_never_show_a_file_secret(tmp_path: Path, amqp_url: str):
    """A refused login (the password file holds a wrong password): the engine logs its
    reconnection errors at debug level and reports the connection unhealthy; neither the log
    nor the status file holds the content."""
    secret_file = tmp_path / "amqp-password"
    secret_file.write_text(SECRET + "\n")
    host = amqp_url.split("@", 1)[1]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(
        f'connections:\n  gcs: {{amqp: "amqp://farmer:${{file:{secret_file}}}@{host}"}}\n'
        "routes:\n  - name: relay\n    source: {amqp: {queue: secret-file-q}}\n    schema: raw_json\n"
        "    sink: {amqp: {exchange: secret-file-out, routing_key: x}}\n")
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--log-level", "debug")
    try:
        wait_for_sync(lambda: "ACCESS_REFUSED" in str(engine.status() or {}) or "ACCESS_REFUSED" in engine.log_file.read_text(),
                      30, "a refused login reported", detail=engine.log)
    finally:
        engine.stop()
    logs, status_text = engine.log_file.read_text(), engine.status_file.read_text() if engine.status_file.exists() else ""
    assert SECRET not in logs and SECRET not in status_text
    assert "farmer:***@" in logs + status_text, logs[-2000:]
