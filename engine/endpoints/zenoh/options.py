"""The Zenoh endpoint's options, declared once (engine/common/options.py): connection, source, sink.

The descriptions are what editors show and what the generated key reference prints, so each
says what the option does to the session or the messages, not only its type.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from engine.common.options import option
from engine.endpoints.base import EndpointOptions

Mode = Literal["peer", "client"]
CongestionControl = Literal["block", "drop"]
Priority = Literal["real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background"]


@dataclass(frozen=True, kw_only=True)
class ZenohConnectionOptions:
    """``connections.<name>.zenoh``: one Zenoh session (eclipse-zenoh), a peer by default."""

    __schema_description__ = ("one Zenoh session (eclipse-zenoh 1.x): a peer (talks to peers and routers directly) or a client "
                              "(through one router); it reconnects by itself")

    mode: Mode = option("peer", description="peer: connects to the endpoints in connect and to what scouting finds, accepts "
                                            "connections on listen; client: goes through a router (one of connect)")
    connect: tuple[str, ...] = option((), description="endpoints to connect to, as tcp/HOST:PORT (also udp/, tls/, quic/, ws/); "
                                                      "a peer retries them in the background, a client needs one at start")
    listen: tuple[str, ...] = option((), description="endpoints a peer accepts connections on, as tcp/0.0.0.0:7447")
    multicast_scouting: bool = option(True, description="find peers and routers on the local network by UDP multicast "
                                                        "(Zenoh's default); false: only connect and what they tell of")
    config_file: str | None = option(None, description="a Zenoh configuration file (JSON5) for what these keys do not say "
                                                       "(TLS, access control, timeouts); the keys above override it; re-read "
                                                       "when it changes (a reload reopens the session)")


@dataclass(frozen=True, kw_only=True)
class ZenohSourceOptions(EndpointOptions):
    __schema_description__ = ("subscribe to a key expression (or answer queries on it); Zenoh resends nothing, so a message "
                              "not settled is dropped and counted (engine/endpoints/zenoh/source.py)")

    key: str = option(description="key expression: * one chunk, ** any number of chunks, {name} one chunk whose value the "
                                  "mapping reads as meta('name') and a sink's template as {name}: farm/{robot}/weather")
    queryable: bool = option(False, description="answer the queries (get) on key instead of subscribing: each query is a "
                                                "request (its payload, else its parameters as a JSON object) and the route's "
                                                "reply its answer (route-language.md, Calls)")


@dataclass(frozen=True, kw_only=True)
class ZenohSinkOptions(EndpointOptions):
    __schema_description__ = "put each message on a key; accepted once the session queued it for sending"

    key: str = option(description="key to put on; may interpolate canonical fields and the source's captures: farm/{agent_id}/cmd")
    congestion_control: CongestionControl = option("block", description="block: a put waits while the session's send queue is "
                                                                        "full (the route slows down); drop: the message is dropped "
                                                                        "then (Zenoh's default, for telemetry)")
    priority: Priority = option("data", description="Zenoh priority of the messages")
    express: bool = option(False, description="send each message at once instead of batching it with others (lower latency, "
                                              "more packets)")
    encoding: str = option("application/json", description="encoding the messages are put with")
