"""Shared fixtures: a real RabbitMQ node per test session (per xdist worker: see
tests/support/workers.py), a private mosquitto per MQTT test (never a mock)."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Iterator

import pytest

from engine.common.processes import LIFETIME_ENV
from engine.endpoints.amqp.broker import LocalBroker, LocalCluster
from engine.endpoints.mqtt.broker import LocalMosquitto
from tests.support.repo import REPO


BROKER_LIFETIME_S = 900
"""Every private broker a test starts, itself or through an engine (``--local-broker``), is
killed from outside after this long (engine/common/processes.py LIFETIME_ENV): a killed run leaves
none behind for longer. Per test; an engine the tests run lives at most 600 s."""
SESSION_BROKER_LIFETIME_S = 3600
"""The session's nodes (``amqp_url``, ``amqp_cluster``) live as long as the worker's session,
which on a loaded machine may take most of ./scripts/test.sh's 1500 s (and more run by hand)."""
os.environ.setdefault(LIFETIME_ENV, str(BROKER_LIFETIME_S))


@pytest.fixture(scope="session", autouse=True)
def private_state_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``XDG_STATE_HOME`` of every engine the session runs (in process or as a child): its default
    dead-letter spool, which would otherwise be one directory in the user's home shared by every
    xdist worker (and every run on the machine)."""
    state = tmp_path_factory.mktemp("state")
    saved = os.environ.get("XDG_STATE_HOME")
    os.environ["XDG_STATE_HOME"] = str(state)
    yield state
    if saved is None:
        os.environ.pop("XDG_STATE_HOME", None)
    else:
        os.environ["XDG_STATE_HOME"] = saved


@pytest.fixture(scope="session")
def amqp_url() -> Iterator[str]:
    """``RABBITROS_TEST_AMQP_URL`` if set, else a private node started for the session."""
    url = os.environ.get("RABBITROS_TEST_AMQP_URL")
    if url:
        yield url
        return
    with LocalBroker(lifetime=SESSION_BROKER_LIFETIME_S) as broker:
        yield broker.url


@pytest.fixture(scope="session")
def amqp_cluster() -> Iterator[LocalCluster]:
    """Three private nodes joined in one cluster, started once for every cluster test
    (about 30 s; per xdist worker that runs a cluster test: keep them in one module). A test that
    kills a node restarts it before it ends."""
    with LocalCluster(3, lifetime=SESSION_BROKER_LIFETIME_S) as cluster:
        yield cluster


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[LocalMosquitto]:
    """A private mosquitto for one test: its own configuration, port and persistence directory
    under ``tmp_path``, run under ``timeout -s KILL`` so a crashed run cannot leave it behind,
    and killed at teardown. The test may ``halt()`` and ``start()`` it (same port and data)."""
    broker = LocalMosquitto(directory=tmp_path / "mosquitto", keep_dir=True, lifetime=BROKER_LIFETIME_S)
    broker.start()
    try:
        yield broker
    finally:
        broker.kill()


@pytest.fixture
def schemas_dir() -> Path:
    return REPO / "schemas"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--alone", choices=("all", "exclude", "only"), default="all",
        help="tests marked `alone` (timing-sensitive: they need the machine to themselves): run them with "
        "the rest (all), leave them out (exclude: ./scripts/test.sh's parallel run), or run only them "
        "(only: its serial run after it)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "alone: timing-sensitive; ./scripts/test.sh runs it after the parallel run, with no other test beside it")
    config.addinivalue_line(
        "markers", "soak: takes 20 s or more (a soak or fault test); its module starts first in ./scripts/test.sh's "
        "parallel run. Still run by CI: `-m 'not soak'` is for a quick local run only")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``--alone``; then the modules with the most ``soak`` tests first, so that ./scripts/test.sh's workers
    (``--dist loadfile``: a module's tests share one worker, as its module-scoped fixtures and the
    cluster tests' three nodes are started once) begin with the longest modules and end together."""
    wanted = config.getoption("alone")
    if wanted != "all":
        alone = [(item.get_closest_marker("alone") is not None) == (wanted == "only") for item in items]
        keep = [item for item, kept in zip(items, alone) if kept]
        dropped = [item for item, kept in zip(items, alone) if not kept]
        if dropped:
            config.hook.pytest_deselected(items=dropped)
            items[:] = keep
    soak = Counter(item.path for item in items if item.get_closest_marker("soak") is not None)
    items.sort(key=lambda item: -soak[item.path])  # stable: the order within a module stays
