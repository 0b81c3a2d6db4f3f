"""Shared fixtures: a real RabbitMQ node per test session (per xdist worker: see
tests/support/workers.py), a private mosquitto per MQTT test (never a mock); the tiers
(``fast``, ``alone``) ./scripts/test.sh runs one after another.

The broker modules are imported inside their fixtures, so that the fast tier (``--fast only``)
runs where neither RabbitMQ, mosquitto nor the protocols' client libraries are installed."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import pytest

from engine.common.processes import LIFETIME_ENV
from tests.support.repo import REPO

if TYPE_CHECKING:
    from engine.endpoints.amqp.broker import LocalCluster
    from engine.endpoints.mqtt.broker import LocalMosquitto


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
    from engine.endpoints.amqp.broker import LocalBroker

    with LocalBroker(lifetime=SESSION_BROKER_LIFETIME_S) as broker:
        yield broker.url


@pytest.fixture(scope="session")
def amqp_cluster() -> Iterator[LocalCluster]:
    """Three private nodes joined in one cluster, started once for every cluster test
    (about 30 s; per xdist worker that runs a cluster test: keep them in one module). A test that
    kills a node restarts it before it ends."""
    from engine.endpoints.amqp.broker import LocalCluster

    with LocalCluster(3, lifetime=SESSION_BROKER_LIFETIME_S) as cluster:
        yield cluster


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[LocalMosquitto]:
    """A private mosquitto for one test: its own configuration, port and persistence directory
    under ``tmp_path``, run under ``timeout -s KILL`` so a crashed run cannot leave it behind,
    and killed at teardown. The test may ``halt()`` and ``start()`` it (same port and data)."""
    from engine.endpoints.mqtt.broker import LocalMosquitto

    broker = LocalMosquitto(directory=tmp_path / "mosquitto", keep_dir=True, lifetime=BROKER_LIFETIME_S)
    broker.start()
    try:
        yield broker
    finally:
        broker.kill()


@pytest.fixture
def schemas_dir() -> Path:
    return REPO / "schemas"


BROKER_FIXTURES = frozenset({"amqp_url", "amqp_cluster", "mosquitto"})
"""The fixtures that start (or reach) a broker: a ``fast`` test may use none of them."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--alone", choices=("all", "exclude", "only"), default="all",
        help="tests marked `alone` (timing-sensitive: they need the machine to themselves): run them with "
        "the rest (all), leave them out (exclude: ./scripts/test.sh's parallel run), or run only them "
        "(only: its serial run after it)")
    parser.addoption(
        "--fast", choices=("all", "exclude", "only"), default="all",
        help="tests marked `fast` (no broker, no network peer, no ROS 2 node): run them with the rest (all), "
        "run only them (only: ./scripts/test.sh's first tier, which stops the run when it fails), or leave "
        "them out (exclude: its later runs)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "alone: timing-sensitive; ./scripts/test.sh runs it after the parallel run, with no other test beside it")
    config.addinivalue_line(
        "markers", "soak: takes 20 s or more (a soak or fault test); its module starts first in ./scripts/test.sh's "
        "parallel run. Still run by CI: `-m 'not soak'` is for a quick local run only")
    config.addinivalue_line(
        "markers", "fast: needs no broker, no network peer and no ROS 2 node, and takes seconds at most; "
        "./scripts/test.sh runs these first (`--fast only`: 341 tests, 55 s of CPU on 2 workers) and stops there when one fails")


def _keep(config: pytest.Config, items: list[pytest.Item], option: str) -> None:
    """Leave out (``exclude``) or keep only (``only``) the items marked ``option``, as the option says."""
    wanted = config.getoption(option)
    if wanted == "all":
        return
    marked = [(item.get_closest_marker(option) is not None) == (wanted == "only") for item in items]
    dropped = [item for item, kept in zip(items, marked) if not kept]
    if dropped:
        config.hook.pytest_deselected(items=dropped)
        items[:] = [item for item, kept in zip(items, marked) if kept]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """``--fast`` and ``--alone``; then the modules with the most ``soak`` tests first, so that
    ./scripts/test.sh's workers (``--dist loadfile``: a module's tests share one worker, as its
    module-scoped fixtures and the cluster tests' three nodes are started once) begin with the
    longest modules and end together."""
    _keep(config, items, "fast")
    _keep(config, items, "alone")
    soak = Counter(item.path for item in items if item.get_closest_marker("soak") is not None)
    items.sort(key=lambda item: -soak[item.path])  # stable: the order within a module stays


def pytest_runtest_setup(item: pytest.Item) -> None:
    """A ``fast`` test that asks for a broker fails, naming the fixture: the fast tier must run
    without one (and in seconds), or it stops being the tier that can run first."""
    if item.get_closest_marker("fast") is None:
        return
    brokers = sorted(BROKER_FIXTURES.intersection(getattr(item, "fixturenames", ())))
    if brokers:
        pytest.fail(f"{item.nodeid} is marked fast but uses {', '.join(brokers)}: the fast tier runs without a broker; "
                    "drop the mark or the fixture", pytrace=False)
    if item.get_closest_marker("alone") is not None or item.get_closest_marker("soak") is not None:
        pytest.fail(f"{item.nodeid} is marked fast and alone/soak: a fast test is neither", pytrace=False)
