"""The MQTT endpoint's options, declared once (engine/common/options.py): connection, source, sink.

The descriptions are what editors show and what the generated key reference prints, so each
says what the option does to the session or the messages, not only its type.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from engine.common.options import option
from engine.common.tls import TlsOptions
from engine.endpoints.base import EndpointOptions

ProtocolVersion = Literal[5, "3.1.1"]
DEFAULT_URL = "mqtt://localhost:1883"


@dataclass(frozen=True, kw_only=True)
class MqttMessageOptions:
    """One message the connection itself publishes: its last will, or what it says on a clean stop."""

    __schema_description__ = ("a message the connection publishes by itself; in payload, the strings {now} (ISO 8601 UTC, ms), "
                              "{now_ms} (ms since 1970) and {next} (one more than the messages the connection published on "
                              "the topic; both a number when they are the whole value) are filled when it is set: a will "
                              "at each connection (the time and count of connecting), on_stop at the stop")

    topic: str = option(pattern=r"^[^+#]+$", description="topic to publish on (no wildcards)")
    payload: str | dict[str, Any] = option(description="the message: a string, or a mapping sent as JSON")
    qos: Literal[0, 1, 2] = option(1, description="QoS of the message")
    retain: bool = option(True, description="the broker keeps it for later subscribers (a presence topic wants that)")


@dataclass(frozen=True, kw_only=True)
class MqttConnectionOptions:
    """``connections.<name>.mqtt``: one broker (``url``, also the string shorthand) and one session."""

    __schema_description__ = ("one MQTT client and session (aiomqtt on paho-mqtt 2, reconnects by itself); "
                              "a client_id makes the session persistent")

    url: str | None = option(None, secret=True, description="mqtt://host:1883 or mqtts://host:8883 (TLS: the system's CAs, or tls); "
                             "user:password@ allowed; default mqtt://localhost:1883")
    client_id: str | None = option(None, description="names a persistent session (clean start off): subscriptions and messages "
                                   "published while the engine is away are kept for session_expiry seconds; one engine per client_id")
    session_expiry: int = option(3600, minimum=0, description="seconds the broker keeps the session of a client_id after a "
                                 "disconnection (MQTT 5; a 3.1.1 broker keeps it as long as it is configured to)")
    keepalive: int = option(30, minimum=1, maximum=65535, description="seconds between pings; a silent broker is taken as lost after 1.5 times this")
    username: str | None = option(None, description="user name to authenticate with (or user@ in the url)")
    password: str | None = option(None, secret=True, description="use ${MQTT_PASSWORD}: never shown in logs or the status")
    protocol: ProtocolVersion = option(5, description="MQTT version: 5 or '3.1.1'")
    receive_maximum: int = option(256, minimum=1, maximum=65535, description="QoS 1 messages the broker may send before the engine "
                                  "acknowledges any (MQTT 5; with 3.1.1 the broker's own limit, mosquitto's max_inflight_messages)")
    tls: TlsOptions | None = option(None)
    will: MqttMessageOptions | None = option(None, description="last will: the broker publishes it when the engine's "
                                            "connection ends without a clean disconnection (the engine died, the network broke)")
    on_stop: MqttMessageOptions | None = option(None, description="published (and acknowledged, within 10 s) before a clean "
                                               "disconnection: an engine stop, or a reload that removes the connection")


@dataclass(frozen=True, kw_only=True)
class MqttSourceOptions(EndpointOptions):
    __schema_description__ = ("subscribe to a topic filter; a QoS 1 message is acknowledged (PUBACK) only once settled "
                              "(route-language.md, MQTT source and sink)")

    topic: str = option(description="topic filter, wildcards + (one level) and # (the rest); a {name} level is one level "
                                    "captured as meta('name') and for the sink's templates (farm/{station}/weather); "
                                    "meta.topic is the message's topic")
    qos: Literal[0, 1, 2] = option(1, description="1: at-least-once, acknowledged (PUBACK) once the route settled the message; "
                                   "0: at most once; 2 is refused (a QoS 2 message is acknowledged on receipt)")
    shared: str | None = option(None, pattern=r"^[^/+#]+$", description="shared subscription group ($share/GROUP/topic): "
                                "engines subscribed with one group split the messages between them")


@dataclass(frozen=True, kw_only=True)
class MqttSinkOptions(EndpointOptions):
    __schema_description__ = "publish on a topic; accepted once the broker acknowledged it (QoS 1 and 2)"

    topic: str = option(description="topic to publish on; may interpolate canonical fields: farm/{agent_id}/cmd")
    qos: Literal[0, 1, 2] = option(1, description="1 and 2: a message is delivered once the broker acknowledged it (PUBACK, PUBCOMP)")
    retain: bool = option(False, description="the broker keeps the last message of each topic for later subscribers")
