"""Shared fixtures: a real RabbitMQ node per test session, a private mosquitto per MQTT test
(never a mock)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import pytest

from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.local_broker import LocalBroker, LocalCluster

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def amqp_url() -> Iterator[str]:
    """``RABBITROS_TEST_AMQP_URL`` if set, else a private node started for the session."""
    url = os.environ.get("RABBITROS_TEST_AMQP_URL")
    if url:
        yield url
        return
    with LocalBroker() as broker:
        yield broker.url


@pytest.fixture(scope="session")
def amqp_cluster() -> Iterator[LocalCluster]:
    """Three private nodes joined in one cluster, started once for every cluster test
    (about 30 s). A test that kills a node restarts it before it ends."""
    with LocalCluster(3) as cluster:
        yield cluster


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[LocalMosquitto]:
    """A private mosquitto for one test: its own configuration, port and persistence directory
    under ``tmp_path``, run under ``timeout -s KILL`` so a crashed run cannot leave it behind,
    and killed at teardown. The test may ``halt()`` and ``start()`` it (same port and data)."""
    broker = LocalMosquitto(directory=tmp_path / "mosquitto", keep_dir=True, lifetime=900)
    broker.start()
    try:
        yield broker
    finally:
        broker.kill()


@pytest.fixture
def schemas_dir() -> Path:
    return REPO / "schemas"
