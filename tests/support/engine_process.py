"""Run ``rabbitros-engine`` as a child process the way an operator does, bounded in time."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Coroutine, TypeVar

from tests.support.repo import REPO
from tests.support.waiting import wait_for_sync

T = TypeVar("T")


class EngineProcess:
    def __init__(self, routes: Path, status_file: Path, env: dict[str, str], *extra: str) -> None:
        self.status_file = status_file
        self.log_file = status_file.with_suffix(".log")
        self._log = open(self.log_file, "w")
        self.process = subprocess.Popen(
            ["timeout", "-s", "KILL", "600", sys.executable, "-m", "engine", "--routes", str(routes),
             "--schemas", str(REPO / "schemas"), "--status-file", str(status_file),
             "--stats-interval", "0.5", "--log-format", "json", *extra],
            cwd=REPO, env={**os.environ, **env}, stdout=self._log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def wait_started(self, timeout: float = 60.0) -> dict[str, Any]:
        """Until the status file says generation 1; fails naming the engine's log if it does
        not within ``timeout`` s, and at once if the engine exits meanwhile."""
        def started() -> dict[str, Any] | None:
            if self.process.poll() is not None:
                raise RuntimeError(f"engine exited {self.process.returncode}: {self.log()}")
            status = self.status()
            return status if status and status.get("generation", 0) >= 1 else None

        return wait_for_sync(started, timeout, "the engine to start (generation 1 in its status file)", self.log)

    def status(self) -> dict[str, Any] | None:
        try:
            return json.loads(self.status_file.read_text())
        except (OSError, ValueError):
            return None

    def current_status(self) -> dict[str, Any]:
        """The status file as the engine last wrote it, for a test that reads it after
        :meth:`wait_started`; fails naming the engine's log if there is none to read."""
        status = self.status()
        assert status is not None, f"no status file {self.status_file}: {self.log()}"
        return status

    def log(self) -> str:
        """The engine's last 4,000 characters of output, while it runs and once it is stopped
        (the child writes to the file itself: nothing of ours to flush)."""
        return self.log_file.read_text(errors="replace")[-4000:]

    def run(self, scenario: Callable[[], Coroutine[Any, Any, T]]) -> tuple[T, dict[str, Any]]:
        """Wait for the engine to start, run ``scenario`` against it, and stop it (exit status 0
        asserted); returns the scenario's result and the engine's last status."""
        try:
            self.wait_started()
            result = asyncio.run(scenario())
            status = self.status() or {}
        finally:
            exited = self.stop()
        assert exited == 0, f"engine exited {exited}: {self.log()}"
        return result, status

    def stop(self, timeout: float = 60.0) -> int:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self._log.close()
        return self.process.returncode
