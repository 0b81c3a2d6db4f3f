"""MAVLink 2 endpoint: telemetry in, commands, missions and JSON (TUNNEL) out, on one shared link.

A connection owns one link (serial device, ``udpin:``, ``udpout:``, ``tcp:``, ``tcpin:``)
driven by asyncio, not by pymavlink's blocking ``mavutil``: a reader cuts frames itself
(framing.py: a datagram on its own, a rejected frame costs only itself) and decodes them with
pymavlink, and one writer packs and writes every frame. Packing at write time keeps sequence numbers and signing timestamps in
wire order, which a receiver requires. The writer paces to the link rate (a SiK radio's
serial buffer is a few hundred bytes to 2 KB and overflows silently), sends control frames
(commands, missions, acknowledgements) first and the routes' frames by their ``priority``
(high, normal, low; engine/endpoints/mavlink/port.py), and slows bulk traffic when the radio's
RADIO_STATUS reports a filling buffer.

Signing (MAVLink 2): outgoing frames are signed by pymavlink; incoming signatures are
verified here rather than by pymavlink because pymavlink records a stream's timestamp before
checking the signature, so one forged frame with a far-future timestamp would make every
genuine frame of that stream look replayed. Rejections are counted in :attr:`MavlinkConnection.stats`,
which the engine status shows per connection (:meth:`MavlinkConnection.health`).

Settings (YAML ``connections.<name>.mavlink``)::

    url: /dev/ttyUSB0 | udpin:HOST:PORT | udpout:HOST:PORT | tcp:HOST:PORT | tcpin:HOST:PORT
    baud: 57600                  # serial only
    source_system: 255
    source_component: 190
    signing: {key_file: PATH | key_env: VAR, link_id: 0, timestamp_file: PATH,
              allow_unsigned: [RADIO_STATUS]}
    rate: BYTES_PER_S            # default baud/10 on serial, unpaced on networks
    heartbeat: 1.0               # Hz, 0 = none (a SiK radio injects RADIO_STATUS only after one)
    heartbeat_timeout: 3.0       # s without a vehicle's HEARTBEAT: down (liveness.py)
    mav_type: 6                  # MAV_TYPE of our HEARTBEAT (6 GCS, 18 onboard controller)
    tunnel: {fragment_size, rto_min, rto_max, retries, sack_delay, window, bundle, rate, ...}
    split_over_workers: false    # udpin under run --workers N: the vehicles split over the workers (split.py)

Source options: ``message`` (optional), ``system_id``, ``component_id``; or ``json_tunnel:
true`` with ``payload_type``. Sink options: ``message``, ``target_system``,
``target_component`` (defaults for those fields); or ``json_tunnel: true`` with
``payload_type``, ``target_system``, ``target_component``. Acknowledged commands and missions
add their own options (:mod:`.command`, :mod:`.mission`). An option the kind of endpoint does
not read (``payload_type`` without ``json_tunnel``, ``acknowledged`` on a message that is not a
command, mission options on a message sink, ``system_id`` on a sink) is an error in ``check``.

Delivery: sources hand messages to the route in batches (``Deliver.batch``). Telemetry waits in
a bounded inbox (the route's ``overflow``; ``block`` drops the oldest, as a radio link cannot be
paused); a JSON tunnel message is acknowledged to its sender only once every route settled it.
Sinks raise :class:`~engine.endpoints.base.MessageRejected` for what can never be sent (a field
out of range, a message too large for the tunnel, a refusal) and
:class:`~engine.endpoints.base.EndpointError` when the far end does not answer. A field the sink
mapping sets to null is refused before that, at the pipeline's ``sink mapping`` stage
(:meth:`MavlinkTransport.sink_field_check`): a field is never guessed (:mod:`.codec`).

This module is the protocol's face to the registry (the :class:`MavlinkTransport`: options,
checks, dry runs, the contract's questions). Modules, one per concern: :mod:`.options` (typed
options), :mod:`.errors` (the link's failures as the two edge errors), :mod:`.dialect`
(pymavlink's tables), :mod:`.settings` (connection settings), :mod:`.links` (serial, UDP, TCP),
:mod:`.signing`, :mod:`.codec` (messages as dicts), :mod:`.port` (paced writer and reader),
:mod:`.connection` (heartbeat, vehicles heard, dispatch), :mod:`.contract` (what the route
endpoints need of the connection), :mod:`.messages` (route endpoints), :mod:`.mission` and
:mod:`.command` (transactions the vehicle acknowledges), :mod:`.enums` (enum names for
mappings), :mod:`.checks` (static checks), :mod:`.tunnel` (JSON over TUNNEL), :mod:`.split` (a
``udpin`` link's vehicles split over the workers of ``run --workers N``; its locks in
:mod:`.split_leases`, its local sockets in :mod:`.split_sockets`). No module
imports one that imports it back.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from engine.common.suggest import closest
from engine.endpoints.base import CheckResult, FieldProblem, Outbound, Transport, flat_field_problem, typed, typed_or_problem
from engine.endpoints.mavlink import settings as _settings
from engine.endpoints.mavlink.checks import sink_problems, source_problems
from engine.endpoints.mavlink.codec import ADDED_FIELDS, MESSAGES, build_message, message_fields, received_nan
from engine.endpoints.mavlink.command import COMMAND_ANSWER
from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.endpoints.mavlink.messages import dry_run, field_check, target_fields
from engine.endpoints.mavlink.mission import MISSION_ANSWER
from engine.endpoints.mavlink.options import MavlinkConnectionOptions, MavlinkSinkOptions, MavlinkSourceOptions
from engine.endpoints.mavlink.settings import settings_problems
from engine.endpoints.workers import ConnectionShare


@functools.lru_cache(maxsize=1)
def message_names() -> dict[str, tuple[str, ...]]:
    """Each message of the dialect with its fields, plus the fields the source adds."""
    return {name: tuple(cls.fieldnames) + ADDED_FIELDS.get(name, ()) for name, cls in MESSAGES.items()}


class MavlinkTransport(Transport):
    name: ClassVar[str] = "mavlink"
    connection_type = MavlinkConnection
    default_settings: ClassVar[Mapping[str, Any]] = {"url": "udpin:0.0.0.0:14550"}
    connection_options = MavlinkConnectionOptions
    source_options = MavlinkSourceOptions
    sink_options = MavlinkSinkOptions
    connection_shorthand = "url"
    options_beside = True
    source_meta = ("system_id", "component_id", "message", "connection", "agent")
    agent_options = {"system_id": "system_id", "target_system": "system_id"}

    def meta_names(self, options: MavlinkSourceOptions) -> tuple[str, ...]:
        """A JSON tunnel's messages carry their sender, not the connection's name (nor an agent's)."""
        return ("system_id", "component_id", "message") if options.json_tunnel else self.source_meta

    def looks_up_agents(self, options: MavlinkSinkOptions) -> bool:
        return bool(target_fields(options)) and not options.json_tunnel

    def queues_per_agent(self, options: MavlinkSourceOptions) -> bool:
        return not options.json_tunnel  # telemetry waits in the route's inbox; a tunnel's sender holds its own

    def connection_problems(self, options: MavlinkConnectionOptions) -> CheckResult:
        return settings_problems(options)[1]

    def source_problems(self, options: MavlinkSourceOptions, mapping: str | None) -> CheckResult:
        return source_problems(options)

    def sink_problems(self, options: MavlinkSinkOptions, mapping: str | None) -> CheckResult:
        return sink_problems(options, mapping)

    def sink_field_check(self, options: MavlinkSinkOptions, mapping: str | None = None) -> Callable[[Any], None] | None:
        return field_check(options)

    def sink_dry_run(self, route: str, options: MavlinkSinkOptions) -> Callable[[Outbound], str | None]:
        build = dry_run(options)

        def built(outbound: Outbound) -> str | None:
            build(outbound)
            return None

        return built

    def test_input(self, options: MavlinkSourceOptions) -> Callable[[Any], dict[str, Any]] | None:
        """The message as the source gives it: its own fields (a null float is the NaN the
        source shows as null), plus those the source adds."""
        if options.json_tunnel or not options.message:
            return None
        mav_cls = MESSAGES[options.message]
        added = ADDED_FIELDS.get(options.message, ())

        def received(value: Any) -> dict[str, Any]:
            if not isinstance(value, Mapping):
                return message_fields(build_message(mav_cls, value))
            own = received_nan(mav_cls, {k: v for k, v in value.items() if k not in added})
            return {**message_fields(build_message(mav_cls, own)), **{k: value[k] for k in added if k in value}}

        return received

    def field_problem(self, options: MavlinkSourceOptions) -> FieldProblem | None:
        if options.json_tunnel or not options.message:
            return None
        fields = message_names().get(options.message)
        if fields is None:
            return None
        return lambda path: flat_field_problem(f"MAVLink {options.message}", fields, path)

    def reply_field_problem(self, options: MavlinkSinkOptions) -> FieldProblem | None:
        """A call's answer has fixed keys: an acknowledged command's (command.COMMAND_ANSWER),
        a mission upload's (mission.MISSION_ANSWER); other sinks answer nothing."""
        if options.mission is not None:
            return lambda path: flat_field_problem("a mission upload's answer", MISSION_ANSWER, path)
        if options.acknowledged:
            return lambda path: flat_field_problem("an acknowledged command's answer", COMMAND_ANSWER, path)
        return None

    def suggest(self, key: str, value: str) -> str | None:
        return closest(value, message_names()) if key == "message" else None

    def canonical_fields(self, options: MavlinkSinkOptions) -> Iterable[tuple[str, str]]:
        return target_fields(options)

    def exclusive_resource(self, settings: MavlinkConnectionOptions | Mapping[str, Any]) -> str | None:
        options, _ = typed_or_problem(MavlinkConnectionOptions, settings)
        return _settings.exclusive_resource(options) if options is not None else None

    def worker_affinity(self, connection: str, settings: MavlinkConnectionOptions | Mapping[str, Any]) -> str | None:
        """A link is one process's even where it holds no device (``udpout``, ``tcp``): the vehicle answers the
        address it heard last, and the link's heartbeats, sequence numbers and radio budget are its own (a link on
        a device or a listening port is placed by that exclusive resource instead)."""
        return f"mavlink link {connection!r}"

    def splits_connection(self, settings: MavlinkConnectionOptions | Mapping[str, Any]) -> bool:
        """``split_over_workers`` on a ``udpin`` link: its vehicles split over the workers (split.py)."""
        options, _ = typed_or_problem(MavlinkConnectionOptions, settings)
        return options is not None and options.split_over_workers and _settings.settings_problems(options)[0] is not None

    def split_connection(self, settings: MavlinkConnectionOptions | Mapping[str, Any], share: ConnectionShare) -> SplitSettings:
        return SplitSettings(typed(MavlinkConnectionOptions, settings, "mavlink connection"), share)

    def split_problems(self, side: str, options: MavlinkSourceOptions) -> list[tuple[str | None, str]]:
        """A JSON tunnel sink waits for the vehicle's TUNNEL acknowledgements, which reach the
        vehicle's own worker only (split.py)."""
        if side == "sink" and options.json_tunnel:
            return [("json_tunnel", "a json_tunnel sink cannot write to a connection with split_over_workers (its vehicle's "
                                    "acknowledgements reach the vehicle's own worker only); use a connection without it")]
        return []

    def key_files(self, settings: MavlinkConnectionOptions | Mapping[str, Any]) -> Iterable[str]:
        options, _ = typed_or_problem(MavlinkConnectionOptions, settings)
        return _settings.key_files(options) if options is not None else []

    def connect(self, name: str, settings: MavlinkConnectionOptions | SplitSettings | Mapping[str, Any]) -> MavlinkConnection:
        if isinstance(settings, SplitSettings):
            return MavlinkConnection(name, settings.options, settings.share)
        return MavlinkConnection(name, settings)


@dataclass(frozen=True)
class SplitSettings:
    """A connection's settings in one worker of ``run --workers N`` when it is split over them
    (``split_connection``): the typed options and the worker's place."""

    options: MavlinkConnectionOptions
    share: ConnectionShare


TRANSPORT = MavlinkTransport()
