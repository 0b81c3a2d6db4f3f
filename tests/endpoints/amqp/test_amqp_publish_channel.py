"""The connection's publish channel outlives a broker's channel error (reviewer's finding on
engine/endpoints/amqp/link.py): another client deletes an exchange one route publishes
to, the broker closes the shared publish channel (404 NOT_FOUND), and every other route of
the connection keeps delivering; the route whose exchange went delivers again once the
engine declared it anew, and nothing is lost on either.

Route ``a``'s loss semantics are made observable with an alternate exchange set by a broker
policy on its exchange's name (a policy outlives the exchange, arguments do not): a message
the broker takes into the re-declared exchange before the test binds its queue again is not
dropped (what AMQP does without a binding, no ``mandatory`` flag) but lands in the
alternate exchange's queue, so every message of ``a`` is either in its output queue or
there, counted, in order."""

from __future__ import annotations

import asyncio
import contextlib
import json
import uuid
from pathlib import Path
from typing import Any, AsyncIterator, Iterator

import aio_pika
import aiormq
import pytest
from aiormq import spec

from engine.endpoints.amqp.broker import LocalBroker
from engine.endpoints.amqp.link import AmqpLink
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, SeqRecorder
from tests.support.waiting import wait_for

AFTER = 100
"""Messages fed to each route once route a's queue is bound to its exchange again."""
DELETE_AFTER = 80
"""The exchange is deleted once both routes delivered this many."""
DEADLINE_S = 60.0

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: a
    source: {{amqp: {{connection: gcs, queue: {in_a}}}}}
    schema: raw_json
    max_attempts: 1000
    sink: {{amqp: {{connection: gcs, exchange: {ex_a}, routing_key: a}}}}
  - name: b
    source: {{amqp: {{connection: gcs, queue: {in_b}}}}}
    schema: raw_json
    max_attempts: 1000
    sink: {{amqp: {{connection: gcs, exchange: {ex_b}, routing_key: b}}}}
"""


@pytest.fixture(scope="module")
def node() -> Iterator[LocalBroker]:
    """A node of its own: the test sets a policy (rabbitmqctl), which the session's node,
    known by its URL only, does not allow."""
    broker = LocalBroker()
    broker.start()
    yield broker
    broker.stop()


class Seqs(Collector):
    """A collector that keeps the ``seq`` of every message, in arrival order."""

    def __init__(self, ack: bool = False, tally: SeqRecorder | None = None) -> None:
        super().__init__(ack, tally)
        self.seqs: list[int] = []

    def received(self, at: float, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self.seqs.append(json.loads(message.body)["seq"])

    def distinct(self) -> list[int]:
        """First arrivals only (a round the broker took but could not confirm before the
        channel closed is published again: at least once)."""
        return list(dict.fromkeys(self.seqs))  # keys keep their first insertion's order


def test_exchange_deleted_behind_the_engine_fails_only_its_route_and_it_recovers(
        node: LocalBroker, tmp_path: Path, schemas_dir: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    names = {"in_a": f"pc-in-a-{tag}", "in_b": f"pc-in-b-{tag}", "ex_a": f"pc-ex-a-{tag}", "ex_b": f"pc-ex-b-{tag}"}
    alternate = f"pc-ae-{tag}"
    node.ctl("set_policy", "--apply-to", "exchanges", f"pc-{tag}", f"^{names['ex_a']}$",
             json.dumps({"alternate-exchange": alternate}))
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "routes.yaml").write_text(ROUTES.format(url=node.url, **names))

    async def scenario() -> dict[str, Any]:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        client = await aio_pika.connect(node.url)
        try:
            channel = await client.channel()
            ae = await channel.declare_exchange(alternate, aio_pika.ExchangeType.FANOUT, durable=True)
            kept = await channel.declare_queue(f"pc-unrouted-{tag}", exclusive=True)
            await kept.bind(ae)
            unrouted = await Seqs.consume(kept)
            queues, outputs = {}, {}
            for key in ("ex_a", "ex_b"):
                exchange = await channel.declare_exchange(names[key], aio_pika.ExchangeType.TOPIC, durable=True)
                queue = queues[key] = await channel.declare_queue(f"pc-out-{key}-{tag}", exclusive=True)
                await queue.bind(exchange, "#")
                outputs[key] = await Seqs.consume(queue)
            out_a, out_b = outputs["ex_a"], outputs["ex_b"]

            def connection() -> dict[str, Any]:
                return engine.status()["connections"]["gcs"]

            rebound = asyncio.Event()

            async def feed() -> int:
                """Both routes' inputs until AFTER messages past the rebinding; how many each."""
                feeder = await client.channel()  # publisher confirms: each message is in its queue
                seq, last = 0, None
                while last is None or seq < last:
                    for queue in (names["in_a"], names["in_b"]):
                        await feeder.default_exchange.publish(aio_pika.Message(json.dumps({"seq": seq}).encode()), queue)
                    seq += 1
                    if last is None and rebound.is_set():
                        last = seq + AFTER
                    await asyncio.sleep(0.003)  # pacing: a steady flow, not one burst
                return seq

            feeding = asyncio.create_task(feed())
            await wait_for(lambda: len(out_a.seqs) >= DELETE_AFTER and len(out_b.seqs) >= DELETE_AFTER, DEADLINE_S,
                        "both routes flowing", lambda: (len(out_a.seqs), len(out_b.seqs)))
            other = await aiormq.connect(node.url)  # another client, not the engine
            try:
                deleting = await other.channel()
                await deleting.exchange_delete(names["ex_a"])
            finally:
                await other.close()
            deleted_at = len(out_b.distinct())
            # route b goes on delivering what is fed meanwhile, whatever happens to route a
            await wait_for(lambda: len(out_b.distinct()) >= deleted_at + 2 * DELETE_AFTER, DEADLINE_S,
                        "route b to go on delivering", lambda: f"{len(out_b.distinct())}, the connection {connection()}")
            await wait_for(lambda: names["ex_a"] in (connection()["last_error"] or ""), DEADLINE_S,
                        "the connection's status to name the deleted exchange", connection)
            # route a delivers into the exchange the engine declared again (no binding yet: the
            # alternate exchange keeps what the broker would drop), then into its queue again
            await wait_for(lambda: bool(unrouted.seqs), DEADLINE_S, "route a to publish again",
                        lambda: (len(out_a.seqs), connection()))
            await queues["ex_a"].bind(names["ex_a"], "#")
            rebound.set()
            n = await feeding
            await wait_for(lambda: len(out_b.distinct()) >= n, DEADLINE_S, "route b to deliver every message",
                        lambda: f"{len(out_b.distinct())} of {n}, the connection {connection()}")
            await wait_for(lambda: len(set(out_a.seqs) | set(unrouted.seqs)) >= n, DEADLINE_S,
                        "every message of route a", lambda: (len(set(out_a.seqs) | set(unrouted.seqs)), connection()))
            status = engine.status()
            return {"n": n, "a": out_a.seqs, "a_distinct": out_a.distinct(), "unrouted": unrouted.distinct(),
                    "b": out_b.seqs, "b_distinct": out_b.distinct(), "deleted_at": deleted_at,
                    "connection": status["connections"]["gcs"],
                    "dead": {name: status["routes"][name]["dead_lettered"] for name in ("a", "b")}}
        finally:
            await client.close()
            await engine.stop()

    result = asyncio.run(scenario())
    print({key: value for key, value in result.items() if key not in ("a", "b", "a_distinct", "b_distinct", "unrouted")},
          "duplicates a/b:", len(result["a"]) - len(result["a_distinct"]), len(result["b"]) - len(result["b_distinct"]),
          "unrouted:", len(result["unrouted"]))
    N = result["n"]
    assert result["b_distinct"] == list(range(N))  # every message of the other route, in order
    a, unrouted = result["a_distinct"], result["unrouted"]
    assert sorted(set(a) | set(unrouted)) == list(range(N))  # none of route a's lost either
    assert a == sorted(a) and unrouted == sorted(unrouted)  # each in order
    before = [s for s in a if s < unrouted[0]]
    after = [s for s in a if s > unrouted[-1]]
    assert before + after == a, (unrouted[0], unrouted[-1], a)  # the outage's messages are one stretch
    assert after, "route a delivers to its queue again once it is bound"
    connection = result["connection"]
    assert connection["state"] == "up" and connection["publish_channel_reopens"] >= 1, connection
    assert "NOT_FOUND" in connection["last_error"] and result["connection"]["last_error"].count(f"'{names['ex_a']}'"), connection
    assert result["dead"] == {"a": {}, "b": {}}, result["dead"]


def _messages(n: int) -> list[tuple[str, bytes, Any]]:
    return [("k", b'{"a": 1}', spec.Basic.Properties(delivery_mode=1)) for _ in range(n)]


@contextlib.asynccontextmanager
async def _connection_and_client(node: LocalBroker, name: str = "c") -> AsyncIterator[tuple[Any, aio_pika.abc.AbstractConnection]]:
    """The engine's AMQP connection ``name`` on ``node``, opened, and another client beside it."""
    from engine.endpoints.amqp.transport import TRANSPORT

    connection = TRANSPORT.connect(name, {"url": node.url})
    await connection.open()
    client = await aio_pika.connect(node.url)
    try:
        yield connection, client
    finally:
        await client.close()
        await connection.close()


def test_publish_channel_closed_under_concurrent_rounds_is_reopened(node: LocalBroker) -> None:
    """The reviewer's reproduction, at the connection's level: thirty publishers without a
    pause, one of them to an exchange another client deleted. Before, aio-pika's restore of
    the robust channel raced the rounds (ChannelNotFoundEntity) and the channel stayed "not
    opened": every publish of the connection failed for good, healthy exchange too, while the
    health said up. Now a publish to the healthy exchange is confirmed again within the
    deadline, the health names the deleted exchange, and no round is left between the
    channel's lock and its frames (the publisher's fast path stays on)."""
    tag = uuid.uuid4().hex[:8]
    healthy, gone = f"pc-ok-{tag}", f"pc-gone-{tag}"

    async def scenario() -> dict[str, Any]:
        async with _connection_and_client(node) as (connection, client):
            assert await connection.publish_batch(healthy, _messages(2)) == [None, None]
            assert await connection.publish_batch(gone, _messages(1)) == [None]
            await (await client.channel()).exchange_delete(gone)
            loop = asyncio.get_running_loop()
            stop = loop.time() + 1.5
            outcomes: dict[str, int] = {}
            states: set[str] = set()

            async def pump(index: int) -> None:
                while loop.time() < stop:
                    for error in await connection.publish_batch(gone if index == 0 else healthy, _messages(1)):
                        kind = "ok" if error is None else type(error).__name__
                        outcomes[kind] = outcomes.get(kind, 0) + 1
                    states.add(connection.health()["state"])
                    await asyncio.sleep(0)

            await asyncio.gather(*(pump(index) for index in range(30)))
            after: list[object] = []

            async def published() -> bool:
                after[:] = await connection.publish_batch(healthy, _messages(1))
                return after == [None]

            await wait_for(published, DEADLINE_S, "a publish to a healthy exchange to succeed",
                           lambda: f"{after}, {connection.health()}")
            publisher = connection._publisher
            return {"outcomes": outcomes, "states": states, "health": connection.health(),
                    "writing": dict(publisher._writing), "gone_again": await connection.publish_batch(gone, _messages(1))}

    result = asyncio.run(scenario())
    print(result)
    health = result["health"]
    assert health["state"] == "up" and health["publish_channel_reopens"] >= 1, health
    assert f"no exchange '{gone}'" in health["last_error"], health
    assert result["outcomes"].get("ok", 0) > 0, result["outcomes"]
    assert result["writing"] == {}, result["writing"]
    assert result["gone_again"] == [None]  # declared again, as at start


def test_a_refused_declaration_fails_only_its_route_and_closes_no_publish_channel(node: LocalBroker) -> None:
    """An exchange of the route's name exists with another type (406 PRECONDITION_FAILED on
    the declaration). The declaration is made on the connection's declare channel, so thirty
    other publishers going on at the same time see no error at all and the publish channel is
    never reopened (on the publish channel the refusal closed it under every route's rounds);
    the refused route's messages fail with the broker's text naming the exchange, and once the
    exchange is fixed they are declared and published again."""
    tag = uuid.uuid4().hex[:8]
    healthy, clash = f"pc-ok-{tag}", f"pc-clash-{tag}"

    async def scenario() -> dict[str, Any]:
        async with _connection_and_client(node) as (connection, client):
            await (await client.channel()).declare_exchange(clash, aio_pika.ExchangeType.FANOUT)
            loop = asyncio.get_running_loop()
            stop = loop.time() + 1.5
            outcomes: dict[str, dict[str, int]] = {"healthy": {}, "clash": {}}
            texts: set[str] = set()

            async def pump(index: int) -> None:
                which = "clash" if index == 0 else "healthy"
                while loop.time() < stop:
                    for error in await connection.publish_batch(clash if index == 0 else healthy, _messages(1)):
                        kind = "ok" if error is None else type(error).__name__
                        outcomes[which][kind] = outcomes[which].get(kind, 0) + 1
                        if error is not None:
                            texts.add(str(error))
                    await asyncio.sleep(0)

            await asyncio.gather(*(pump(index) for index in range(30)))
            health = connection.health()
            await (await client.channel()).exchange_delete(clash)
            return {"outcomes": outcomes, "texts": texts, "health": health,
                    "fixed": await connection.publish_batch(clash, _messages(2))}

    result = asyncio.run(scenario())
    print(result)
    outcomes = result["outcomes"]
    assert set(outcomes["healthy"]) == {"ok"} and outcomes["healthy"]["ok"] > 29, outcomes
    assert "ok" not in outcomes["clash"] and sum(outcomes["clash"].values()) >= 1, outcomes
    assert all("PRECONDITION_FAILED" in text and clash in text for text in result["texts"]), result["texts"]
    assert result["health"]["state"] == "up" and result["health"]["publish_channel_reopens"] == 0, result["health"]
    assert result["fixed"] == [None, None]  # the exchange declared anew on a fresh declare channel


def test_the_calls_channel_closed_by_the_broker_is_opened_again_and_only_once(node: LocalBroker) -> None:
    """The AMQP sink as a caller (engine/endpoints/amqp/calls.py) keeps a channel of its own for
    direct reply-to. A request to an exchange deleted behind the engine makes the broker close
    it (404); the call waiting on it fails at once with a clear, retryable error (its answer can
    no longer come), the next call opens one fresh channel, declares the exchange again and is
    answered, on one calls channel. On the robust channel it had
    before, aio-pika restored the closed channel itself and the call after the exchange was
    back got no answer (``no answer within 3 s``): the caller's replies never came. (The
    calls' timeout is 30 s here, so that "at once" stands far from it on a loaded machine.)"""
    from engine.endpoints.amqp.calls import AmqpCaller
    from engine.endpoints.base import EndpointError

    tag = uuid.uuid4().hex[:8]
    exchange, queue, name = f"pc-calls-{tag}", f"pc-worker-{tag}", f"calls-{tag}"

    def channels() -> int:
        rows = node.ctl("list_channels", "connection", "name", "--no-table-headers", "--quiet").splitlines()
        return sum(1 for row in rows if row.strip())

    async def scenario() -> dict[str, Any]:
        async with _connection_and_client(node, name) as (connection, worker):
            caller = AmqpCaller(connection, f"route {name!r}", timeout=30.0)
            try:
                channel = await worker.channel()

                async def bind() -> None:
                    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
                    await (await channel.declare_queue(queue, exclusive=True)).bind(target, "svc")

                async def answer(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                    await channel.default_exchange.publish(
                        aio_pika.Message(b'{"sum": %d}' % (json.loads(message.body)["a"] + 1), correlation_id=message.correlation_id),
                        message.reply_to or "")

                await bind()
                await (await channel.get_queue(queue)).consume(answer, no_ack=True)

                async def call(a: int) -> Any:
                    return await caller.call(exchange, "topic", True, "svc", b'{"a": %d}' % a, "application/json", None)

                first = await call(1)
                before = await asyncio.to_thread(channels)
                await channel.exchange_delete(exchange)
                loop = asyncio.get_running_loop()
                began = loop.time()
                with pytest.raises(EndpointError) as failed:  # not MessageRejected: the worker never had it
                    await call(2)
                failed_after = loop.time() - began
                await bind()
                again = await call(3)
                return {"first": first, "again": again, "failed": str(failed.value), "failed_kind": type(failed.value).__name__,
                        "failed_after": failed_after, "before": before,
                        "after": await asyncio.to_thread(channels)}
            finally:
                await caller.close()

    result = asyncio.run(scenario())
    print(result)
    assert (result["first"], result["again"]) == ({"sum": 2}, {"sum": 4})
    assert f"route {name!r}: the calls channel closed" in result["failed"] and f"NOT_FOUND - no exchange '{exchange}'" in result["failed"], result["failed"]
    assert result["failed_kind"] == "EndpointError", result  # retried, not MessageRejected (dead-lettered)
    assert result["failed_after"] < 10.0, result  # at the channel's close, not at the call's 30 s timeout
    assert result["after"] == result["before"], result  # one calls channel, not a restored one beside it


async def _proxy(target_port: int) -> tuple[asyncio.Server, dict[str, Any]]:
    """A TCP relay to the node that can stop reading from its clients (``state["paused"]``
    set) and cut them (``state["cut"]()``): a connection whose peer no longer reads fills its
    socket, then aiormq's write queue, then dies."""
    state: dict[str, Any] = {"paused": asyncio.Event(), "clients": []}

    async def relay(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, pause: bool) -> None:
        try:
            while data := await reader.read(65536):
                if pause and state["paused"].is_set():
                    await asyncio.Event().wait()  # reads nothing more: the client's socket fills
                writer.write(data)
                await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    async def serve(client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        broker_reader, broker_writer = await asyncio.open_connection("127.0.0.1", target_port)
        tasks = [asyncio.create_task(relay(client_reader, broker_writer, True)),
                 asyncio.create_task(relay(broker_reader, client_writer, False))]
        state["clients"].append((client_writer, broker_writer, tasks))

    def cut() -> None:
        for client_writer, broker_writer, tasks in state["clients"]:
            client_writer.transport.abort()  # RST: the engine's connection dies
            broker_writer.transport.abort()
            for task in tasks:
                task.cancel()

    state["cut"] = cut
    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    return server, state


def test_a_channel_the_broker_never_opens_fails_within_its_bound(node: LocalBroker) -> None:
    """The publish, declare and calls channels open through engine/endpoints/amqp/channels.py
    within a bound: aio-pika's own ``Channel.initialize(timeout=...)`` ignores its timeout, so a
    Channel.Open the broker never answers (here a relay that stops passing the client's bytes
    on) held the opener, and every route behind its lock, for ever. Bounded at 0.5 s, the open
    fails with ``asyncio.TimeoutError`` within a few seconds (the outer 30 s bound is the old
    code's hang) and the relay is still connected when it does."""
    from engine.endpoints.amqp.channels import open_plain_channel

    async def scenario() -> dict[str, Any]:
        server, relay = await _proxy(node.port)
        port = server.sockets[0].getsockname()[1]
        connection = await aio_pika.connect(f"amqp://guest:guest@127.0.0.1:{port}/")
        loop = asyncio.get_running_loop()
        try:
            relay["paused"].set()
            began = loop.time()
            try:
                await asyncio.wait_for(open_plain_channel(connection, publisher_confirms=False, timeout=0.5), 30)
                failure = "none"
            except asyncio.TimeoutError as exc:
                failure = type(exc).__name__
            return {"failure": failure, "after_s": loop.time() - began, "connection_closed": connection.is_closed}
        finally:
            relay["cut"]()
            server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(connection.close(), 5)

    result = asyncio.run(scenario())
    print(result)
    assert result["failure"] == "TimeoutError", result
    assert result["after_s"] < 5.0, result  # 0.5 s, and the half-open channel's close (1 s at most)
    assert result["connection_closed"] is False, result


def test_a_round_waiting_for_room_in_the_write_queue_ends_with_its_connection(node: LocalBroker) -> None:
    """Reviewer's finding 3: a round of the publisher's slow path waiting in aiormq's full
    write queue when the connection dies was never woken (aiormq stops draining the queue and
    wakes no ``put``), so its routes waited for ever and ``_writing`` never went back to 0,
    which kept the fast path off for the connection's life. The broker here is reached
    through a relay that stops reading (the socket, then the write queue fill) and then
    cuts the connection: every round must end, with a failure, and nothing stays counted."""
    from engine.endpoints.amqp.transport import TRANSPORT

    tag = uuid.uuid4().hex[:8]
    exchange = f"pc-big-{tag}"
    body = b"x" * 60_000

    async def scenario() -> dict[str, Any]:
        server, relay = await _proxy(int(node.url.rsplit(":", 1)[1].split("/")[0]))
        port = server.sockets[0].getsockname()[1]
        # without confirms each round's frame asks aiormq's writer to drain the socket, so a
        # peer that stops reading stops the writer and fills the write queue (with confirms
        # aiormq writes without draining: the transport's buffer grows instead)
        connection = TRANSPORT.connect("c", {"url": f"amqp://guest:guest@127.0.0.1:{port}/", "publisher_confirms": False})
        assert isinstance(connection, AmqpLink), "the amqp transport connects an AmqpLink"
        await connection.open()
        try:
            assert await connection.publish_batch(exchange, [("k", b"{}", spec.Basic.Properties())]) == [None]
            publisher = connection._publisher
            assert publisher is not None, "an open link has its publisher"
            relay["paused"].set()
            loop = asyncio.get_running_loop()
            publishing: list[asyncio.Task[list[BaseException | None]]] = []
            deadline = loop.time() + DEADLINE_S
            while not publisher._writing:  # until a round waits for room in the write queue
                assert loop.time() < deadline and len(publishing) < 5000, f"the write queue never filled ({len(publishing)} rounds)"
                publishing.append(asyncio.create_task(
                    connection.publish_batch(exchange, [("k", body, spec.Basic.Properties())])))
                await asyncio.sleep(0)
            relay["cut"]()
            server.close()  # aio-pika's reconnection attempts are refused from now on
            done, waiting = await asyncio.wait(publishing, timeout=DEADLINE_S)
            return {"rounds": len(publishing), "waiting": len(waiting), "writing": dict(publisher._writing),
                    "failed": sum(1 for task in done if task.result() != [None])}
        finally:
            await connection.close()

    result = asyncio.run(scenario())
    print(result)
    assert result["waiting"] == 0, result  # every route heard back
    assert result["writing"] == {}, result  # the fast path is not kept off
    assert result["failed"] >= 1, result
