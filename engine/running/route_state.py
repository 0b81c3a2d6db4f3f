"""What a route's runner (engine/running/runner.py) and its collaborators share: the engine
that hosts the route, the view of the route the collaborators read, and the messages in flight.

The collaborators (engine/running/dead_lettering.py, engine/running/held.py) read the runner
through :class:`RunningRoute` rather than importing it: a reload swaps the runner's ``spec`` and
``pipeline``, so they must read the current ones, and the import direction stays one way.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, Sequence

from engine.endpoints.base import Connection, Inbound, Outbound
from engine.running.buffer import Buffers
from engine.running.dead_letters import DeadLetters
from engine.running.delivery import Failure
from engine.running.observe import Observers, RouteObserver
from engine.running.pipeline import Pipeline
from engine.running.replies import Replies

if TYPE_CHECKING:
    from engine.language.specs import RouteSpec


class RouteHost(Protocol):
    """What a route needs of the engine that runs it (engine/running/runtime.py's ``Engine``)."""

    observers: Observers
    """Every route's counters, by route name, kept across reloads."""
    buffers: Buffers
    """Every route's buffer, shared across a reload by the runners of a route."""
    dead_letters: DeadLetters | None
    """The engine's one dead-letter destination (set before any route starts)."""

    def is_open(self, connection: Connection) -> bool:
        """Whether ``connection`` was opened (it may be reconnecting now)."""

    async def wait_open(self, connections: Sequence[Connection]) -> None:
        """Return once every one of ``connections`` is open."""


class RunningRoute(Protocol):
    """What the runner's collaborators read of it: always the current spec and pipeline."""

    host: RouteHost
    spec: RouteSpec
    pipeline: Pipeline
    observer: RouteObserver
    replies: Replies

    def sink_can_take(self, pipeline: Pipeline | None = None) -> bool: ...

    def too_old(self, age_ns: int) -> bool: ...


class Converted:
    """A message between its conversion and its settling: converted, so it has an outbound."""

    __slots__ = ("index", "inbound", "outbound", "attempts", "failure", "pipeline", "dedupe_key")

    def __init__(self, index: int, inbound: Inbound, outbound: Outbound, attempts: int,
                 pipeline: Pipeline, failure: Failure | None = None) -> None:
        self.index = index
        self.inbound = inbound
        self.outbound = outbound
        self.attempts = attempts
        self.pipeline = pipeline
        """The pipeline (generation) that converted it, whose sink sends it."""
        self.failure = failure
        """The sink's last transient failure while it is retried."""
        self.dedupe_key: str | None = None
        """Its ``dedupe:`` key, recorded once the sink accepted it."""


class Dead:
    """A message that failed for good, to be stored as a dead letter: its ``failure`` is
    known, its ``outbound`` is None when it failed before or in its conversion; ``canonical``:
    what its mapping gave when its conversion failed after that (the schema, ``when:`` or
    sink-mapping stage), for ``remember ... when: failed``."""

    __slots__ = ("index", "inbound", "outbound", "attempts", "failure", "pipeline", "canonical")

    def __init__(self, index: int, inbound: Inbound, outbound: Outbound | None, attempts: int,
                 pipeline: Pipeline, failure: Failure, canonical: Any = None) -> None:
        self.index = index
        self.inbound = inbound
        self.outbound = outbound
        self.attempts = attempts
        self.pipeline = pipeline
        self.failure = failure
        self.canonical = canonical
