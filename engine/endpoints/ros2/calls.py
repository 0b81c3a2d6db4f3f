"""ROS 2 calls: the engine as a client of a ROS 2 service or action (issue 19), sinks of the ros2 transport.

    sink: {ros2: {service: /robot1/set_spray, type: std_srvs/srv/SetBool, timeout: 5, max_in_flight: 10}}

Each message is one request (its sink mapping's output, or the canonical message, built as the
service's ``Request`` by the rules of engine/endpoints/rosmsg.py); the response, in rosbridge
JSON, is the call's ``result`` reply (engine/running/replies.py). A message is accepted once its
response arrived, so the route's source acknowledges a call only once it was answered.

Failures are permanent (:class:`MessageRejected`, so the caller's ``error`` reply comes within
``timeout`` and the request is dead-lettered): no server within ``timeout`` ("not available"),
no response within ``timeout`` (a response up to ``late_window`` later is dropped and counted
``late``; after that rclpy has forgotten the request), a
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
import json
import logging
import re
import threading
from typing import Any, Callable, Mapping, Sequence

from rclpy.action import ActionClient
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future as RclpyFuture

from engine.common.backoff import Backoff
from engine.endpoints.base import Deliver, EndpointError, Inbound, Inbox, MessageRejected, Outbound, Sink, Source, late_window
from engine.endpoints.ros2 import rosmsg
from engine.endpoints.pump import pump

log = logging.getLogger("engine.ros2")

DEFAULT_CALL_TIMEOUT = 10.0
DEFAULT_MAX_IN_FLIGHT = 10
"""The depth of ROS 2's default service QoS: see the module docstring."""
_SERVICE_TYPE = re.compile(r"^([a-z][a-z0-9_]*)/srv/([A-Z][A-Za-z0-9]*)$")
_ACTION_TYPE = re.compile(r"^([a-z][a-z0-9_]*)/action/([A-Z][A-Za-z0-9]*)$")
GOAL_STATUS = {4: "SUCCEEDED", 5: "CANCELED", 6: "ABORTED"}
"""action_msgs/msg/GoalStatus: the terminal states a result reply names."""
_AVAILABLE_FIRST, _AVAILABLE_MAX = 0.01, 0.25
"""Backoff between looks for a server that is not there yet (a look costs microseconds)."""


def resolve_service(name: Any) -> rosmsg.RosClass:
    """The service class of ``pkg/srv/Type``; MessageError if it is not installed."""
    return _resolve_interface(name, "srv", "Request")


def _resolve_interface(name: Any, kind: str, part: str) -> rosmsg.RosClass:
    """The ``pkg/<kind>/Type`` interface class (it has ``part``: Request, Goal); MessageError
    naming it when the name is malformed or the package is not installed."""
    pattern = _SERVICE_TYPE if kind == "srv" else _ACTION_TYPE
    match = pattern.match(name.strip()) if isinstance(name, str) else None
    if match is None:
        raise rosmsg.MessageError(f"{'service' if kind == 'srv' else 'action'} type {name!r} is not of the form pkg/{kind}/Type")
    pkg, cls_name = match.groups()
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
    except ImportError:
        module = None
    cls = getattr(module, cls_name, None)
    if not isinstance(cls, type) or not hasattr(cls, part):
        raise rosmsg.MessageError(f"{'service' if kind == 'srv' else 'action'} type '{pkg}/{kind}/{cls_name}' is not installed")
    return cls


def service_qos(max_in_flight: int) -> QoSProfile:
    """The services' default QoS (reliable, volatile) with a depth for ``max_in_flight`` calls."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, max_in_flight),
                      reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def resolve_action(name: Any) -> rosmsg.RosClass:
    """The action class of ``pkg/action/Type``; MessageError if it is not installed."""
    return _resolve_interface(name, "action", "Goal")


class CallNode:
    """The node of a connection's calls and the executor thread that serves its responses."""

    def __init__(self, context: Context, node_name: str, namespace: str) -> None:
        self.node = Node(f"{node_name}_calls", namespace=namespace, context=context, start_parameter_services=False,
                         parameter_overrides=[Parameter("start_type_description_service", value=False)])
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._closing = False
        self._thread = threading.Thread(target=self._spin, name=f"ros2-calls-{node_name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while True:
            try:
                self.executor.spin()
                return
            except NoResponse:
                continue  # a served call ended without a response (ServiceSource)
            except ExternalShutdownException:
                return
            except Exception as exc:
                if self._closing or not self.node.context.ok():
                    return
                # an entity destroyed while the executor held it (a route's service or client
                # removed by a reload): rclpy raises it from spin; the other calls go on
                log.warning("ros2 calls node %r: %s", self.node.get_name(), exc)

    def submit(self, work: Any) -> asyncio.Future[Any]:
        """Run ``work()`` on the executor's thread (rclpy's action client registers a goal's
        future only after sending it, so a response taken by the executor in between would be
        ignored: sending from the executor's own thread closes that window); its return value,
        or its error, comes back as an asyncio future."""
        loop = asyncio.get_running_loop()
        done: asyncio.Future[Any] = loop.create_future()

        def run() -> None:
            try:
                result = work()
            except Exception as exc:
                loop.call_soon_threadsafe(_fail, done, exc)
            else:
                loop.call_soon_threadsafe(_succeed, done, result)

        self.executor.create_task(run)
        return done

    def close(self) -> None:
        """Blocking (the connection runs it in a thread): stop the executor, then the node."""
        self._closing = True
        self.executor.shutdown(timeout_sec=2.0)
        self._thread.join(5.0)
        self.node.destroy_node()


class _CallSink(Sink):
    """A sink whose messages are calls: a batch's calls run together (each bounded by its own
    timeout), and each settles on its own, as an error or None (``_settled``)."""

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        return list(await asyncio.gather(*(self._settled(message) for message in messages)))

    async def _settled(self, message: Outbound) -> BaseException | None:
        raise NotImplementedError


class ServiceSink(_CallSink):
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
        self._forgetting: dict[Any, asyncio.TimerHandle] = {}
        """Timed-out calls still pending in rclpy, and when they are forgotten (``_forget_later``)."""
        try:
            self._client = calls.node.create_client(self._cls, service, qos_profile=service_qos(max_in_flight))
        except Exception as exc:
            raise EndpointError(f"{self._where}: cannot create the client: {exc}") from exc

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
            late = message.reply.late if message.reply is not None else None
            future = self._client.call_async(request)
            future.add_done_callback(lambda done: loop.call_soon_threadsafe(_settle, answered, done, late))
            try:
                response = await asyncio.wait_for(answered, max(0.0, deadline - loop.time()))
            except asyncio.TimeoutError:
                self._forget_later(future)
                raise MessageRejected(f"{self._where}: no response within {self._timeout:g} s") from None
        if message.reply is not None:
            await message.reply("result", rosmsg.to_dict(response))

    def _forget_later(self, future: Any) -> None:
        """A call that timed out stays pending in rclpy for :func:`late_window`, so a response
        in that window is counted ``late`` (rclpy drops one for a forgotten request without a
        trace); then it is forgotten. Bounded: a call holds its slot for ``timeout`` before it
        times out, so at most ``max_in_flight`` x (window / timeout + 1) calls wait to be forgotten."""
        handle = asyncio.get_running_loop().call_later(late_window(self._timeout), self._forget, future)
        self._forgetting[future] = handle

    def _forget(self, future: Any) -> None:
        self._forgetting.pop(future, None)
        self._client.remove_pending_request(future)

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
        for handle in self._forgetting.values():
            handle.cancel()
        self._forgetting.clear()
        try:
            self._calls.node.destroy_client(self._client)
        except Exception:  # the node is gone with its connection
            pass


def bridged(future: Any) -> asyncio.Future[Any]:
    """An rclpy future as an asyncio future of the running loop."""
    loop = asyncio.get_running_loop()
    answered: asyncio.Future[Any] = loop.create_future()
    future.add_done_callback(lambda done: loop.call_soon_threadsafe(_settle, answered, done))
    return answered


def _succeed(future: asyncio.Future[Any], result: Any) -> None:
    if not future.done():
        future.set_result(result)


def _fail(future: asyncio.Future[Any], error: BaseException) -> None:
    if not future.done():
        future.set_exception(EndpointError(str(error)))


class ActionSink(_CallSink):
    """Sends one goal per message (see the module docstring of the reply kinds).

    A message is accepted once the server accepted or rejected its goal (replies ``accepted``
    or ``rejected``), so the route's source moves on and a cancel can follow on the same route;
    the goal is then followed in a task of its own: each feedback is a ``feedback`` reply
    ``{kind, feedback}`` (rosbridge JSON), the end a ``result`` reply ``{kind, status, result}``
    with ``status`` SUCCEEDED, ABORTED or CANCELED. ``timeout`` bounds the whole goal, from
    sending to result: then the goal is canceled on the server and the caller gets an ``error``
    reply (after acceptance it is no dead letter: the request was settled). A message whose
    source marks it a cancel (``meta["cancel"]``: the AMQP header ``x-rabbitros-cancel``
    naming the goal's correlation id) cancels that goal; the goal's ``result`` with CANCELED
    goes to the goal's own caller. Closing the sink (a reload, the engine stopping) cancels the
    goals it follows and tells their callers with an ``error`` reply."""

    cancels = True

    def __init__(self, calls: CallNode, route: str, action: str, type_name: str, timeout: float) -> None:
        self._where = f"route {route!r}, ros2 action {action!r}"
        try:
            self._cls = resolve_action(type_name)
        except rosmsg.MessageError as exc:
            raise EndpointError(f"{self._where}: {exc}") from None
        self._calls = calls
        self._timeout = timeout
        self._goals: dict[str, Any] = {}
        """Goal handles in flight by the correlation id of their request (what a cancel names)."""
        self._following: set[asyncio.Task[None]] = set()
        try:
            self._client = ActionClient(calls.node, self._cls, action)
        except Exception as exc:
            raise EndpointError(f"{self._where}: cannot create the client: {exc}") from exc

    async def _settled(self, message: Outbound) -> BaseException | None:
        try:
            cancel = message.meta.get("cancel")
            if cancel is not None:
                await self._cancel(str(cancel))
            else:
                await self._send_goal(message)
        except EndpointError as error:
            return error
        return None

    def _goal(self, message: Outbound) -> Any:
        mapped = message.fields is not message.canonical
        try:
            return rosmsg.from_dict(self._cls.Goal, message.fields if message.fields is not None else {}, null_as_nan=not mapped)
        except rosmsg.NullValue as exc:
            raise MessageRejected(f"{self._where}: {exc}", stage="sink mapping") from exc
        except rosmsg.MessageError as exc:
            raise MessageRejected(f"{self._where}: {exc}") from exc

    async def _send_goal(self, message: Outbound) -> None:
        goal, reply = self._goal(message), message.reply
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._timeout
        backoff = Backoff(_AVAILABLE_FIRST, _AVAILABLE_MAX)
        while not self._client.server_is_ready():
            if loop.time() >= deadline:
                raise MessageRejected(f"{self._where}: not available (no server within {self._timeout:g} s)")
            await asyncio.sleep(min(deadline - loop.time(), backoff.next()))
        events: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()

        def feedback(msg: Any) -> None:  # the executor's thread
            loop.call_soon_threadsafe(events.put_nowait, ("feedback", rosmsg.to_dict(msg.feedback)))

        try:
            sent = await asyncio.wait_for(self._calls.submit(lambda: self._client.send_goal_async(goal, feedback)),
                                          max(0.0, deadline - loop.time()))
            handle = await asyncio.wait_for(bridged(sent), max(0.0, deadline - loop.time()))
        except asyncio.TimeoutError:
            raise MessageRejected(f"{self._where}: the goal was not answered within {self._timeout:g} s") from None
        if not handle.accepted:
            if reply is not None:
                await reply("rejected", {"kind": "rejected"})
            return
        if reply is not None:
            await reply("accepted", {"kind": "accepted"})
        correlation_id = message.meta.get("correlation_id")
        if correlation_id:
            self._goals[str(correlation_id)] = handle
        task = asyncio.create_task(self._follow(handle, events, reply, deadline, correlation_id))
        self._following.add(task)
        task.add_done_callback(self._following.discard)

    async def _follow(self, handle: Any, events: asyncio.Queue[tuple[str, Any]], reply: Any, deadline: float,
                      correlation_id: Any) -> None:
        """Feedback and result, in the order the executor took them, until the result or the deadline."""
        loop = asyncio.get_running_loop()
        try:
            requested = await self._calls.submit(handle.get_result_async)
            requested.add_done_callback(lambda done: loop.call_soon_threadsafe(events.put_nowait, ("result", done)))
            while True:
                kind, data = await asyncio.wait_for(events.get(), max(0.0, deadline - loop.time()))
                if kind == "feedback":
                    if reply is not None:
                        await reply("feedback", {"kind": "feedback", "feedback": data})
                    continue
                if data.exception() is not None:
                    raise EndpointError(str(data.exception()))
                answer = data.result()
                if reply is not None:
                    await reply("result", {"kind": "result", "status": GOAL_STATUS.get(answer.status, str(answer.status)),
                                           "result": rosmsg.to_dict(answer.result)})
                return
        except (asyncio.TimeoutError, asyncio.CancelledError) as exc:
            if isinstance(exc, asyncio.TimeoutError):
                why = f"goal not done within {self._timeout:g} s; canceled on the server"
            else:
                why = "goal canceled on the server: the route stopped or was reloaded"
            try:
                await asyncio.wait_for(self._calls.submit(handle.cancel_goal_async), 2.0)
            except (asyncio.TimeoutError, EndpointError):
                why += " (the cancel request could not be sent)"
            if reply is not None:
                await reply("error", {"stage": "sink", "error": f"{self._where}: {why}"})
        except EndpointError as exc:
            if reply is not None:
                await reply("error", {"stage": "sink", "error": f"{self._where}: {exc}"})
        finally:
            if correlation_id:
                self._goals.pop(str(correlation_id), None)

    async def _cancel(self, correlation_id: str) -> None:
        handle = self._goals.get(correlation_id)
        if handle is None:
            raise MessageRejected(f"{self._where}: no goal in flight for correlation id {correlation_id!r} to cancel")
        requested = await self._calls.submit(handle.cancel_goal_async)
        await asyncio.wait_for(bridged(requested), self._timeout)

    async def close(self) -> None:
        following = list(self._following)
        for task in following:
            task.cancel()
        await asyncio.gather(*following, return_exceptions=True)
        try:
            self._client.destroy()
        except Exception:  # the node is gone with its connection
            pass


def _settle(answered: asyncio.Future[Any], done: Any, late: Callable[[], None] | None = None) -> None:
    if answered.done():  # timed out meanwhile: the late response is dropped, and counted
        if late is not None and done.exception() is None:
            late()
        return
    error = done.exception()
    if error is not None:
        answered.set_exception(EndpointError(str(error)))
    else:
        answered.set_result(done.result())


class NoResponse(Exception):
    """Ends a served call without a response (see :class:`ServiceSource`)."""


class ServiceSource(Source):
    """The engine as a ROS 2 service server backed by the route's sink (an AMQP worker):

        source: {ros2: {service: /robot1/plan, type: pkg/srv/Type}}

    Each call becomes a message (the request in rosbridge JSON) with a ``reply_to`` of its own;
    the sink's answer, shaped by the route's ``reply:`` mapping, is built as the service's
    ``Response`` and sent. ROS 2 services have no error response: an ``error`` reply (the sink
    gave no answer within its timeout, the request failed conversion, the answer does not fit
    the Response) sends nothing, counts the call as failed, and the client's own wait ends it.

    rclpy sends whatever a service callback returns; the only way to send nothing is for the
    callback to fail, which the executor re-raises from ``spin``: the calls thread catches
    exactly :class:`NoResponse` and spins on (:meth:`CallNode._spin`).

    Bound: ``max_in_flight`` calls go to the sink at once, and the service's request queue (its
    QoS depth, keep-last) keeps that many: the executor takes one request per turn of its wait
    set, so a burst from many clients at once waits in that queue, and with ROS 2's default 10
    a burst of more than 10 calls lost some (tests/endpoints/ros2/test_ros2_calls_bounds.py)."""

    def __init__(self, calls: CallNode, route: str, service: str, type_name: str,
                 max_in_flight: int = DEFAULT_MAX_IN_FLIGHT) -> None:
        self._where = f"route {route!r}, ros2 service {service!r}"
        self._max_in_flight = max_in_flight
        try:
            self._cls = resolve_service(type_name)
        except rosmsg.MessageError as exc:
            raise EndpointError(f"{self._where}: {exc}") from None
        self._calls, self._service_name = calls, service
        self._service: Any = None
        self._inbox: Inbox[Inbound] = Inbox(1 << 30)
        self._pending: dict[str, Any] = {}
        """rclpy futures of the calls waiting for their answer, by reply_to token."""
        self._serial = 0
        self._loop: asyncio.Task[None] | None = None
        self.counters = {"calls": 0, "answered": 0, "failed": 0}

    async def start(self, deliver: Deliver) -> None:
        self._inbox = deliver.inbox(deliver.overflow)
        running = asyncio.get_running_loop()

        async def serve(request: Any, response: Any) -> Any:  # the executor's thread
            answered = RclpyFuture(executor=self._calls.executor)
            running.call_soon_threadsafe(self._offer, rosmsg.to_dict(request), answered)
            await answered
            if answered.exception() is not None:
                raise NoResponse(str(answered.exception()))
            return answered.result()

        try:
            self._service = self._calls.node.create_service(  # reentrant: many calls wait for their answers at once
                self._cls, self._service_name, serve, qos_profile=service_qos(self._max_in_flight),
                callback_group=ReentrantCallbackGroup())
        except Exception as exc:
            raise EndpointError(f"{self._where}: cannot offer the service: {exc}") from exc
        self._loop = asyncio.create_task(pump(self, deliver, self._where))

    def _offer(self, fields: dict[str, Any], answered: Any) -> None:
        self._serial += 1
        token = f"ros2-call-{self._serial}"
        self._pending[token] = answered
        self.counters["calls"] += 1
        self._inbox.offer(Inbound(fields=fields, meta={"reply_to": token, "correlation_id": token}))
        self._inbox.wake()

    async def read_batch(self) -> list[Inbound]:
        """Calls waiting for the route, at most ``max_in_flight`` at once."""
        return await self._inbox.take(self._max_in_flight)

    def inbounds(self, batch: Sequence[Inbound]) -> Sequence[Inbound]:
        return batch

    async def settle(self, batch: Sequence[Inbound], settled: list[bool]) -> None:
        """A call the route did not settle is answered with nothing (its client's wait ends
        it): it must not wait forever, and a service cannot take a request back."""
        for inbound, done in zip(batch, settled):
            if not done:
                self._end(str(inbound.meta["reply_to"]), None, "not settled (route stopping)")

    async def reply(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        token = str(meta["reply_to"])
        if kind == "error":
            self._end(token, None, body.decode("utf-8", "replace"))
            return
        try:
            response = rosmsg.from_dict(self._cls.Response, json.loads(body))
        except (rosmsg.MessageError, ValueError) as exc:
            self._end(token, None, str(exc))
            raise EndpointError(f"{self._where}: the answer is not a {rosmsg.type_name(self._cls.Response)}: {exc}") from None
        self._end(token, response, None)

    def _end(self, token: str, response: Any, error: str | None) -> None:
        answered = self._pending.pop(token, None)
        if answered is None:
            return
        if error is None:
            self.counters["answered"] += 1
            answered.set_result(response)
        else:
            self.counters["failed"] += 1
            answered.set_exception(NoResponse(error))
        self._calls.executor.wake()  # the waiting callback resumes only when the executor wakes

    def status(self) -> dict[str, Any]:
        return dict(self.counters)

    async def stop(self) -> None:
        if self._service is not None:
            try:
                self._calls.node.destroy_service(self._service)
            except Exception:
                pass
            self._service = None
        self._inbox.close()
        if self._loop is not None:
            await self._loop
        for token in list(self._pending):
            self._end(token, None, "the route stopped")
