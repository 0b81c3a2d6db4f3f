"""The conformance suite: every protocol of the registry (engine/endpoints/__init__.py
``PROTOCOLS``) through the same cases, each protocol giving only its harness
(harness.py; harnesses/<protocol>.py), as Redpanda Connect's
``internal/integration/stream_test_definitions.go`` runs one set of stream tests over every
connector.

Cases: open and close; a message through the source and the sink with metadata; a bad payload
dead-lettered once; health following the broker or peer; a reload that keeps the connection;
at-least-once under an engine ``kill -9``; a subscription the broker drops taken up again. A
protocol that does not promise a case is left out of it by its harness, with the reason (never
skipped); a protocol without a harness fails every case, naming itself.

The engine runs in the test's process (engine.running.runtime.Engine), except under ``kill -9``
(a child, tests/support/engine_process.py); the health case serves the engine's admin endpoint
(engine/ops/admin.py ``AdminServer``) on a loopback port and reads ``/healthz`` over HTTP.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any, Awaitable, Callable

import pytest

from engine.endpoints import PROTOCOLS
from engine.ops.admin import AdminServer
from engine.running.runtime import Engine
from tests.endpoints.conformance.harness import CASES, Harness, Seen, harness_class
from tests.support.engine_process import EngineProcess
from tests.support.repo import REPO
from tests.support.waiting import probe_until, wait_for

pytestmark = pytest.mark.timeout(180)
"""A case's scenario has SCENARIO_S; with its peer's start (a private RabbitMQ node: up to 90 s on
a loaded machine) it ends well within this, and a hang is named sooner than the default 300 s."""

CONNECTION = "peer"
SCENARIO_S = 90.0
"""Each case's own deadline (the per-test timeout, 300 s, is the backstop)."""
STOP_S = 15.0
"""An engine stop (drain 10 s at most, then the connections close) must end within this."""

ROUTES = """
connections:
  {connection}: {connection_yaml}
routes:
  - name: {route}
    source: {{{protocol}: {{connection: {connection}, {source}}}}}
    mapping: "{mapping}"
    schema: raw_json
    sink:
      {protocol}: {{connection: {connection}, {sink}}}
{sink_mapping}"""


def taking_part(case: str) -> list[str]:
    """The registry's protocols in ``case``: all but those whose harness excludes it (one without
    a harness takes part, and fails naming itself)."""
    return [protocol for protocol in PROTOCOLS
            if (cls := harness_class(protocol)) is None or case not in cls.EXCLUDED]


def route_name(harness: Harness) -> str:
    return f"conformance-{harness.tag}"


def write_routes(harness: Harness, case: str, edition: int = 1) -> Path:
    routes = harness.tmp_path / "routes"
    routes.mkdir(exist_ok=True)
    (routes / "r.yaml").write_text(ROUTES.format(
        connection=CONNECTION, connection_yaml=harness.connection(case), route=route_name(harness),
        protocol=harness.PROTOCOL, source=harness.source(), sink=harness.sink(),
        mapping=quoted(harness.mapping(edition)),
        sink_mapping=f'      mapping: "{quoted(sink_mapping)}"\n' if (sink_mapping := harness.sink_mapping()) else ""))
    return routes


def quoted(expression: str) -> str:
    """``expression`` inside a YAML double-quoted string."""
    return expression.replace("\\", "\\\\").replace('"', '\\"')


def make_harness(protocol: str, tmp_path: Path) -> Harness:
    cls = harness_class(protocol)
    assert cls is not None, (f"protocol {protocol!r} of the registry has no conformance harness: add "
                             f"tests/endpoints/conformance/harnesses/{protocol}.py exposing HARNESS")
    return cls("c" + uuid.uuid4().hex[:8], tmp_path)


def run_case(protocol: str, case: str, tmp_path: Path, request: pytest.FixtureRequest,
             scenario: Callable[[Harness], Awaitable[None]]) -> None:
    """Stand up ``protocol``'s peer for ``case``, run ``scenario`` within SCENARIO_S, close the peer."""
    harness = make_harness(protocol, tmp_path)
    fixtures = {name: request.getfixturevalue(name) for name in harness.FIXTURES}

    async def bounded() -> None:
        await harness.open(fixtures, case)
        try:
            await asyncio.wait_for(scenario(harness), SCENARIO_S)
        finally:
            await harness.close()

    asyncio.run(bounded())


async def started(harness: Harness, case: str) -> Engine:
    engine = Engine(write_routes(harness, case), REPO / "schemas")
    await engine.start()
    return engine


def peer_health(engine: Engine) -> dict[str, Any]:
    return engine.status()["connections"].get(CONNECTION, {})


async def healthz(admin: AdminServer) -> tuple[int, dict[str, Any]]:
    """``GET /healthz``: its status code and document."""
    import aiohttp

    async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=10)) as client:
        async with client.get(f"http://127.0.0.1:{admin.port}/healthz") as response:
            return response.status, await response.json()


async def until_healthy(engine: Engine, healthy: bool, admin: AdminServer | None = None,
                        timeout: float = 30.0) -> dict[str, Any]:
    """Until the connection's health in the status (and in ``/healthz``, given the admin
    endpoint: 200 or 503 naming it) is ``healthy``; returns the status's health."""
    seen: dict[str, Any] = {}

    async def reached() -> dict[str, Any] | None:
        health = peer_health(engine)
        code, document = await healthz(admin) if admin is not None else (None, {})
        seen.update(health=health, code=code, document=document)
        served = admin is None or ((code == 200) is healthy and (CONNECTION in document["down"]) is not healthy)
        return health if health.get("healthy") is healthy and served else None

    return await wait_for(reached, timeout, f"connection {CONNECTION} healthy={healthy}",
                          lambda: f"status {seen.get('health')}, /healthz {seen.get('code')} {seen.get('document')}")


async def until_seen(harness: Harness, condition: Callable[[list[Seen]], bool], what: str, timeout: float = 30.0) -> list[Seen]:
    await wait_for(lambda: condition(harness.seen()), timeout, what, lambda: harness.seen()[-5:])
    return harness.seen()


async def carried(harness: Harness, robot: int, seq: int, edition: int, timeout: float = 30.0) -> None:
    """Inject ``seq`` for ``robot`` until it arrives carried by ``edition`` (once a subscription
    is taken anew — a reload, a broker back — a message injected before it is in place is not
    carried by protocols that do not hold messages for absent subscribers: injected again
    every second, seq stays the same so the copies are recognised)."""
    await probe_until(lambda: any(s.robot == robot and s.seq == seq and s.edition == edition for s in harness.seen()),
                      lambda: harness.inject(robot, seq), timeout, f"seq {seq} for robot {robot} carried by edition {edition}",
                      every=1.0, detail=lambda: harness.seen()[-5:])


# ------------------------------------------------------------------------------ the registry


@pytest.mark.fast
def test_every_protocol_of_the_registry_has_a_harness() -> None:
    """A protocol added to engine/endpoints/__init__.py is under the suite without another line:
    this fails naming each protocol that has no harness module yet."""
    missing = [protocol for protocol in PROTOCOLS if harness_class(protocol) is None]
    assert not missing, f"no conformance harness for {missing}: add tests/endpoints/conformance/harnesses/<protocol>.py"


@pytest.mark.fast
def test_every_exclusion_names_a_case_and_gives_its_reason() -> None:
    """An exclusion is explicit: a known case and a reason of some words (never an empty skip)."""
    for protocol in PROTOCOLS:
        cls = harness_class(protocol)
        assert cls is not None and cls.PROTOCOL == protocol, protocol
        for case, reason in cls.EXCLUDED.items():
            assert case in CASES, f"{protocol}: unknown case {case!r} (known: {CASES})"
            assert len(reason.split()) >= 6, f"{protocol} excludes {case} without a reason: {reason!r}"


# ------------------------------------------------------------------------------ the cases


@pytest.mark.parametrize("protocol", taking_part("open_close"))
def test_open_and_close(protocol: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """The engine starts, its connection is healthy and carries one message, and it stops within
    STOP_S with its routes' sources stopped and its connections closed."""

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "open_close")
        try:
            await until_healthy(engine, True)
            await harness.ready()
            await harness.inject(1, 0)
            await until_seen(harness, lambda seen: len(seen) == 1, "one message")
        finally:
            began = time.monotonic()
            await asyncio.wait_for(engine.stop(), STOP_S)
            stopped_in = time.monotonic() - began
        assert engine.connections.items() == [], "the connections are closed once the engine stopped"
        assert stopped_in < STOP_S

    run_case(protocol, "open_close", tmp_path, request, scenario)


@pytest.mark.parametrize("protocol", taking_part("through"))
def test_a_message_goes_through_source_and_sink_with_metadata(protocol: str, tmp_path: Path,
                                                              request: pytest.FixtureRequest) -> None:
    """20 messages for two robots arrive once each, in order per robot, each at the sink address
    rendered from the ``origin`` the mapping read from the source's metadata."""
    sent = [(1 + seq % 2, seq) for seq in range(20)]

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "through")
        try:
            await harness.ready()
            for robot, seq in sent:
                await harness.inject(robot, seq)
            seen = await until_seen(harness, lambda seen: len(seen) >= len(sent), f"{len(sent)} messages")
            await wait_for(lambda: engine.status()["routes"][route_name(harness)]["delivered"] == len(sent), 10,
                           "the route's delivered count", lambda: engine.status()["routes"][route_name(harness)])
        finally:
            await engine.stop()
        assert sorted((s.robot, s.seq) for s in seen) == sorted(sent), "each message once"
        for robot in (1, 2):
            assert [s.seq for s in seen if s.robot == robot] == [seq for r, seq in sent if r == robot], "in order per robot"
        assert all(s.origin == harness.expected_origin(s.robot) and s.edition == 1 for s in seen), seen

    run_case(protocol, "through", tmp_path, request, scenario)


@pytest.mark.parametrize("protocol", taking_part("dead_letter"))
def test_a_bad_payload_is_dead_lettered_once(protocol: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """A bad payload is dead-lettered once at the harness's stage, and the messages after it flow."""

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "dead_letter")
        route = route_name(harness)
        try:
            await harness.ready()
            await harness.inject_bad(1)
            await harness.inject(1, 0)
            await until_seen(harness, lambda seen: any(s.seq == 0 for s in seen), "the message after the bad one")
            await wait_for(lambda: engine.status()["routes"][route]["dead_lettered"] == {harness.BAD_STAGE: 1}, 10,
                           f"one dead letter at stage {harness.BAD_STAGE}", lambda: engine.status()["routes"][route])
            await harness.inject(1, 1)
            await until_seen(harness, lambda seen: any(s.seq == 1 for s in seen), "a second message")
            status = engine.status()["routes"][route]
        finally:
            await engine.stop()
        assert status["dead_lettered"] == {harness.BAD_STAGE: 1}, f"dead-lettered once: {status}"
        assert [s.seq for s in harness.seen()] == [0, 1]

    run_case(protocol, "dead_letter", tmp_path, request, scenario)


@pytest.mark.parametrize("protocol", taking_part("health"))
def test_health_follows_the_broker_or_peer(protocol: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """Healthy with its peer; the peer gone, unhealthy in the status and in /healthz, with a reason;
    the peer back, healthy again and carrying."""

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "health")
        admin = AdminServer(engine, "127.0.0.1", 0)
        await admin.start()
        try:
            await until_healthy(engine, True, admin)
            await harness.peer_down()
            down = await until_healthy(engine, False, admin)
            await harness.peer_back()
            await until_healthy(engine, True, admin, timeout=45)
            await carried(harness, 1, 0, 1)
        finally:
            await admin.stop()
            await engine.stop()
        assert down.get("state") != "up" and (down.get("last_error") or down.get("state")), down

    run_case(protocol, "health", tmp_path, request, scenario)


@pytest.mark.parametrize("protocol", taking_part("reload"))
def test_a_reload_keeps_the_connection(protocol: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """A route edit (its mapping) is applied by a reload on the connection already open: the
    connection object and its session with the peer are the ones from before."""

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "reload")
        try:
            await harness.ready()
            await carried(harness, 1, 0, 1)
            (_, before), = engine.connections.items()
            session = harness.session_of(before)
            write_routes(harness, "reload", edition=2)
            assert await engine.reload(), engine.status()["reloads"]
            await carried(harness, 1, 1, 2)
            (_, after), = engine.connections.items()
            assert after is before, "the reload opened another connection"
            assert harness.session_of(after) is session, "the reload opened another session with the peer"
            assert engine.generation == 2 and peer_health(engine).get("healthy") is True
        finally:
            await engine.stop()

    run_case(protocol, "reload", tmp_path, request, scenario)


KILL9_MESSAGES = 400
KILL9_AFTER = 100


@pytest.mark.parametrize("protocol", taking_part("kill9"))
def test_at_least_once_under_an_engine_kill_9(protocol: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    """Messages injected steadily while the engine (a child process) is killed with -9 and started
    again: every one arrives (duplicates allowed, counted), none lost."""

    async def scenario(harness: Harness) -> None:
        routes = write_routes(harness, "kill9")
        engines: list[EngineProcess] = []

        def start() -> EngineProcess:
            engine = EngineProcess(routes, tmp_path / f"status-{len(engines)}.json", {})
            engines.append(engine)
            engine.wait_started()
            return engine

        try:
            first = await asyncio.to_thread(start)
            await harness.ready()

            async def inject_all() -> None:
                for seq in range(KILL9_MESSAGES):
                    await harness.inject(1 + seq % 2, seq)
                    await asyncio.sleep(0.005)  # pacing: a steady stream, not a wait for something

            injecting = asyncio.create_task(inject_all())
            await until_seen(harness, lambda seen: len(seen) >= KILL9_AFTER, f"{KILL9_AFTER} messages before the kill")
            os.killpg(first.process.pid, signal.SIGKILL)
            await asyncio.to_thread(first.process.wait, 30)
            killed_at = len({s.seq for s in harness.seen()})
            await asyncio.to_thread(start)
            await injecting
            await until_seen(harness, lambda seen: len({s.seq for s in seen}) == KILL9_MESSAGES,
                             f"all {KILL9_MESSAGES} messages", timeout=60)
        finally:
            for engine in engines:
                if engine.process.poll() is None:
                    engine.stop()
        counts = Counter(s.seq for s in harness.seen())
        print(f"\n{protocol} kill -9: sent={KILL9_MESSAGES} delivered={len(counts)} "
              f"duplicates={sum(counts.values()) - len(counts)} killed_after={killed_at}")
        assert killed_at < KILL9_MESSAGES, "the kill came after every message was carried: nothing was tested"
        assert set(counts) == set(range(KILL9_MESSAGES)), "none lost"

    run_case(protocol, "kill9", tmp_path, request, scenario)


@pytest.mark.parametrize("protocol", taking_part("cancel"))
def test_a_subscription_the_broker_drops_is_taken_up_again(protocol: str, tmp_path: Path,
                                                           request: pytest.FixtureRequest) -> None:
    """The broker drops the source's subscription (a restarted broker that forgot the session, a
    deleted queue); the route subscribes again (declaring again what it declares) and carries
    again, healthy in the status and /healthz, without a restart or a reload. (How the status
    says why meanwhile is protocol-specific: tests/endpoints/amqp/test_amqp_cancelled.py.)"""

    async def scenario(harness: Harness) -> None:
        engine = await started(harness, "cancel")
        admin = AdminServer(engine, "127.0.0.1", 0)
        await admin.start()
        try:
            await harness.ready()
            await carried(harness, 1, 0, 1)
            await harness.cancel_subscription()
            await carried(harness, 1, 1, 1, timeout=45)
            await until_healthy(engine, True, admin)
            route = engine.status()["routes"][route_name(harness)]
        finally:
            await admin.stop()
            await engine.stop()
        assert route["generation"] == 1, "taken up again by the running route, not by a reload"
        assert route.get("source_degraded") is None, f"the route still says it is degraded: {route}"

    run_case(protocol, "cancel", tmp_path, request, scenario)
