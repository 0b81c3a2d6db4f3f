"""The paper's first experiment on two hosts: RabbitMQ -> engine -> ROS 2 -> robot (second
network namespace) -> ROS 2 -> engine -> RabbitMQ, byte for byte at all three points."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from bench.netns import NamespacesUnavailable
from bench.roundtrip_ros2 import run_experiment

SIZES = [50, 150, 250]


@pytest.mark.soak
def test_round_trip_across_two_hosts_is_byte_identical(tmp_path: Path):
    try:
        summary = run_experiment(runs=1, count=100, rate=200.0, sizes=SIZES, out=tmp_path)
    except NamespacesUnavailable as exc:  # a missing part is a red run, never a skip
        pytest.fail(f"network namespaces cannot be created here: {exc}")
    rows = summary["results"]
    assert [row["size"] for row in rows] == SIZES
    for row in rows:
        assert (row["sent"], row["at_robot"], row["back"], row["identical"]) == (100, 100, 100, 100), row
        with open(row["csv"], newline="") as handle:
            records = list(csv.DictReader(handle))
        assert len(records) == 100
        for record in records:
            assert record["original"] == record["at_robot"] == record["back_at_gcs"]
            assert len(record["original"].encode()) == row["size"]
    payload = 100 * sum(SIZES)
    assert summary["robot_link_rx_bytes"] > payload, "the messages did not cross the veth link"
