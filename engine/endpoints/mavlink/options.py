"""The MAVLink endpoint's options, declared once (engine/common/options.py): the connection (the
``mavlink:`` string and the keys beside it), sources and sinks.

Bounds a check below reports in its own words (``retries must be an integer >= 0``) are
schema-only keywords here; the check (settings.py, checks.py, transaction.py) enforces them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from engine.common.options import option
from engine.endpoints.base import EndpointOptions
from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.tunnel import DEFAULT_PAYLOAD_TYPE, TunnelSettings

_BYTE: dict[str, Any] = {"minimum": 0, "maximum": 255}
TARGET_FIELD = r"^(\{.*\}|[A-Za-z_][A-Za-z0-9_.-]*)$"
"""A sink target read from the canonical message (``"{vehicle}"``, ``"{target.system}"``), or
an agent's name (``uav2``: engine/language/agents.py, resolved by the route loader). What is
inside the braces is checked by the engine's one template grammar (checks.py, through
engine/common/placeholders.py ``whole_field``), which says what is wrong in words."""
AGENT_NAME = r"^[A-Za-z_][A-Za-z0-9_.-]*$"
"""An agent's name where a number is wanted (``system_id: uav2``)."""
_SERIAL = TunnelSettings.from_settings(None, serial=True)
_NETWORK = TunnelSettings.from_settings(None, serial=False)


def _tunnel_default(name: str, unit: str = "") -> str:
    """The tunnel's default for ``name`` on each kind of link, as the docs show it."""
    serial, network = getattr(_SERIAL, name), getattr(_NETWORK, name)
    if serial == network:
        return f"default {serial}{unit}"
    return f"default {serial}{unit} on serial links, {network}{unit} on networks"


@dataclass(frozen=True, kw_only=True)
class MavlinkAcceptedKey:
    __schema_description__ = ("a previous key, still accepted on incoming frames until a deadline, during a fleet-wide "
                              "key rotation; outgoing frames always use key_file/key_env")

    key_file: str = option(description="file holding the old key (32 bytes, or 64 hex digits)")
    until: str = option(description="ISO 8601 time with a zone (2026-12-01T00:00:00Z): frames signed with this key are refused from then on")


@dataclass(frozen=True, kw_only=True)
class MavlinkSigning:
    __schema_description__ = ("MAVLink 2 signing with a 32-byte key: what we send is signed; unsigned, forged and "
                              "replayed frames are dropped and counted (status: link rejections); without signing, nothing is signed or checked")

    key_file: str | None = option(None, description="file holding the key (32 bytes, or 64 hex digits); give key_file or key_env. "
                                                     "A new key written there reopens the connection")
    key_env: str | None = option(None, description="environment variable holding the key (32 bytes or 64 hex digits), instead of key_file")
    link_id: int = option(0, **_BYTE, description="link id in our signatures")
    timestamp_file: str | None = option(None, description="file keeping the signing timestamp across restarts, so a restart never "
                                                          "reuses one (its directory must exist); without it, the clock alone")
    allow_unsigned: tuple[str, ...] = option(("RADIO_STATUS",),
                                             description="message names accepted unsigned (a SiK radio's RADIO_STATUS is never signed)")
    accept: tuple[MavlinkAcceptedKey, ...] = option((), description="old keys accepted on incoming frames until their deadline "
                                                    "(a key rotation: vehicles switch one by one)")


@dataclass(frozen=True, kw_only=True)
class MavlinkTunnel:
    """JSON-over-TUNNEL protocol tuning; an absent value takes the link's default
    (engine/endpoints/mavlink/tunnel/hub.py ``TunnelSettings``: a SiK radio needs patience)."""

    __schema_description__ = "tuning of JSON over TUNNEL (json_tunnel routes); an absent value takes the link's default"

    fragment_size: float | None = option(None, minimum=0, description=f"data bytes per TUNNEL frame; {_tunnel_default('fragment_size')}")
    rto_min: float | None = option(None, minimum=0, description=f"seconds: the shortest retransmission timeout; {_tunnel_default('rto_min')}")
    rto_max: float | None = option(None, minimum=0, description=f"seconds: the longest retransmission timeout (it doubles per unanswered timeout); {_tunnel_default('rto_max')}")
    retries: float | None = option(None, minimum=0, description=f"timeouts without progress before a send fails (its source then redelivers the message); {_tunnel_default('retries')}")
    sack_delay: float | None = option(None, minimum=0, description=f"seconds of silence after which a receiver missing fragments reports its gaps; {_tunnel_default('sack_delay')}")
    window: float | None = option(None, minimum=0, description=f"transfers (messages or bundles) in flight per sink; {_tunnel_default('window')}")
    rate: float | None = option(None, minimum=0, description="bytes/s for DATA frames; default 0: the link's budget (half the serial rate on serial links, unpaced on networks)")
    reassembly_timeout: float | None = option(None, minimum=0, description=f"seconds a partly received message is kept; {_tunnel_default('reassembly_timeout')}")
    memory: float | None = option(None, minimum=0, description=f"ids of delivered messages remembered, so a repeat is not delivered twice; {_tunnel_default('memory')}")
    memory_ttl: float | None = option(None, minimum=0, description=f"seconds a delivered id is remembered; {_tunnel_default('memory_ttl')}")
    bundle: float | None = option(None, minimum=0, description=f"largest bundle of queued messages sent as one transfer, bytes of its body, 0: each on its own; {_tunnel_default('bundle')}")


@dataclass(frozen=True, kw_only=True)
class MavlinkConnectionOptions:
    """``connections.<name>``: ``mavlink: URL`` and the keys beside it."""

    __schema_description__ = "one MAVLink 2 link (common dialect); its other keys sit beside mavlink:"

    url: str = option(description="pymavlink-style connection string: /dev/ttyUSB0, udpin:0.0.0.0:14550, udpout:, tcp:, tcpin:")
    baud: int | None = option(None, minimum=1200, description="bits/s of a serial link (57600 for a SiK radio); default 57600")
    source_system: int = option(255, minimum=1, maximum=255, description="our MAVLink system id (255: a ground station)")
    source_component: int = option(190, **_BYTE, description="our MAVLink component id (190: MAV_COMP_ID_MISSIONPLANNER)")
    signing: MavlinkSigning | None = option(None)
    rate: float | None = option(None, exclusive_minimum=0, description="bytes/s cap on everything written; default baud/10 on serial links, unpaced on networks")
    budget: float | None = option(None, exclusive_minimum=0,
                                  description="bytes/s the routes' frames (message sinks and tunnel fragments) may take at most; "
                                              "the radio's RADIO_STATUS (buffer filling, fading signal) lowers it from there. "
                                              "Default tunnel.rate if set, else half the serial rate on serial links "
                                              "(2,880 B/s at 57,600 baud, about what a SiK radio carries one way); networks "
                                              "are not paced. Commands, missions, acknowledgements and heartbeats are outside it")
    heartbeat: float = option(1.0, minimum=0,
                              description="Hz of our HEARTBEAT, 0 = none (a SiK radio injects RADIO_STATUS only after one)")
    heartbeat_timeout: float = option(3.0, exclusive_minimum=0,
                                      description="seconds without a HEARTBEAT after which a vehicle heard on the link is "
                                                  "down: /healthz answers 503 naming it, rabbitros_vehicle_up is 0, and "
                                                  "commands and missions to it fail at once (three missed 1 Hz heartbeats)")
    mav_type: int = option(mavlink2.MAV_TYPE_GCS, **_BYTE,
                           description="MAV_TYPE of our HEARTBEAT: 6 ground station, 18 onboard controller")
    tunnel: MavlinkTunnel | None = option(None)
    split_over_workers: bool = option(False, description="udpin links under run --workers N: the link's vehicles are split over "
                                                         "the workers by system id (one worker holds the socket and hands each "
                                                         "vehicle's frames to its worker; every worker runs the link's routes and "
                                                         "sends through it). Without --workers it changes nothing. Not with "
                                                         "signing nor json_tunnel sinks")


@dataclass(frozen=True, kw_only=True)
class MavlinkSourceOptions(EndpointOptions):
    """A message source (``message``, or every message without it) or a JSON tunnel source.
    Every key a sink may name is declared so ``check`` can say where it applies instead."""

    __schema_description__ = ("MAVLink messages of one link, or canonical JSON over TUNNEL; a key the kind of "
                              "endpoint does not read is an error in check")

    message: str | None = option(None, description="MAVLink message name (GLOBAL_POSITION_INT, COMMAND_LONG...); a source "
                                                   "without message and json_tunnel takes every message; a sink with message "
                                                   "needs sink.mapping producing its fields")
    json_tunnel: bool = option(False, description="carry canonical JSON in TUNNEL frames (fragmented, CRC-32, selectively "
                                                  "acknowledged: at-least-once over a lossy radio)")
    system_id: int | str | None = option(None, **_BYTE, pattern=AGENT_NAME,
                                         description="sources only: accept only messages from this system id (or the "
                                                     "agents table's agent of that name: its system_id)")
    component_id: int | None = option(None, **_BYTE, description="sources only: accept only messages from this component id")
    target_system: int | str | None = option(None, **_BYTE, pattern=TARGET_FIELD,
                                             description="sinks only: the receiver's system id (the message's target_system "
                                                         "when the mapping sets none; 1 for acknowledged commands and missions; "
                                                         "0, everyone, for a tunnel); an agent's name: its system_id; "
                                                         "\"{field}\": a message, command or mission sink takes it from "
                                                         "that canonical field of each message (an id, or an agent's name)")
    target_component: int | str | None = option(None, **_BYTE, pattern=TARGET_FIELD,
                                                description="sinks only: the receiver's component id (as target_system; "
                                                            "1 for acknowledged commands and missions)")
    payload_type: int = option(DEFAULT_PAYLOAD_TYPE, minimum=32768, maximum=65535,
                               description="json_tunnel: TUNNEL payload type of the channel (default 0xA900), so several tunnels can share a link")


@dataclass(frozen=True, kw_only=True)
class MavlinkSinkOptions(MavlinkSourceOptions):
    """A message sink, an acknowledged command sink (``acknowledged``) or a mission upload
    (``mission: upload``); the transaction options are resolved by ``TransactionOptions``."""

    __schema_description__ = ("send a MAVLink message, an acknowledged command (acknowledged: true), a mission "
                              "(mission: upload) or canonical JSON (json_tunnel: true)")

    mission: str | None = option(None, schema={"enum": ["upload"]},
                                 description="upload: the canonical mission's waypoints (each at its one altitude: alt_msl in "
                                             "MAV_FRAME_GLOBAL_INT or alt_rel in MAV_FRAME_GLOBAL_RELATIVE_ALT_INT), or the items "
                                             "sink.mapping produces, with the MAVLink mission protocol, accepted once the "
                                             "vehicle's MISSION_ACK says so")
    acknowledged: bool = option(False, description="COMMAND_LONG/COMMAND_INT: accepted only once the target's COMMAND_ACK says "
                                                   "MAV_RESULT_ACCEPTED; a refusal (DENIED, FAILED, UNSUPPORTED, "
                                                   "TEMPORARILY_REJECTED) is an answer (see refusals); silence is sent "
                                                   "again within command_timeout")
    home_placeholder: bool = option(False, description="mission: ArduPilot's seq-0 home item first")
    mission_type: str | int | None = option(None, description="mission: MAV_MISSION_TYPE_MISSION (default), _FENCE or _RALLY, "
                                                              "by name, short name (fence) or number")
    timeout: float | None = option(None, description="acknowledged commands, missions: seconds to wait for each answer before "
                                                     "sending again, >= 0.05; default 1.5 on serial links, 0.5 on networks")
    retries: int | None = option(None, schema={"minimum": 0}, description="acknowledged commands, missions: sends again after a "
                                                                          "timeout before the send fails (its source then "
                                                                          "redelivers); default 5")
    vehicle_timeout: float | None = option(None, description="acknowledged commands, missions: seconds to wait for a target not "
                                                             "heard yet (no HEARTBEAT), within command_timeout; default 10")
    command_timeout: float | None = option(None, description="acknowledged commands, missions: seconds from when the route "
                                                             "received the message (a mission: from the vehicle's last "
                                                             "answer) after which nothing more is sent and the message "
                                                             "fails for good, naming the vehicle and when it was last "
                                                             "heard: a late vehicle never acts on a stale command. >= 0.05; "
                                                             "default (retries + 1) x timeout: 3 s on networks, 9 s on "
                                                             "serial links")
    refusals: str | None = option(None, schema={"enum": ["reply", "dead_letter"]},
                                  description="acknowledged commands: what a refusal (COMMAND_ACK DENIED, FAILED, "
                                              "UNSUPPORTED, or TEMPORARILY_REJECTED until command_timeout) is. reply "
                                              "(default): an answer, replied through reply.mapping as {kind: result, "
                                              "result: MAV_RESULT_DENIED, command} and counted refused, not a dead "
                                              "letter; dead_letter: a dead letter naming the result")
    in_progress_timeout: float | None = option(None, description="acknowledged commands: how long MAV_RESULT_IN_PROGRESS extends "
                                                                 "the wait for the final COMMAND_ACK, seconds; default 30")
    retry_delay: float | None = option(None, description="acknowledged commands: seconds before sending again after "
                                                          "MAV_RESULT_TEMPORARILY_REJECTED; default 1")
