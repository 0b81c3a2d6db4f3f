"""ROS 2 calls: the engine as a client of a ROS 2 service (issue 19), a sink of the ros2 transport.

    sink: {ros2: {service: /robot1/set_spray, type: std_srvs/srv/SetBool, timeout: 5, max_in_flight: 10}}

Each message is one request (its sink mapping's output, or the canonical message, built as the
service's ``Request`` by the rules of engine/endpoints/rosmsg.py); the response, in rosbridge
JSON, is the call's ``result`` reply (engine/replies.py). A message is accepted once its
response arrived, so the route's source acknowledges a call only once it was answered.

Failures are permanent (:class:`MessageRejected`, so the caller's ``error`` reply comes within
``timeout`` and the request is dead-lettered): no server within ``timeout`` ("not available"),
no response within ``timeout`` (a late response is dropped: rclpy forgets the request), a
request the type cannot carry. Retrying would answer a caller who has given up, and a service
call is not known to be idempotent.

Concurrency: the calls of a batch run together, at most ``max_in_flight`` at a time per sink.
Its default, 10, is the depth of ROS 2's default service QoS (``rmw_qos_profile_services_default``:
KEEP_LAST 10), which a server created with the defaults keeps: more requests in flight could
overwrite unread ones in the server's reader and be lost. The client's own request writer and
response reader are sized to ``max_in_flight``; raise it together with the servers' depth.

Executor: the connection's main node runs no executor (engine/endpoints/ros2.py), so calls use a
second node in the same rclpy context (one DDS participant; ``<node>_calls`` in
``ros2 node list``) spun by a ``SingleThreadedExecutor`` in a thread of its own; a response
settles the asyncio future of its call with ``call_soon_threadsafe``. ``call_async`` and
``create_client`` are safe from the asyncio thread while that executor spins (rclpy takes the
client's lock and wakes the executor's wait set).
"""

from __future__ import annotations

import asyncio
import importlib
import logging
import re
import threading
from typing import Any, Sequence

from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from engine.backoff import Backoff
from engine.endpoints import rosmsg
from engine.endpoints.base import EndpointError, MessageRejected, Outbound, Sink

log = logging.getLogger("engine.ros2")

DEFAULT_CALL_TIMEOUT = 10.0
DEFAULT_MAX_IN_FLIGHT = 10
"""The depth of ROS 2's default service QoS: see the module docstring."""
_SERVICE_TYPE = re.compile(r"^([a-z][a-z0-9_]*)/srv/([A-Z][A-Za-z0-9]*)$")
_AVAILABLE_FIRST, _AVAILABLE_MAX = 0.01, 0.25
"""Backoff between looks for a server that is not there yet (a look costs microseconds)."""


def resolve_service(name: Any) -> type:
    """The service class of ``pkg/srv/Type``; MessageError if it is not installed."""
    match = _SERVICE_TYPE.match(name.strip()) if isinstance(name, str) else None
    if match is None:
        raise rosmsg.MessageError(f"service type {name!r} is not of the form pkg/srv/Type")
    pkg, cls_name = match.groups()
    try:
        module = importlib.import_module(f"{pkg}.srv")
    except ImportError:
        raise rosmsg.MessageError(f"service type '{pkg}/srv/{cls_name}' is not installed") from None
    cls = getattr(module, cls_name, None)
    if not isinstance(cls, type) or not hasattr(cls, "Request"):
        raise rosmsg.MessageError(f"service type '{pkg}/srv/{cls_name}' is not installed")
    return cls


def service_qos(max_in_flight: int) -> QoSProfile:
    """The services' default QoS (reliable, volatile) with a depth for ``max_in_flight`` calls."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, max_in_flight),
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


class CallNode:
    """The node of a connection's calls and the executor thread that serves its responses."""

    def __init__(self, context: Context, node_name: str, namespace: str) -> None:
        self.node = Node(f"{node_name}_calls", namespace=namespace, context=context, start_parameter_services=False,
                         parameter_overrides=[Parameter("start_type_description_service", value=False)])
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"ros2-calls-{node_name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass
        except Exception as exc:  # the context went away under it
            log.error("ros2 calls node %r stopped: %s", self.node.get_name(), exc)

    def close(self) -> None:
        """Blocking (the connection runs it in a thread): stop the executor, then the node."""
        self.executor.shutdown(timeout_sec=2.0)
        self._thread.join(5.0)
        self.node.destroy_node()


class ServiceSink(Sink):
    """Calls one service per message; replies with the response (see the module docstring)."""

    def __init__(self, calls: CallNode, route: str, service: str, type_name: str, timeout: float,
                 max_in_flight: int) -> None:
        self._where = f"route {route!r}, ros2 service {service!r}"
        try:
            self._cls = resolve_service(type_name)
        except rosmsg.MessageError as exc:
            raise EndpointError(f"{self._where}: {exc}") from None
        self._calls = calls
        self._service = service
        self._timeout = timeout
        self._slots = asyncio.Semaphore(max_in_flight)
        try:
            self._client = calls.node.create_client(self._cls, service, qos_profile=service_qos(max_in_flight))
        except Exception as exc:
            raise EndpointError(f"{self._where}: cannot create the client: {exc}") from exc

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        """The batch's calls together, ``max_in_flight`` at a time."""
        return list(await asyncio.gather(*(self._settled(message) for message in messages)))

    async def _settled(self, message: Outbound) -> BaseException | None:
        try:
            await self._call(message)
        except (EndpointError, rosmsg.MessageError) as error:
            return error if isinstance(error, EndpointError) else MessageRejected(f"{self._where}: {error}")
        return None

    def _request(self, message: Outbound) -> Any:
        mapped = message.fields is not message.canonical
        try:
            return rosmsg.from_dict(self._cls.Request, message.fields if message.fields is not None else {},
                                    null_as_nan=not mapped)
        except rosmsg.NullValue as exc:
            raise MessageRejected(f"{self._where}: {exc}", stage="sink mapping") from exc
        except rosmsg.MessageError as exc:
            raise MessageRejected(f"{self._where}: {exc}") from exc

    async def _call(self, message: Outbound) -> None:
        request = self._request(message)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._timeout
        async with self._slots:
            await self._available(deadline)
            answered: asyncio.Future[Any] = loop.create_future()
            future = self._client.call_async(request)
            future.add_done_callback(lambda done: loop.call_soon_threadsafe(_settle, answered, done))
            try:
                response = await asyncio.wait_for(answered, max(0.0, deadline - loop.time()))
            except asyncio.TimeoutError:
                self._client.remove_pending_request(future)
                raise MessageRejected(f"{self._where}: no response within {self._timeout:g} s") from None
        if message.reply is not None:
            await message.reply("result", rosmsg.to_dict(response))

    async def _available(self, deadline: float) -> None:
        """Return once a server is matched; MessageRejected at ``deadline``."""
        client, loop = self._client, asyncio.get_running_loop()
        backoff = Backoff(_AVAILABLE_FIRST, _AVAILABLE_MAX)
        while not client.service_is_ready():
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise MessageRejected(f"{self._where}: not available (no server within {self._timeout:g} s)")
            await asyncio.sleep(min(remaining, backoff.next()))

    async def close(self) -> None:
        try:
            self._calls.node.destroy_client(self._client)
        except Exception:  # the node is gone with its connection
            pass


def _settle(answered: asyncio.Future[Any], done: Any) -> None:
    if answered.done():
        return  # timed out meanwhile: the late response is dropped
    error = done.exception()
    if error is not None:
        answered.set_exception(EndpointError(str(error)))
    else:
        answered.set_result(done.result())
