"""What the engine knows about Zenoh before connecting: option classes, static checks, the
exclusive resource of a listening session, and what a source gives each message."""

from __future__ import annotations

import re
from typing import Any, Callable, Iterable, Mapping

from engine.common.placeholders import template_fields
from engine.endpoints.base import CheckResult, Connection, Outbound, Transport, typed_or_problem
from engine.endpoints.zenoh.connection import ZenohConnection
from engine.endpoints.zenoh.errors import describe
from engine.endpoints.zenoh.keys import key_renderer, key_variables, pattern_problems, template_problems
from engine.endpoints.zenoh.options import ZenohConnectionOptions, ZenohSinkOptions, ZenohSourceOptions
from engine.endpoints.zenoh.session import session_config

ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/[^/\s]+")
"""A Zenoh locator: ``PROTOCOL/ADDRESS`` (``tcp/192.168.1.10:7447``, ``tcp/[::1]:7447``), then
``?metadata`` and ``#config`` if any; the address itself is Zenoh's to judge when it opens."""


class ZenohTransport(Transport):
    name = "zenoh"
    connection_type = ZenohConnection
    default_settings = {}
    """A peer that scouts the local network by multicast (Zenoh's own default)."""
    connection_options = ZenohConnectionOptions
    source_options = ZenohSourceOptions
    sink_options = ZenohSinkOptions
    source_meta = ("key", "encoding")
    replies = True
    """A source with ``queryable: true`` answers its queriers (calls.py)."""

    def source_answers(self, options: ZenohSourceOptions) -> bool:
        return options.queryable

    def source_variables(self, options: ZenohSourceOptions) -> tuple[str, ...]:
        """The key's ``{name}`` chunks (keys.py)."""
        return key_variables(options.key)

    def meta_names(self, options: ZenohSourceOptions) -> tuple[str, ...]:
        extra = ("parameters",) if options.queryable else ()
        return (*self.source_meta, *extra, *self.source_variables(options))

    def connection_problems(self, options: ZenohConnectionOptions) -> CheckResult:
        for key in ("connect", "listen"):
            for endpoint in getattr(options, key):
                if not ENDPOINT.match(endpoint):
                    yield key, (f"{endpoint!r} is not a Zenoh endpoint: PROTOCOL/ADDRESS, as tcp/192.168.1.10:7447 "
                                "(protocols: tcp, udp, tls, quic, ws, unixsock-stream, serial)")
        if options.mode == "client" and not options.connect and not options.multicast_scouting and options.config_file is None:
            yield "connect", "a client needs a router: name one in connect (or let multicast_scouting find one)"
        if options.mode == "client" and options.listen:
            yield "listen", "a client accepts no connections (listen is for a peer)"
        if options.config_file is not None:
            try:
                session_config(options)
            except Exception as exc:  # ZError (malformed) or OSError (unreadable)
                yield "config_file", f"config_file {options.config_file}: {describe(exc)}"

    def source_problems(self, options: ZenohSourceOptions, mapping: str | None) -> CheckResult:
        for message in pattern_problems(options.key):
            yield "key", message

    def sink_problems(self, options: ZenohSinkOptions, mapping: str | None) -> CheckResult:
        for message in template_problems(options.key):
            yield "key", message

    def sink_dry_run(self, route: str, options: ZenohSinkOptions) -> Callable[[Outbound], str | None]:
        render = key_renderer(options.key, f"route {route!r}: zenoh sink")
        return lambda outbound: render(outbound.template_data)

    def canonical_fields(self, options: ZenohSinkOptions) -> Iterable[tuple[str, str]]:
        return [("key", name) for name in template_fields(options.key)]

    def key_files(self, settings: Any) -> Iterable[str]:
        """The config file: a changed one reopens the session."""
        options, _ = typed_or_problem(ZenohConnectionOptions, settings)
        return [options.config_file] if options is not None and options.config_file else []

    def exclusive_resource(self, settings: ZenohConnectionOptions) -> str | None:
        """A session that listens holds its ports: a reload that changes the connection closes
        the old session before the new one listens on them."""
        return f"zenoh-listen:{','.join(sorted(settings.listen))}" if settings.listen else None

    def connect(self, name: str, settings: ZenohConnectionOptions | Mapping[str, Any]) -> Connection:
        return ZenohConnection(name, settings)


TRANSPORT = ZenohTransport()
