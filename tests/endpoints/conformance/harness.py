"""What a protocol supplies to the conformance suite (test_conformance.py): how to stand up its
peer, the route-file snippets of its connection, source and sink, how to inject a message and how
to observe one, and which cases it is excluded from and why.

The model is Redpanda Connect's ``internal/integration/stream_test_definitions.go``: one set of
stream tests written once, each connector giving only its peer and its config template. Here each
protocol's harness lives in ``harnesses/<protocol>.py`` (the module is found by the protocol's
registry name, engine/endpoints/__init__.py ``PROTOCOLS``), so a protocol added to the registry
is under the suite at once: without a harness module its cases fail naming it.

Every route the suite runs is one loop through the protocol's peer: its source takes what the test
injects for robot N, the mapping adds ``origin`` (read from the source's metadata) and
``edition`` (which route-file edition carried it), and its sink delivers to an address rendered
from ``origin``; the observer reads the robot back from the address it arrived on, so one message
shows source metadata, the mapping and the sink's template together.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

CASES = ("open_close", "through", "dead_letter", "health", "reload", "kill9", "cancel")
"""The suite's cases (test_conformance.py, one test each): a harness excludes one by naming it in
``EXCLUDED`` with the reason (a case is never skipped: it runs, or the protocol declared why not)."""


@dataclass(frozen=True)
class Seen:
    """One message the observer took off the peer: the robot its address names, and the body's
    ``seq``, ``origin`` (what the route's mapping read from the source's metadata) and ``edition``."""

    robot: int
    seq: int
    origin: str
    edition: int


class Harness:
    """One protocol's side of the suite. Subclasses set the class attributes and implement the
    methods; the suite calls ``open`` before writing the route file and ``close`` after the
    engine stopped. Every method that waits has its own deadline."""

    PROTOCOL: ClassVar[str]
    FIXTURES: ClassVar[tuple[str, ...]] = ()
    """pytest fixtures the harness needs (``amqp_url``, ``mosquitto``), handed to ``open``."""
    EXCLUDED: ClassVar[dict[str, str]] = {}
    """Case -> why this protocol does not take part (what it does not promise, with the doc)."""
    BAD_STAGE: ClassVar[str] = "decode"
    """The dead-letter stage of the harness's bad payload."""

    def __init__(self, tag: str, tmp_path: Path) -> None:
        self.tag = tag
        self.tmp_path = tmp_path

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        """Stand up the peer (and the observer on it) for ``case``."""

    async def close(self) -> None:
        """Undo ``open``."""

    def connection(self, case: str) -> str:
        """The connection's YAML flow mapping (``{mqtt: {url: ...}}``)."""
        raise NotImplementedError

    def source(self) -> str:
        """The source's YAML flow mapping, without ``connection`` (``{mqtt: {topic: ...}}``)."""
        raise NotImplementedError

    def sink(self) -> str:
        """The sink's YAML flow mapping, its address rendered from the field ``origin``."""
        raise NotImplementedError

    def mapping(self, edition: int) -> str:
        """The route's mapping: the body with ``origin`` from the source's metadata and ``edition``."""
        return f"merge(@, {{origin: {self.origin_expression()}, edition: `{edition}`}})"

    def sink_mapping(self) -> str | None:
        """The sink's own mapping (the fields a MAVLink message sink sends), or None."""
        return None

    def origin_expression(self) -> str:
        """What the mapping reads the robot's origin from (JMESPath over ``meta()``)."""
        raise NotImplementedError

    def expected_origin(self, robot: int) -> str:
        """What ``origin_expression`` gives for a message injected for ``robot``."""
        raise NotImplementedError

    async def ready(self) -> None:
        """Until a message injected now reaches the engine's source (a matched subscription)."""

    async def inject(self, robot: int, seq: int) -> None:
        raise NotImplementedError

    async def inject_bad(self, robot: int) -> None:
        """A message the route dead-letters at ``BAD_STAGE`` (no JSON, where the payload is JSON)."""
        raise NotImplementedError

    def seen(self) -> list[Seen]:
        """Everything observed so far, in arrival order."""
        raise NotImplementedError

    def session_of(self, connection: Any) -> Any:
        """The object that is the connection's session with its peer (a reload must keep it)."""
        return connection

    async def peer_down(self) -> None:
        """Take the broker or peer away (``health``)."""
        raise NotImplementedError

    async def peer_back(self) -> None:
        """Bring it back where it was."""
        raise NotImplementedError

    async def cancel_subscription(self) -> None:
        """Make the broker drop the source's subscription (``cancel``), and leave it able to serve again."""
        raise NotImplementedError


def harness_class(protocol: str) -> type[Harness] | None:
    """The harness of ``protocol`` (``harnesses/<protocol>.py``'s ``HARNESS``), or None."""
    try:
        module = importlib.import_module(f"{__package__}.harnesses.{protocol}")
    except ModuleNotFoundError as missing:
        if missing.name == f"{__package__}.harnesses.{protocol}":
            return None
        raise
    return module.HARNESS
