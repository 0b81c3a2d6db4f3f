"""The options of the running engine's stages, declared where the route language reads them.

A route file's ``buffer:``, ``dead_letters:``, ``fair:``, ``throttle:``, ``reply:`` and the
delivery limits are parsed and checked by the route language (engine/language/routes.py and the modules it composes) and
acted on by the running engine (engine/running/). Declaring them here, rather than beside the
code that acts on them, keeps the import direction one way: the language never imports the
running engine (tests/project/test_import_graph.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from engine.common.field_keys import FIELD_PATH
from engine.common.options import option
from engine.common.state import state_dir
from engine.endpoints.base import OVERFLOW_POLICIES

DEFAULT_MAX_ATTEMPTS = 5
DEFAULT_MAX_MESSAGE_BYTES = 8 * 1024 * 1024
DEFAULT_QUEUE_LIMIT = 10_000
"""Messages a source may hold in memory between its protocol and the pipeline."""


@dataclass(frozen=True)
class RouteDelivery:
    """A route's delivery settings, parsed once from its route file."""

    max_attempts: int = DEFAULT_MAX_ATTEMPTS
    overflow: str = "block"
    queue_limit: int = DEFAULT_QUEUE_LIMIT
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    """The source connection's limit (messages larger are dead-lettered unparsed)."""
    sink_max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_age_ns: int | None = None
    """``max_age``: older messages are expired instead of sent (engine/running/runner.py decides)."""

    def __post_init__(self) -> None:
        assert self.overflow in OVERFLOW_POLICIES and self.max_attempts >= 1


DEFAULT_MAX_MESSAGES = 10_000


@dataclass(frozen=True)
class BufferSpec:
    """A route's ``buffer:`` option, resolved (the spill directory made absolute)."""

    max_messages: int = DEFAULT_MAX_MESSAGES
    spill_dir: Path | None = None
    fsync_interval: float = 1.0
    latest_per: tuple[str, ...] | None = None
    """``latest_only``: the canonical field whose values keep only their newest message (``()``: one for the route)."""

    @classmethod
    def parse(cls, value: BufferOptions | bool | None, source_redelivers: bool, base: Path) -> BufferSpec | None:
        """``buffer: false`` is none; absent is the default for sources that cannot have a
        message redelivered (ROS 2, MAVLink, MQTT QoS 0) and none for those whose broker keeps
        what the engine has not acknowledged (``Transport.redelivers``: AMQP, MQTT QoS 1)."""
        if value is False or (value is None and source_redelivers):
            return None
        value = value if isinstance(value, BufferOptions) else BufferOptions()
        return cls(
            value.max_messages,
            (base / value.spill_dir).resolve() if value.spill_dir else None,
            float(value.fsync_interval),
            None if value.latest_only is None else tuple(value.latest_only.per.split(".")) if value.latest_only.per else (),
        )


@dataclass(frozen=True, kw_only=True)
class LatestOnlyOptions:
    """``buffer.latest_only``: after an outage, replay only the newest held message per key."""

    __schema_description__ = ("after an outage only the newest held message per value of the canonical field 'per' is sent, "
                              "the older ones are counted conflated: for telemetry, never for events that must all arrive")

    per: str | None = option(None, pattern=FIELD_PATH,
                             description="canonical field (a.b) whose values keep their newest message each; none: the route's newest")


@dataclass(frozen=True, kw_only=True)
class BufferOptions:
    """A route's ``buffer:`` as written (``buffer: false`` is none at all)."""

    __schema_description__ = ("messages of a source that cannot redeliver held, in order, while "
                              "the sink is down, and sent when it is back")

    max_messages: int = option(DEFAULT_MAX_MESSAGES, minimum=1,
                               description="held at most; when full, the source waits (and its overflow applies)")
    spill_dir: str | None = option(None, description="keep held messages on disk here (relative to the routes directory), replayed at start")
    fsync_interval: float = option(1.0, minimum=0, description="seconds between fsyncs of the spill files (each message is written before the source is acknowledged)")
    latest_only: LatestOnlyOptions | None = option(None)


DEFAULT_DEAD_LETTER_MAX_LENGTH = 100_000
DEFAULT_SPOOL_MAX_BYTES = 64 * 1024 * 1024

@dataclass(frozen=True, kw_only=True)
class DeadLettersOptions:
    """``dead_letters:`` as written in a route file (resolved into :class:`DeadLetterSpec`)."""

    __schema_description__ = "the engine's one dead-letter destination; default: the only connection that keeps dead letters (a broker), else a local spool"

    connection: str | None = option(None, description="a connection that keeps dead letters (a broker: exchange and queue rabbitros.dead-letter, routing key = route name)")
    max_length: int = option(DEFAULT_DEAD_LETTER_MAX_LENGTH, minimum=1, description="x-max-length of the dead-letter queue (oldest dropped beyond it)")
    spool_dir: str | None = option(None, description="directory of rotated JSON-lines files; default ~/.local/state/rabbitros-engine/dead-letters")
    spool_max_bytes: int = option(DEFAULT_SPOOL_MAX_BYTES, minimum=4096, description="bytes of the spool's rotated files together (the newest dead letters are kept)")


@dataclass(frozen=True)
class DeadLetterSpec:
    """``dead_letters:`` of a routes directory, resolved: exactly one of connection/spool_dir."""

    connection: str | None = None
    max_length: int = DEFAULT_DEAD_LETTER_MAX_LENGTH
    spool_dir: str | None = None
    spool_max_bytes: int = DEFAULT_SPOOL_MAX_BYTES


DEFAULT_BATCH = 4
DEFAULT_QUEUE = 1000



@dataclass(frozen=True, kw_only=True)
class FairOptions:
    """A route's ``fair:`` (see the module docstring)."""

    __schema_description__ = ("one queue per agent (each value of the source's metadata 'per'), taken round-robin: one "
                              "agent's flood neither delays nor drops the others' messages")

    per: str = option(description="the source metadata naming the agent, as meta() reads it (system_id, topic, ...)")
    batch: int = option(DEFAULT_BATCH, minimum=1, description="most messages of one agent in one batch towards the sink: "
                                                              "an agent waits at most about 2 x batch x agents / (sink rate)")
    queue: int = option(DEFAULT_QUEUE, minimum=1, description="most messages queued per agent; beyond it that agent's oldest "
                                                              "(newest with overflow: drop_newest) is dropped, counted per agent")


@dataclass(frozen=True, kw_only=True)
class ThrottleOptions:
    """A route's ``throttle:`` (see the module docstring)."""

    __schema_description__ = ("at most max_rate messages/s per value of the canonical field 'per'; "
                              "between slots only the latest is kept (conflation)")

    max_rate: float = option(exclusive_minimum=0, description="messages per second per slot")
    per: str | None = option(None, pattern=FIELD_PATH,
                             description="canonical field (a.b) whose values get a slot each; none: one slot for the route")


@dataclass(frozen=True, kw_only=True)
class ReplyOptions:
    __schema_description__ = ("the replies to requests that carry a reply address: the sink's answer shaped by mapping "
                              "and checked by schema; error replies are never mapped (route-language.md, Calls)")

    mapping: str | None = option(None, nullable=True, description="JMESPath from the sink's answer (what each sink answers: "
                                                                  "route-language.md, Calls) to the reply body; absent: the "
                                                                  "answer itself")
    schema: str | None = option(None, description="canonical schema the reply body must satisfy (NAME or NAME.vN); a reply that "
                                                  "fails it becomes an error reply (stage reply schema)")


DEFAULT_DEDUPE_MAX_KEYS = 100_000


@dataclass(frozen=True, kw_only=True)
class DedupeOptions:
    """A route's ``dedupe:`` as written (engine/running/dedupe.py acts on it)."""

    __schema_description__ = ("a message whose key the sink accepted within ttl seconds is settled unsent and counted "
                              "duplicates (a mission redelivered after a crash is uploaded once); the keys survive a "
                              "restart, kept in the engine's state directory")

    key: str = option(description="JMESPath on the canonical message (meta(name) reads the source's metadata) giving the "
                                  "message's identity (a mission id); a message whose key is null is always sent")
    ttl: float = option(exclusive_minimum=0, description="seconds an accepted key keeps later messages with it from being sent")
    max_keys: int = option(DEFAULT_DEDUPE_MAX_KEYS, minimum=1, description=(
        "keys kept at most (memory and the state file); beyond it the oldest is forgotten before its ttl, counted evicted"))
    in_doubt: Literal["send", "skip"] = option("send", description=(
        "a key whose message was being sent when the engine died (no answer heard): send sends it again (at least once: "
        "nothing lost, a second copy possible), skip takes it as accepted (at most once for that batch: commands)"))
    state_dir: str | None = option(None, description=(
        "directory of the route's key file (relative to the routes directory); default "
        "~/.local/state/rabbitros-engine/dedupe ($XDG_STATE_HOME)"))


@dataclass(frozen=True)
class DedupeSpec:
    """A route's ``dedupe:``, resolved: the key file's absolute path chosen at load."""

    key: str
    ttl: float
    max_keys: int
    path: Path
    in_doubt: str = "send"

    @classmethod
    def parse(cls, options: DedupeOptions | None, route: str, base: Path) -> DedupeSpec | None:
        if options is None:
            return None
        directory = (base / options.state_dir).resolve() if options.state_dir else state_dir() / "dedupe"
        return cls(options.key, float(options.ttl), options.max_keys, directory / f"{route}.keys", options.in_doubt)
