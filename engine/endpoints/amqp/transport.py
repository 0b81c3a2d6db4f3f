"""AMQP 0-9-1 (RabbitMQ) endpoint on aio-pika (robust connections) and aiormq (hot path). This
module is the protocol's face to the registry (the :class:`AmqpTransport`: options, checks,
defaults, dry runs); the parts are one module per concern: options.py (typed options),
errors.py (the libraries' failures as the two edge errors), link.py (the connection to the
broker: publish and declare channels, dead letters, health), connection.py (the connection
that makes sources and sinks), source.py (a queue consumed in batches), acks.py (its held
acknowledgements), resume.py (a consumer the broker cancelled, taken up again), sink.py
(publishing, mandatory), publisher.py (every route's publishes in one round), returns.py (the
broker's returns of mandatory messages),
calls.py (a sink's request/reply), channels.py, cluster.py (cluster URLs, failover, leases),
partitions.py (partitioned ordered routes: a consistent-hash exchange, a queue per partition),
topology.py (what a retired source leaves behind), tls.py and broker.py (a private broker).
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Mapping

from engine.common.options import evolve, given
from engine.common.placeholders import MappingError, compile_template, template_fields, template_problem
from engine.common.redaction import Secret, has_url_password, redact_urls, reveal
from engine.endpoints.amqp.broker import CA_ENV, URL_ENV, URLS_ENV, elsewhere
import engine.endpoints.amqp.cluster as amqp_cluster
from engine.endpoints.amqp.connection import AmqpConnection
from engine.endpoints.amqp.link import redact
from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpSinkOptions, AmqpSourceOptions
from engine.endpoints.amqp.partitions import partition_problems
import engine.endpoints.amqp.tls as amqp_tls
from engine.endpoints.base import CheckResult, Connection, MessageRejected, Outbound, Transport, typed_or_problem


def _secret(url: str) -> str | Secret:
    return Secret(url) if has_url_password(url) else url


class AmqpTransport(Transport):
    name = "amqp"
    connection_type = AmqpConnection
    default_settings = {"url": "amqp://guest:guest@localhost:5672/"}
    replies = True
    accepts_secrets = True
    connection_options = AmqpConnectionOptions
    source_options = AmqpSourceOptions
    sink_options = AmqpSinkOptions
    connection_shorthand = "url"
    source_meta = ("routing_key", "exchange", "headers", "correlation_id", "reply_to", "message_id")

    def connection_problems(self, options: AmqpConnectionOptions) -> CheckResult:
        problems = list(amqp_cluster.check_urls(options, redact))
        yield from problems
        if not problems:
            yield from amqp_tls.tls_problems(options, amqp_cluster.connection_urls(options))

    def key_files(self, settings: AmqpConnectionOptions | Mapping[str, Any]) -> Iterable[str]:
        """The TLS files: a renewed certificate or CA changes the connection's fingerprint,
        and the reload the watcher starts reopens the connection with it."""
        options, _ = typed_or_problem(AmqpConnectionOptions, settings)
        return amqp_tls.key_files(options) if options is not None else []

    def source_problems(self, options: AmqpSourceOptions, mapping: str | None) -> CheckResult:
        written = given(options)
        if "queue" not in written and "exchange" not in written:
            yield None, "an amqp source needs a queue, an exchange, or both"
        if "binding_key" in written and not options.exchange:
            yield "binding_key", "binding_key needs an exchange to bind to"
        if "exchange_type" in written and not options.exchange:
            yield "exchange_type", "exchange_type is not used without an exchange to declare"
        yield from amqp_cluster.check_queue(options)

    def sink_problems(self, options: AmqpSinkOptions, mapping: str | None) -> CheckResult:
        written = given(options)
        if "exchange" not in written and "routing_key" not in written:
            yield None, "an amqp sink needs an exchange and/or a routing_key"
        problem = template_problem(options.routing_key)
        if problem:
            yield "routing_key", problem
        for key in ("exchange_type", "durable"):
            if key in written and not options.exchange:
                yield key, f"{key} is not used: the default exchange is never declared (name an exchange)"

    async def source_retired(
        self, connection: Connection, route: str, options: AmqpSourceOptions,
        remaining: Iterable[tuple[str, AmqpSourceOptions]],
    ) -> None:
        from engine.endpoints.amqp.topology import retire_source

        await retire_source(connection, route, options, remaining)

    def canonical_fields(self, options: AmqpSinkOptions) -> Iterable[tuple[str, str]]:
        return [("routing_key", name) for name in template_fields(options.routing_key)]

    def default_connection_settings(self, env: Mapping[str, str]) -> Mapping[str, Any]:
        """``RABBITROS_AMQP_URL`` (``--local-broker`` sets it), else localhost; a local cluster
        (``--local-broker --cluster N`` sets ``RABBITROS_AMQP_URLS``): every node, replicated queues;
        ``RABBITROS_AMQP_CA_FILE`` (``--local-broker-tls`` sets it): the CA the node's TLS
        certificate is verified against."""
        cluster = env.get(URLS_ENV, "").split()
        if cluster:
            return {"urls": [_secret(url) for url in cluster], "queue_type": "quorum"}
        ca_file = env.get(CA_ENV)
        return {"url": _secret(env.get(URL_ENV, self.default_settings["url"])), **({"tls": {"ca_file": ca_file}} if ca_file else {})}

    def private_broker_warning(self, settings: AmqpConnectionOptions, env: Mapping[str, str]) -> str | None:
        private = env.get(URLS_ENV, "").split() or [env.get(URL_ENV, "")]
        urls = [reveal(url) for url in ([settings.url] if settings.url else settings.urls or ())]
        other = elsewhere(urls, private)
        if not other:
            return None
        return (f"names its own broker ({', '.join(redact_urls(url) for url in other)}), so {{private}} does not serve it "
                "and its routes use that broker; to use the private node, write the URL as "
                f"\"${{{URL_ENV}:-<the URL>}}\", or leave the connection out")

    def redelivers(self, options: AmqpSourceOptions) -> bool:
        """The broker requeues what the engine did not acknowledge."""
        return True

    supports_ordered = True
    shares_sources = True

    def ordered_source(self, options: AmqpSourceOptions, partitions: int = 1, key: str = "") -> AmqpSourceOptions:
        """A single active consumer: one instance at a time consumes the queue, in order; with
        ``partitions``, that many such classic queues behind a consistent-hash exchange (partitions.py)."""
        if partitions > 1:
            return evolve(options, ordered=True, partitions=partitions, partition_key=key)
        return evolve(options, ordered=True)

    def partition_problems(self, options: AmqpSourceOptions, partitions: int, key: str) -> CheckResult:
        """A consistent-hash exchange fed from the source's exchange by the routing key or a
        header: the source needs an exchange to bind it to, and classic queues (partitions.py)."""
        return partition_problems(options, key)

    def sink_dry_run(self, route: str, options: AmqpSinkOptions) -> Callable[[Outbound], str | None]:
        render = compile_template(options.routing_key)

        def routing_key(outbound: Outbound) -> str | None:
            try:
                return render(outbound.template_data)
            except MappingError as exc:
                raise MessageRejected(str(exc)) from None

        return routing_key

    def competing_consumers(self, route: str, options: AmqpSourceOptions) -> str | None:
        queue = options.queue
        return f"queue {queue!r}" if queue else None

    def connect(self, name: str, settings: AmqpConnectionOptions | Mapping[str, Any]) -> Connection:
        return AmqpConnection(name, settings)


TRANSPORT = AmqpTransport()
