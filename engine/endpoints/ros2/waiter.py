"""The thread that waits for a connection's subscriptions, so that no rclpy executor runs.

Executor design. rclpy's executors do not fit an asyncio program: SingleThreadedExecutor
tops out near 2,000 msg/s, polling ``spin_once(0)`` from the loop costs 45 % of a core while
idle, and EventsExecutor spinning in a thread deadlocks the first ``create_publisher`` made
from another thread (in ``Node._wake_executor``). So a connection uses no executor at all:

* a *waiter* thread (:class:`Waiter`) blocks in ``rcl_wait`` (GIL released) on a wait set
  holding the node's subscriptions and one guard condition (``_rclpy.WaitSet``, what rclpy's
  own executors use). When subscriptions are ready it hands their handles to the loop with
  ``call_soon_threadsafe`` and sleeps until the loop has taken them, as the wait set is
  level-triggered. It never calls into the node or user code and costs nothing while idle;
* everything else runs on the asyncio thread (node.py, source.py, sink.py): taking messages
  (at most ``TAKE_BUDGET`` per subscription per wake-up, so a flood cannot starve AMQP),
  converting and queueing them, publishing, and creating or destroying publishers and
  subscriptions. With no executor attached to the node, ``Node._wake_executor`` is a no-op
  and there is no lock to take. A change of subscriptions triggers the guard condition so the
  waiter rebuilds its wait set; a subscription destroyed while the waiter holds it is freed
  when the waiter lets go.

Measured on the 2-core development machine (bench/bench_ros2_executor.py): 10,000 msg/s
received without loss (String and NavSatFix), 0.1 % CPU while idle, p50 latency under 1 ms.
Not serviced: QoS event handlers (e.g. rclpy's incompatible-QoS warning).
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from contextlib import ExitStack
from typing import Any, Callable

from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

log = logging.getLogger("engine.ros2")

STOP_WAIT = 5.0
"""Seconds :meth:`Waiter.stop` waits for the thread before it says so and goes on."""


class Waiter:
    """One connection's waiter thread and its hand-over to the loop.

    ``subscriptions`` returns the subscriptions to wait on: a new tuple after each change (the
    wait set is rebuilt when the tuple is not the one it was built from), triggered through
    ``guard``. ``take_ready`` runs on the loop with the ready subscriptions' handle pointers."""

    def __init__(self, name: str, context: Context, guard: GuardCondition,
                 subscriptions: Callable[[], tuple[Any, ...]], take_ready: Callable[[list[int]], None]) -> None:
        self._name = name
        self._context = context
        self._guard = guard
        self._subscriptions = subscriptions
        self._take_ready = take_ready
        self._loop = asyncio.get_running_loop()
        self._taken: queue.SimpleQueue[None] = queue.SimpleQueue()
        """One token per hand-over the loop finished (and one at stop): what the waiter waits
        on. A C queue: ``threading.Event``'s set ran its Condition's notify in Python on the
        loop at every hand-over (1.3 % of the engine's GIL samples in bench/fleet.py)."""
        self._closing = False
        self._thread = threading.Thread(target=self._wait_loop, name=f"ros2-wait-{name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    async def stop(self) -> None:
        """Wake the thread and wait (bounded) for it to end; it holds no handle afterwards."""
        self._closing = True
        self._guard.trigger()
        self._taken.put(None)
        await asyncio.to_thread(self._thread.join, STOP_WAIT)
        if self._thread.is_alive():
            log.warning("ros2 connection %r: wait thread did not stop", self._name)

    def _wait_loop(self) -> None:
        """Blocks in rcl_wait; hands ready subscription handles to the loop, then waits for
        the loop to take them (the wait set is level-triggered).

        The wait set and the hold on its subscriptions' handles are kept until the
        subscriptions change (a new tuple from ``subscriptions``), not rebuilt at every wake-up:
        rebuilding entered every handle in Python, O(subscriptions) with the GIL held at every
        message of a fleet's 100 topics at 10 Hz (15 % of the engine's samples in bench/fleet.py)."""
        context, guard = self._context, self._guard
        held = ExitStack()
        waited: tuple[Any, ...] | None = None
        handles: list[Any] = []
        wait_set: Any = None
        try:
            while not self._closing:
                try:
                    current = self._subscriptions()
                    if waited is not current:  # (re)build: hold the handles, size the wait set
                        held.close()
                        held = ExitStack()
                        waited = current
                        handles = []
                        for sub in waited:
                            try:
                                held.enter_context(sub.handle)
                            except InvalidHandle:
                                continue
                            handles.append(sub.handle)
                        held.enter_context(guard.handle)
                        context_handle = context.handle
                        assert context_handle is not None  # rclpy.init ran before the waiter started
                        held.enter_context(context_handle)
                        wait_set = _rclpy.WaitSet(len(handles), 1, 0, 0, 0, 0, context.handle)
                    wait_set.clear_entities()
                    for handle in handles:
                        wait_set.add_subscription(handle)
                    wait_set.add_guard_condition(guard.handle)
                    wait_set.wait(-1)
                    ready = wait_set.get_ready_entities("subscription")
                except Exception as exc:
                    held.close()
                    waited = None
                    if self._closing or not context.ok():
                        return
                    log.error("ros2 connection %r: wait failed: %s", self._name, exc)
                    time.sleep(0.1)
                    continue
                if not ready or self._closing:
                    continue
                try:
                    self._loop.call_soon_threadsafe(self._hand_over, ready)
                except RuntimeError:
                    return  # the loop is closed
                self._taken.get()
        finally:
            held.close()

    def _hand_over(self, ready: list[int]) -> None:
        """On the loop: the ready subscriptions taken, the waiter may wait again."""
        try:
            self._take_ready(ready)
        finally:
            self._taken.put(None)
