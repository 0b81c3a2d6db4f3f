"""A real rclpy node for tests: its own context (on the test's ROS 2 domain), spun by an
executor in a thread of its own, so the test's asyncio loop and the engine's are never
blocked by it; ``close()`` undoes it all. rclpy is told not to take SIGINT/SIGTERM."""

from __future__ import annotations

import threading
from typing import Any, Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions


class SpunNode:
    """``SpunNode(domain, "name")``; ``executor`` makes the executor for the context (default:
    single-threaded; action servers that sleep between feedbacks want a MultiThreadedExecutor)."""

    def __init__(self, domain_id: int, name: str,
                 executor: Callable[[Context], Executor] = lambda context: SingleThreadedExecutor(context=context)) -> None:
        self.context = Context()
        rclpy.init(args=[], context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(name, context=self.context, start_parameter_services=False)
        self.executor = executor(self.context)
        self.executor.add_node(self.node)
        self._closing: list[Any] = []
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def destroy_on_close(self, entity: Any) -> Any:
        """``entity`` (an action server, …) is destroyed before the node when closing."""
        self._closing.append(entity)
        return entity

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        self.thread.join(5)
        for entity in self._closing:
            entity.destroy()
        self.node.destroy_node()
        self.context.try_shutdown()
