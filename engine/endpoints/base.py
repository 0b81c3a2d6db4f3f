"""The small contract every protocol endpoint implements.

The engine core (routes, pipeline, runtime) knows only these types. Each protocol lives in
one package of this package that subclasses them and translates its library's exceptions
into :class:`EndpointError` at the edge (one table per package), so a new protocol means one
new package and one line in the registry (engine/endpoints/__init__.py). Every question the
core has about a protocol (does its source redeliver, can it keep dead letters or hold a
lease, what does its sink do in a dry run, which fields does its source give) is a method or
class attribute here: the core asks, and never names a protocol.

Delivery contract: a :class:`Source` is started with a :class:`Deliver` (where its route's
messages go, and its bounds) and reads its protocol with the engine's read loop
(engine/endpoints/pump.py): it implements :class:`BatchReader` (read a batch, each item as an
:class:`Inbound`, settle a batch once the route said which of it was settled) and runs
``pump(reader, deliver, where)`` as its task; a source that must settle outside that loop (a
message settled alone in its protocol's callback, a message several routes read at once)
goes through ``pump.settle_batch``, which answers a failure of the engine itself as the loop does.
The route settles a batch with ``deliver.batch(inbounds)`` (``await deliver(inbound)`` for
one), which returns once the messages are *settled*: accepted by the sink or dead-lettered.
A source that queues messages in the engine (a push protocol: ROS 2 takes, MAVLink frames)
asks its route for that queue (:meth:`Deliver.inbox`): the route decides whether it is one
FIFO or, with ``fair:``, one queue per agent; endpoints never import the engine's fairness
or throttle (tests/project/test_import_graph.py checks). Which failures are retried and which are
dead-lettered is decided by the engine (engine/running/delivery.py), never by a source or a
sink: endpoints only raise :class:`EndpointError` (transient) or :class:`MessageRejected`
(permanent) at the edge.
A sink whose destination cannot take messages yet though its connection is up (a ROS 2 topic
no subscriber has matched) says so with :attr:`Sink.ready`; the engine then holds the route's
messages as it does while the connection is down: not sent, not acknowledged to the source,
no delivery attempt spent, the reason (:meth:`Sink.not_ready_reason`) in the status.
A message ``batch`` reports as not settled was not delivered - this happens only while the
route stops, when even the dead letters fail, or when the engine itself failed (then the
whole batch is reported unsettled) - and the source's :meth:`BatchReader.settle` must let it
be redelivered if it can (AMQP: nack with requeue; MQTT: tried again after a wait); a
source that cannot (ROS 2, MAVLink) counts it as dropped.

Reply contract (request/reply, issue 19): a source whose protocol can answer its sender (AMQP:
``reply_to`` and ``correlation_id``) puts a non-empty ``reply_to`` in ``Inbound.meta`` and
implements :meth:`Source.reply`; its transport says so (``Transport.replies``). The runner
gives each converted message an ``Outbound.reply`` (:data:`Reply`); a sink whose destination
answers (a ROS 2 service response, an action's feedback and result, a MAVLink COMMAND_ACK)
calls it with a kind of :data:`REPLY_KINDS` and the answer as plain JSON data. The runner
shapes it by the route's ``reply:`` mapping and schema and hands it to the source that received
the request; a request that fails for good (dead-lettered) gets one ``error`` reply from the
runner, so a caller never waits forever. Sinks never know who asked, or over what protocol.
The meta keys of a call: ``reply_to`` (where replies go: only the source reads it),
``correlation_id`` (the caller's name for the request) and ``cancel`` (this message cancels
the request with that correlation id; see :attr:`Sink.cancels`).

The contract's errors live in engine/endpoints/errors.py and its message values (Inbound,
Outbound, Inbox, Reply) in engine/endpoints/messages.py; this module names them too
(``__all__``), so it stays the one module the contract is imported from.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Iterable, Mapping, Protocol, Sequence, TypeVar

from engine.common.options import OptionError, describe, dotted, option, parse
from engine.common.suggest import closest
from engine.endpoints.errors import (Conflated, EndpointError, ExceptionTable, Expired, MessageRejected, NotSent, Refused, Unroutable,
                                     UnroutableRejected)
from engine.endpoints.messages import FINAL_REPLIES, OVERFLOW_POLICIES, REPLY_KINDS, Inbound, Inbox, Outbound, Reply, StoredLetter, late_window
from engine.endpoints.workers import ConnectionShare, WorkerHints

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = [  # the contract's errors (engine/endpoints/errors.py) and values (engine/endpoints/messages.py), named here too:
    # engine/endpoints/base.py is the one module protocol packages and the core import the contract from
    "Conflated", "EndpointError", "ExceptionTable", "Expired", "MessageRejected", "NotSent", "Refused", "Unroutable", "UnroutableRejected",
    "FINAL_REPLIES", "OVERFLOW_POLICIES", "REPLY_KINDS", "Inbound", "Inbox", "Outbound", "Reply", "StoredLetter", "late_window",
    "DeadLetterReader",
    "Deliver", "BatchReader", "Source", "Sink", "ConnectionMetric", "Connection", "Lease", "ELEMENT", "FieldPath", "FieldProblem",
    "CheckResult", "flat_field_problem", "EndpointOptions", "typed", "typed_or_problem", "Transport", "ConnectionShare",
]


class Deliver(Protocol):
    """What a route gives its source: where messages go, and the source's bounds."""

    @property
    def overflow(self) -> str:
        """One of :data:`OVERFLOW_POLICIES`, for sources that queue messages in memory."""

    @property
    def queue_limit(self) -> int:
        """The most messages a source may hold between its protocol and ``batch``."""

    @property
    def batches_in_flight(self) -> int:
        """How many ``batch`` calls a source that settles in batches (AMQP) may have running at
        once: 1 unless the route's sink declares more (:attr:`Sink.batches_in_flight`) and the
        route neither keeps order (``ordered``) nor holds messages in a buffer. The source still
        settles its batches in the order it took them, each message only once ``batch`` said so."""

    async def __call__(self, inbound: Inbound) -> None:
        """Settle one message; raises :class:`EndpointError` if it could not be settled."""

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        """Settle messages in order; ``result[i]`` says whether ``inbounds[i]`` was settled."""

    def dropped(self, count: int = 1) -> None:
        """Count messages the source dropped (overflow, or not settled and not redeliverable)."""

    def inbox(self, overflow: str) -> Inbox[Inbound]:
        """The queue a push source keeps the route's messages in, bounded by
        :attr:`queue_limit`, dropping by ``overflow`` (the source may narrow the route's
        :attr:`overflow`: a radio link cannot block). With the route's ``fair:`` it is one
        queue per agent (engine/running/fairness.py), which counts per agent what it drops."""


T = TypeVar("T")


class BatchReader(Protocol[T]):
    """What a source tells the engine's read loop (engine/endpoints/pump.py): ``T`` is what the
    source reads from its protocol (a delivered frame with its tag, a decoded message)."""

    async def read_batch(self) -> Sequence[T]:
        """Wait for what is ready and return it (at most the source's bound); an empty batch
        once the source was closed and holds nothing more: the loop ends."""
        ...

    def inbounds(self, batch: Sequence[T]) -> Sequence[Inbound]:
        """The batch as the route takes it, in order (the batch itself where ``T`` is Inbound)."""
        ...

    async def settle(self, batch: Sequence[T], settled: list[bool]) -> None:
        """Tell the protocol: ``settled[i]`` says whether ``batch[i]`` was settled. What is not
        settled the source lets be redelivered if it can (a broker's requeue, tried again
        later), else counts it with :meth:`Deliver.dropped` (or ends the call it carried)."""
        ...


class Source(ABC):
    @abstractmethod
    async def start(self, deliver: Deliver) -> None:
        """Begin receiving; every message goes through ``deliver``."""

    @abstractmethod
    async def stop(self) -> None:
        """Stop taking messages and wait for those in flight; unsettled ones are redelivered."""

    def status(self) -> dict[str, Any]:
        """What the source wants operators to see in the status (counters, problems)."""
        return {}

    def degraded_reason(self) -> str | None:
        """Why the source receives nothing though its connection is up (the broker cancelled
        its subscription: a queue deleted, a revoked subscription) while it takes it up again;
        None while it receives. The route's status (``source_degraded``) and ``/healthz`` show
        it: a route that silently stopped receiving looked healthy."""
        return None

    async def reply(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        """Deliver one reply (kind of :data:`REPLY_KINDS`, JSON ``body``) to the sender of the
        request whose ``Inbound.meta`` was ``meta`` (it holds ``reply_to``); raise
        :class:`EndpointError` if it could not be handed over. Only sources of a transport with
        ``replies`` set are asked."""
        raise EndpointError("this source cannot reply")


class Sink(ABC):
    batches_in_flight: ClassVar[int] = 1
    """How many of a route's batches the sink may be sending at once (see
    :attr:`Deliver.batches_in_flight`). With 1 the source hands the next batch only once the
    sink accepted the previous one, so the sink idles for its own acceptance round trip
    between batches. A sink that takes long to accept but can send more meanwhile declares
    more: the JSON tunnel over a radio (engine/endpoints/mavlink/tunnel/sink.py) accepts a message
    only when the vehicle acknowledged it (a TDM round and more; seconds when a last fragment
    or its acknowledgement was lost), and measured on the emulated SiK radio the radio stood
    idle for that long after every batch (bench/results/2026-11-23/goodput/)."""
    cancels: ClassVar[bool] = False
    """True when the sink understands a cancel: a message whose source marked it
    ``meta["cancel"] = <correlation id of an earlier request>`` reaches the sink unconverted
    (its body is not the request's: ``Outbound.canonical`` and ``fields`` are None) and stops
    that request (a ROS 2 action goal). Other sinks get such a message converted as any other."""
    @abstractmethod
    async def send(self, message: Outbound) -> None:
        """Return once the destination has accepted the message; raise EndpointError if not."""

    @property
    def ready(self) -> bool:
        """False while the destination cannot take messages though the connection is up (a
        ROS 2 topic without a matched subscriber): the engine waits, polling this every
        ``HEALTH_POLL``, instead of sending and spending attempts. Asked before every batch,
        so it must cost no more than a counter read."""
        return True

    def not_ready_reason(self) -> str | None:
        """Why :attr:`ready` is False, for the status (None while ready)."""
        return None

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        """Deliver several messages; ``result[i]`` is None when ``messages[i]`` was accepted,
        else the error (EndpointError or MessageRejected). Sinks whose protocol can pipeline
        (AMQP with publisher confirms) override this; the default sends one by one."""
        results: list[BaseException | None] = []
        for message in messages:
            try:
                await self.send(message)
            except Exception as error:  # classified by the engine's delivery policy
                results.append(error)
            else:
                results.append(None)
        return results

    async def close(self) -> None:  # noqa: B027  # a hook: most sinks hold nothing of their own
        """Release what the sink holds (the connection itself stays open)."""


@dataclass(frozen=True, slots=True)
class ConnectionMetric:
    """One sample a connection gives ``/metrics``: exported as ``rabbitros_<name>`` (a counter
    gets ``_total``) with the label ``connection`` and ``labels``; samples with the same name
    must have the same label keys."""

    name: str
    help: str
    kind: str
    """``counter`` or ``gauge``"""
    value: float
    labels: tuple[tuple[str, str], ...] = ()


class DeadLetterReader(ABC):
    """Dead letters of one store, read and then removed only once they were sent again; what is
    not removed stays where it was when the reader closes."""

    @abstractmethod
    async def read(self, limit: int) -> list[StoredLetter]:
        """At most ``limit`` dead letters, oldest first, none removed."""

    @abstractmethod
    async def remove(self, letters: Sequence[StoredLetter]) -> None:
        """Remove ``letters`` (read by this reader) from the store; raise EndpointError if not."""

    @abstractmethod
    async def close(self) -> None:
        """Give back what was read and not removed."""


class Connection(ABC):
    """One named connection (a broker, a ROS 2 node, a MAVLink link) shared by routes."""

    keeps_dead_letters: ClassVar[bool] = False
    """True where :meth:`dead_letter` stores messages durably (a broker), so the engine can
    use this connection as its dead-letter destination."""

    def __init__(self, name: str, settings: Any) -> None:
        self.name = name
        self.settings = settings
        """The transport's typed connection options."""

    @abstractmethod
    async def open(self) -> None: ...

    @abstractmethod
    def source(self, route: str, options: Any) -> Source:
        """A source from the transport's typed source options (a mapping is parsed first)."""

    @abstractmethod
    def sink(self, route: str, options: Any) -> Sink: ...

    @abstractmethod
    async def close(self) -> None: ...

    @property
    def healthy(self) -> bool:
        """False while the connection is known to be down: the engine then waits for it instead
        of counting delivery attempts against messages, and /healthz and the status show it."""
        return True

    def health(self) -> dict[str, Any]:
        """What the status shows: ``state`` (up, connecting, reconnecting, degraded, down) and, when
        known, ``last_error`` (never a secret)."""
        return {"state": "up" if self.healthy else "down"}

    def unavailable(self) -> list[str]:
        """Parts of an up connection that routes need and that are down (a vehicle silent for
        its timeout), each named with why: /healthz answers 503 with them. The connection
        itself stays usable for the rest (unlike :attr:`healthy`)."""
        return []

    def metrics(self) -> Iterable[ConnectionMetric]:
        """The connection's own samples for ``/metrics`` (a link's bad frames, a vehicle's
        liveness), read at scrape time from counters the connection keeps as plain integers."""
        return ()

    async def prepare_dead_letters(self, max_length: int | None) -> None:
        """Declare what :meth:`dead_letter` needs (only where ``keeps_dead_letters``)."""
        raise NotImplementedError

    async def dead_letter(self, route: str, messages: Sequence[tuple[bytes, Mapping[str, Any]]]) -> None:
        """Store ``(body, headers)`` dead letters of ``route``; raise EndpointError if not stored."""
        raise NotImplementedError

    def dead_letter_destination(self) -> str:
        """Where :meth:`dead_letter` stores, for the status (only where ``keeps_dead_letters``)."""
        return f"connection {self.name!r}"

    async def dead_letter_reader(self) -> DeadLetterReader:
        """The dead letters :meth:`dead_letter` stored, to be read and removed one by one
        (``rabbitros-engine dead-letters``; only where ``keeps_dead_letters``)."""
        raise NotImplementedError

    holds_leases: ClassVar[bool] = False
    """True where :meth:`lease` gives a lease other instances see (a broker queue), so an
    ``active_standby`` route can fail over through this connection."""

    def lease(self, name: str, instance: str, heartbeat: float) -> Lease:
        """The lease ``name`` of an ``active_standby`` route (only where ``holds_leases``)."""
        raise NotImplementedError


class Lease(Protocol):
    """What :meth:`Connection.lease` returns; engine/running/leases.py starts and stops it."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...


FieldPath = tuple[str, ...]
"""A path a mapping reads, one step per field; :data:`ELEMENT` steps into a list's elements."""
ELEMENT = "[]"
FieldProblem = Callable[[FieldPath], "str | None"]
"""What a source's message says about a path a mapping reads: None, or why it has no such field."""


def flat_field_problem(label: str, fields: Sequence[str], path: FieldPath) -> str | None:
    """:data:`FieldProblem` of a flat message (``label``) with these ``fields``."""
    if not path or path[0] == ELEMENT or path[0] in fields:
        return None
    guess = closest(path[0], fields)
    hint = f"; did you mean {guess!r}?" if guess else f" (fields: {', '.join(fields)})"
    return f"mapping reads {path[0]!r}, which {label} does not have{hint}"

CheckResult = Iterable[tuple[str | None, str]]
"""``(option key or None, message)`` pairs; the route loader attaches file and line."""


@dataclass(frozen=True, kw_only=True)
class EndpointOptions:
    """What every source and sink option class has (engine/common/options.py declares the rest)."""

    connection: str | None = option(None, description="name of a connection from any file of the directory; default: the only "
                                                       "connection of the protocol, else the protocol's default connection")
    agents: Mapping[str, Mapping[str, Any]] | None = option(None, internal=True)
    """The agents table's entries on the endpoint's connection (engine/language/agents.py), handed by
    the route loader to an endpoint that looks agents up per message; None otherwise."""
    priority: str = option("normal", internal=True)
    """The route's ``priority`` (high, normal, low), handed to its sink by the route loader: a
    sink whose connection carries several routes over one slow link orders its writes by it
    (MAVLink); the others ignore it."""
    latest_per: tuple[str, ...] | None = option(None, internal=True)
    """The route's ``buffer.latest_only.per`` (``()``: one key for the route), handed to its
    sink by the route loader: the route is telemetry, so a sink that cannot send everything
    now (a radio's budget) may replace a waiting message by a newer one with the same key and
    report the older one :class:`Conflated`; None: every message must arrive."""
    max_age: float | None = option(None, internal=True)
    """The route's ``max_age`` in seconds, handed to its sink by the route loader: a sink that
    keeps trying to deliver a message (a tunnel's retransmissions) gives it up as
    :class:`Expired` once it is older than that."""


O = TypeVar("O", bound="DataclassInstance")
"""An option class (a dataclass, engine/common/options.py)."""


def typed(cls: type[O], value: Any, where: str) -> O:
    """``value`` as the option class ``cls``: the typed value the loader parsed, or a mapping
    (a caller that skipped the loader) parsed now; EndpointError names ``where``."""
    if isinstance(value, cls):
        return value
    try:
        return parse(cls, value)
    except OptionError as exc:
        raise EndpointError(f"{where}: {exc}") from None


def typed_or_problem(cls: type[O], value: Any) -> tuple[O | None, list[tuple[str | None, str]]]:
    """For the static checks: the typed value, or the problems that stop the parse, each
    with the option it belongs to (``qos.depth`` for a nested one)."""
    if isinstance(value, cls):
        return value, []
    try:
        return parse(cls, value), []
    except OptionError as exc:
        return None, [(dotted(path) if path else None, describe(path, message)) for path, message in exc.problems]


class Transport(WorkerHints, ABC):
    """What the engine knows about a protocol before connecting: defaults and static checks
    (and, from :class:`WorkerHints`, how its sources spread over instances and workers)."""

    name: ClassVar[str]
    connection_type: ClassVar[type[Connection]] = Connection  # type: ignore[type-abstract]  # read for its capabilities, never instantiated
    """The class :meth:`connect` returns: the core reads its capabilities (``keeps_dead_letters``,
    ``holds_leases``) at load, before anything connects."""
    default_settings: ClassVar[Mapping[str, Any]]
    connection_options: ClassVar[type[DataclassInstance]]
    """The option class of ``connections.<name>.<protocol>`` (engine/common/options.py)."""
    source_options: ClassVar[type[EndpointOptions]]
    sink_options: ClassVar[type[EndpointOptions]]
    connection_shorthand: ClassVar[str | None] = None
    """The connection option a plain string stands for (``amqp: amqp://host`` is the url)."""
    options_beside: ClassVar[bool] = False
    """True when the protocol key holds only the shorthand and the other connection options
    sit beside it (``mavlink: udpin:...`` with ``baud:`` and ``signing:`` next to it)."""
    source_meta: ClassVar[tuple[str, ...]] = ()
    """The names of the metadata this protocol's source gives each message (``Inbound.meta``),
    which a mapping reads with ``meta(name)``: ``check`` refuses any other name (the route's
    template variables aside), and a route test gives them as ``meta: {name: value}``."""
    delivers: ClassVar[bool] = True
    """False for a sink that sends nothing anywhere (memory): its route exists only for what it
    remembers, so the loader requires ``remember:`` on it."""
    replies: ClassVar[bool] = False
    """True when this protocol's sources can answer a request's sender (:meth:`Source.reply`):
    only then may a route with such a source have ``reply:`` (the loader checks)."""

    def source_answers(self, options: Any) -> bool:
        """Whether a source with these (typed) options can answer its sender (``reply:`` is
        allowed): by default, whether the protocol's sources can (:attr:`replies`)."""
        return self.replies

    accepts_secrets: ClassVar[bool] = False
    """True when the connection settings may hold engine.common.redaction.Secret values, which the
    endpoint reveals only where it connects; otherwise the loader hands it plain values."""

    def source_variables(self, options: Any) -> tuple[str, ...]:
        """The names a source with these (typed) options captures from where each message came
        (a ROS 2 topic pattern ``/{agent}/fix``: the segment each topic has there), also in
        :meth:`meta_names`. The pipeline hands their values to the sink (``Outbound.captured``),
        whose templates read them before canonical fields. By default none."""
        return ()

    def meta_names(self, options: Any) -> tuple[str, ...]:
        """What ``meta(name)`` can read from a source with these (typed) options; by default
        :attr:`source_meta`, for a protocol whose sources differ by kind to narrow or extend."""
        return self.source_meta

    def check_connection(self, settings: Any) -> CheckResult:
        """Static checks of a connection's options: those the parse finds (a mapping is parsed
        first; the loader passes the typed value), else :meth:`connection_problems`."""
        parsed, problems = typed_or_problem(self.connection_options, settings)
        return problems if parsed is None else list(self.connection_problems(parsed))

    def check_source(self, options: Any, mapping: str | None) -> CheckResult:
        parsed, problems = typed_or_problem(self.source_options, options)
        return problems if parsed is None else list(self.source_problems(parsed, mapping))

    def check_sink(self, options: Any, mapping: str | None) -> CheckResult:
        parsed, problems = typed_or_problem(self.sink_options, options)
        return problems if parsed is None else list(self.sink_problems(parsed, mapping))

    def connection_problems(self, options: Any) -> CheckResult:
        """What the declaration cannot say about valid typed options (a reachable device...)."""
        return ()

    def source_problems(self, options: Any, mapping: str | None) -> CheckResult:
        """What the declaration cannot say: options that contradict each other, or are not
        used by this kind of source, a type that is not installed, the mapping's keys."""
        return ()

    def sink_problems(self, options: Any, mapping: str | None) -> CheckResult:
        return ()

    def sink_field_check(self, options: Any, mapping: str | None = None) -> Callable[[Any], None] | None:
        """What a sink with these (typed, checked) options refuses in its sink mapping's output
        before anything is sent: a typed sink raises :class:`MessageRejected` naming a field set
        to null (a null, or a path the message lacks) instead of guessing a value for it. The
        pipeline runs it as the last step of its ``sink mapping`` stage, so the run and
        ``rabbitros-engine test`` report the same error, and the message never reaches the
        throttle, the buffer or the sink (nor waits there for a reader). ``mapping``: the
        route's sink mapping (None: the sink is given the canonical message). None (the
        default): the sink takes what it is given."""
        return None

    def exclusive_resource(self, settings: Any) -> str | None:
        """The operating-system resource only one open connection can hold (a listening port,
        a serial device: two readers would split the bytes), as a key such as ``udp:14550``,
        or None. A reload that changes such a connection closes the old one before opening
        the new (break-before-make) instead of the usual make-before-break."""
        return None

    def key_files(self, settings: Any) -> Iterable[str]:
        """Files whose contents the connection reads when it opens (signing keys): a reload
        reopens the connection when their contents change."""
        return ()

    async def source_retired(  # noqa: B027  # a hook: only AMQP undoes anything
        self, connection: Connection, route: str, options: Any,
        remaining: Iterable[tuple[str, Any]],
    ) -> None:
        """The source of ``route`` stopped for good (route removed, or source replaced):
        undo on ``connection`` what only it needed (AMQP: bindings, an auto-named queue).
        ``remaining`` are the (route, options) of the sources configured on that connection now."""

    def canonical_fields(self, options: Any) -> Iterable[tuple[str, str]]:
        """``(option key, dotted field path)`` of each canonical field a sink's options
        interpolate (``routing_key: canonical.{agent_id}``): ``check`` warns about one the
        route's schema does not declare, as a message without it is dead-lettered."""
        return ()

    def competing_consumers(self, route: str, options: Any) -> str | None:
        """For a source whose consumers compete for messages (an AMQP queue), the name of what
        it consumes; ``check`` warns when two routes name the same one."""
        return None

    def default_connection_settings(self, env: Mapping[str, str]) -> Mapping[str, Any]:
        """The settings of the protocol's default connection (``default-<protocol>``, used by
        routes that name none): :attr:`default_settings`, or what ``env`` says (the private
        broker ``--local-broker`` started)."""
        return self.default_settings

    def private_broker_warning(self, settings: Any, env: Mapping[str, str]) -> str | None:
        """Under ``--local-broker`` (``env`` as it set it): when a connection with these typed
        settings names its own broker instead of the private one, why, for a load warning that
        begins with the connection's name (``{private}`` stands for the private broker's)."""
        return None

    def redelivers(self, options: Any) -> bool:
        """True when a source with these (typed) options gets back every message the engine did
        not settle (a broker keeps what was not acknowledged): its route needs no buffer while
        the sink is down. False (the default, and an MQTT QoS 0 subscription): a message not
        settled is gone, so the route holds messages in a buffer by default."""
        return False

    agent_options: ClassVar[Mapping[str, str]] = {}
    """Options that take an agent's name (engine/language/agents.py), each with the key of the agent's
    entry whose value replaces the name at load (MAVLink: ``target_system`` -> ``system_id``)."""

    def looks_up_agents(self, options: Any) -> bool:
        """Whether a sink with these (typed) options resolves agents' names per message (a
        ``{field}`` holding ``uav2``): the loader then hands it the agents on its connection in
        its ``agents`` option. A source gets them when its route reads ``meta('agent')``."""
        return False

    def queues_per_agent(self, options: Any) -> bool:
        """Whether a source with these (typed) options queues its messages in the engine
        (:meth:`Deliver.inbox`), where a route's ``fair:`` gives each agent its own queue;
        False (the default): a broker holds the backlog, and ``fair`` is a check error."""
        return False

    supports_ordered: ClassVar[bool] = False
    """True when a source can be consumed by one engine instance at a time, in order
    (``ordered: true``; :meth:`ordered_source` says how). Otherwise a route's source is carried
    by one instance through ``instances`` or ``active_standby``."""

    def ordered_source(self, options: Any, partitions: int = 1, key: str = "") -> Any:
        """The source options of an ``ordered`` route: one consumer at a time (only where
        ``supports_ordered``), or ``partitions`` > 1 split by ``key`` (where :meth:`partition_problems` found none)."""
        raise NotImplementedError

    def partition_problems(self, options: Any, partitions: int, key: str) -> CheckResult:
        """For ``check``: why a source cannot be split into ordered partitions (``ordered: {partitions, key}``)."""
        yield None, f"a {self.name} source cannot be partitioned (use ordered: true for one instance at a time)"

    def sink_dry_run(self, route: str, options: Any) -> Callable[[Outbound], str | None]:
        """What the sink would do short of sending, for ``rabbitros-engine test``: the rendered
        routing key or topic (shown), and for a typed sink the message built from the fields.
        Raises :class:`MessageRejected` (its ``stage`` is the error's) for what the sink would
        refuse. The default accepts anything and shows nothing: a protocol with templates or
        types must override it, or ``test`` passes what the run dead-letters."""
        return lambda outbound: None

    def test_input(self, options: Any) -> Callable[[Any], dict[str, Any]] | None:
        """For ``rabbitros-engine test``: the field dict a typed source (these options) hands
        over for a case's ``input``, after a round trip through the real type, so defaults
        fill in and a field the type lacks is an error (EndpointError/ValueError/TypeError) as
        on the wire. None (the default): a byte source, the input is sent as JSON bytes."""
        return None

    def field_problem(self, options: Any) -> FieldProblem | None:
        """For ``check``: what a typed source (these options) says about each path its route's
        mapping reads (a field its message type lacks, with a did-you-mean). None (the
        default): the source gives bytes or JSON, whose fields nothing declares."""
        return None

    def reply_field_problem(self, options: Any) -> FieldProblem | None:
        """For ``check``: what a sink (these options) says about each path the route's
        ``reply.mapping`` reads from its answer (a field a typed answer, such as a service's
        response, lacks, with a did-you-mean). None (the default): the sink answers nothing,
        or nothing whose fields it declares."""
        return None

    def suggest(self, key: str, value: str) -> str | None:
        """For ``check``: the known name closest to a misspelt ``value`` of option ``key`` (a
        ROS 2 type, a MAVLink message), or None."""
        return None

    @abstractmethod
    def connect(self, name: str, settings: Any) -> Connection:
        """A connection from the typed connection options (or a mapping, parsed here)."""
