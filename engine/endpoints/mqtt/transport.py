"""What the engine knows about MQTT before connecting: option classes, static checks, the
exclusive resource of a persistent session, and undoing a removed route's subscription."""

from __future__ import annotations

from typing import Any, Callable, Iterable, Mapping
from urllib.parse import urlsplit

from engine.common import tls as tls_common
from engine.common.options import given
from engine.common.placeholders import template_fields
from engine.common.redaction import redact_urls, reveal
from engine.endpoints.base import CheckResult, Connection, Outbound, Transport, typed_or_problem
from engine.endpoints.mqtt.connection import MqttConnection
from engine.endpoints.mqtt.link import Endpoint
from engine.endpoints.mqtt.options import MqttConnectionOptions, MqttSinkOptions, MqttSourceOptions
from engine.endpoints.mqtt.topics import capture_names, filter_problems, subscription, template_problems, topic_renderer

QOS2_SOURCE = ("qos 2 is not offered on a source: paho acknowledges a QoS 2 message (PUBREC) as it arrives, "
               "before the route settled it, so an engine stopped meanwhile would lose it; qos 1 is at-least-once "
               "end to end (a QoS 2 publication reaches a qos 1 subscription as QoS 1)")


class MqttTransport(Transport):
    name = "mqtt"
    connection_type = MqttConnection
    default_settings = {}
    accepts_secrets = True
    connection_options = MqttConnectionOptions
    source_options = MqttSourceOptions
    sink_options = MqttSinkOptions
    connection_shorthand = "url"
    source_meta = ("topic", "qos", "retain")

    def source_variables(self, options: MqttSourceOptions) -> tuple[str, ...]:
        """The topic's ``{name}`` levels (``farm/{station}/weather``), captured from each
        message's topic (topics.py): ``meta('station')`` and the sink's templates read them."""
        return capture_names(options.topic)

    def meta_names(self, options: MqttSourceOptions) -> tuple[str, ...]:
        return (*self.source_meta, *self.source_variables(options))

    def connection_problems(self, options: MqttConnectionOptions) -> CheckResult:
        written = given(options)
        try:
            endpoint = Endpoint.parse(options)
        except ValueError as exc:
            yield "url", str(exc)
            return
        if options.tls is not None and not endpoint.tls:
            yield "tls", "tls applies to mqtts:// URLs; this one is mqtt:// (plain TCP), which would never use it"
        for problem in tls_common.file_problems(options.tls):
            yield "tls", problem
        if options.client_id == "":
            yield "client_id", "client_id is empty (leave it out for a clean session)"
        if "session_expiry" in written and options.client_id is None:
            yield "session_expiry", "session_expiry keeps the session of a client_id; without one every connection starts clean"
        if options.protocol != 5:
            for key in ("session_expiry", "receive_maximum"):
                if key in written:
                    yield key, f"{key} is an MQTT 5 property (protocol is {options.protocol!r})"
        url_user = urlsplit(reveal(options.url)).username if options.url is not None else None
        if url_user and options.username is not None:
            yield "username", "the url names a user already; give it in one place"
        if endpoint.password is not None and endpoint.username is None:
            yield "password", "a password needs a username"

    def source_problems(self, options: MqttSourceOptions, mapping: str | None) -> CheckResult:
        for message in filter_problems(options.topic):
            yield "topic", message
        if options.qos == 2:
            yield "qos", QOS2_SOURCE

    def sink_problems(self, options: MqttSinkOptions, mapping: str | None) -> CheckResult:
        for message in template_problems(options.topic):
            yield "topic", message

    def private_broker_warning(self, settings: MqttConnectionOptions, env: Mapping[str, str]) -> str | None:
        """A connection with a ``url`` keeps its broker; one without uses the private mosquitto."""
        if settings.url is None:
            return None
        return (f"names its own broker ({redact_urls(reveal(settings.url))}), so {{private}} does not serve it; "
                "to use the private broker, leave its url out")

    def redelivers(self, options: MqttSourceOptions) -> bool:
        """QoS 1: the broker resends what was not acknowledged (PUBACK after the route settled);
        a QoS 0 message is delivered once, so its route keeps the default buffer."""
        return options.qos >= 1

    def spreads_over_workers(self, options: MqttSourceOptions) -> bool:
        """A shared subscription (``shared: GROUP``): the broker hands each message to one member
        of the group, so every worker subscribes; a plain one gives each subscriber every message."""
        return options.shared is not None

    def sink_dry_run(self, route: str, options: MqttSinkOptions) -> Callable[[Outbound], str | None]:
        render = topic_renderer(options.topic, f"route {route!r}: mqtt sink")
        return lambda outbound: render(outbound.template_data)

    def canonical_fields(self, options: MqttSinkOptions) -> Iterable[tuple[str, str]]:
        return [("topic", name) for name in template_fields(options.topic)]

    def key_files(self, settings: Any) -> Iterable[str]:
        """The TLS files: a renewed certificate reopens the connection (engine/common/tls.py)."""
        options, _ = typed_or_problem(MqttConnectionOptions, settings)
        return tls_common.key_files(options.tls) if options is not None else []

    def exclusive_resource(self, settings: MqttConnectionOptions) -> str | None:
        """A client_id names one session on one broker: two connections holding it would take
        it from each other, so a reload that changes the connection closes the old one first."""
        if settings.client_id is None:
            return None
        try:
            endpoint = Endpoint.parse(settings)
        except ValueError:
            return None
        return f"mqtt:{endpoint.host}:{endpoint.port}/{settings.client_id}"

    async def source_retired(
        self, connection: Connection, route: str, options: MqttSourceOptions,
        remaining: Iterable[tuple[str, Any]],
    ) -> None:
        """Unsubscribe the removed route's filter unless a configured route still uses it
        (a persistent session would otherwise keep collecting its messages)."""
        assert isinstance(connection, MqttConnection)
        filter_ = subscription(options.topic, options.shared)
        wanted = {subscription(other.topic, other.shared) for _, other in remaining if isinstance(other, MqttSourceOptions)}
        if filter_ in wanted:
            await connection.unsubscribe(filter_, route, keep_subscription=True)
        else:
            await connection.unsubscribe(filter_, route)

    def connect(self, name: str, settings: MqttConnectionOptions | Mapping[str, Any]) -> Connection:
        return MqttConnection(name, settings)


TRANSPORT = MqttTransport()
