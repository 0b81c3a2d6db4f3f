"""What keeps pytest-xdist workers (``./scripts/test.sh`` runs several) apart on one machine.

Ports are never fixed (every server's is drawn at random below the kernel's ephemeral range by
``engine.common.processes.listening_port``) and private brokers get uuid node names and their own
temporary directories, so those need nothing from here. What does: the ROS 2 domain.
DDS discovers every participant of a domain on the host, so two workers on one domain see
each other's topics. Each worker gets its own block of :data:`SLOTS` domains, and each test
module takes its own slot in the block (an engine of the previous test still shutting down
never shares the next test's domain). Blocks are chosen from the run's id (xdist gives every
worker of one run the same id; a plain pytest run uses its pid), so two runs on one machine
(helpers testing side by side) rarely share a block.
"""

from __future__ import annotations

import os
import zlib

SLOTS = 20
"""Domains per worker: one per test module that starts ROS 2 nodes (see :func:`ros_domain`)."""
BLOCKS = 232 // SLOTS
"""ROS 2 domain ids go up to 232 on Linux (Fast DDS derives its UDP ports from them)."""


def worker_index() -> int:
    """0 for ``gw0`` or a run without xdist, N for ``gwN``."""
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return int(name.removeprefix("gw") or 0)


def _run_seed() -> int:
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    return zlib.crc32(run.encode()) if run else os.getpid()


def ros_domain(slot: int) -> int:
    """A ROS 2 domain id (1..231) for test slot ``slot`` (0..SLOTS-1) that no other worker of
    this run uses."""
    if not 0 <= slot < SLOTS:
        raise ValueError(f"slot {slot} is outside 0..{SLOTS - 1}: raise SLOTS")
    block = (_run_seed() + worker_index()) % BLOCKS
    return 1 + block * SLOTS + slot
