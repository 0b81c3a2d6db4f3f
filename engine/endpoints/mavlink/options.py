"""The MAVLink endpoint's options, declared once (engine/options.py): the connection (the
``mavlink:`` string and the keys beside it), sources and sinks.

Bounds a check below reports in its own words (``retries must be an integer >= 0``) are
schema-only keywords here; the check (settings.py, checks.py, transaction.py) enforces them.
"""

from __future__ import annotations

from dataclasses import dataclass

from engine.endpoints.base import EndpointOptions
from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.tunnel import DEFAULT_PAYLOAD_TYPE
from engine.options import option

_BYTE = {"minimum": 0, "maximum": 255}


@dataclass(frozen=True, kw_only=True)
class MavlinkSigning:
    key_file: str | None = option(None)
    key_env: str | None = option(None)
    link_id: int = option(0, show_default=False, **_BYTE)
    timestamp_file: str | None = option(None)
    allow_unsigned: tuple[str, ...] = option(("RADIO_STATUS",), show_default=False,
                                             description="message names accepted unsigned (default: RADIO_STATUS)")


@dataclass(frozen=True, kw_only=True)
class MavlinkTunnel:
    """JSON-over-TUNNEL protocol tuning; an absent value takes the link's default
    (engine/endpoints/mavlink/tunnel.py ``TunnelSettings``: a SiK radio needs patience)."""

    __schema_description__ = "JSON-over-TUNNEL protocol tuning"

    fragment_size: float | None = option(None, minimum=0)
    rto_min: float | None = option(None, minimum=0)
    rto_max: float | None = option(None, minimum=0)
    retries: float | None = option(None, minimum=0)
    sack_delay: float | None = option(None, minimum=0)
    window: float | None = option(None, minimum=0)
    rate: float | None = option(None, minimum=0)
    reassembly_timeout: float | None = option(None, minimum=0)
    memory: float | None = option(None, minimum=0)
    memory_ttl: float | None = option(None, minimum=0)
    bundle: float | None = option(None, minimum=0)


@dataclass(frozen=True, kw_only=True)
class MavlinkConnectionOptions:
    """``connections.<name>``: ``mavlink: URL`` and the keys beside it."""

    url: str = option(description="pymavlink-style connection string: /dev/ttyUSB0, udpin:0.0.0.0:14550, udpout:, tcp:, tcpin:")
    baud: int | None = option(None, minimum=1200)
    source_system: int = option(255, show_default=False, minimum=1, maximum=255)
    source_component: int = option(190, show_default=False, **_BYTE)
    signing: MavlinkSigning | None = option(None)
    rate: float | None = option(None, exclusive_minimum=0, description="bytes/s cap on everything written; default baud/10 on serial")
    heartbeat: float = option(1.0, show_default=False, minimum=0,
                              description="Hz of our HEARTBEAT, 0 = none (a SiK radio injects RADIO_STATUS only after one)")
    mav_type: int = option(mavlink2.MAV_TYPE_GCS, show_default=False, **_BYTE,
                           description="MAV_TYPE of our HEARTBEAT: 6 ground station, 18 onboard controller")
    tunnel: MavlinkTunnel | None = option(None)


@dataclass(frozen=True, kw_only=True)
class MavlinkSourceOptions(EndpointOptions):
    """A message source (``message``, or every message without it) or a JSON tunnel source.
    Every key a sink may name is declared so ``check`` can say where it applies instead."""

    message: str | None = option(None, description="MAVLink message name, e.g. GLOBAL_POSITION_INT")
    json_tunnel: bool = option(False, show_default=False, description="carry canonical JSON in TUNNEL frames")
    system_id: int | None = option(None, **_BYTE)
    component_id: int | None = option(None, **_BYTE)
    target_system: int | None = option(None, **_BYTE)
    target_component: int | None = option(None, **_BYTE)
    payload_type: int = option(DEFAULT_PAYLOAD_TYPE, show_default=False, minimum=32768, maximum=65535)


@dataclass(frozen=True, kw_only=True)
class MavlinkSinkOptions(MavlinkSourceOptions):
    """A message sink, an acknowledged command sink (``acknowledged``) or a mission upload
    (``mission: upload``); the transaction options are resolved by ``TransactionOptions``."""

    mission: str | None = option(None, schema={"enum": ["upload"]},
                                 description="upload the canonical mission (or mapped items) with the mission protocol")
    acknowledged: bool = option(False, show_default=False,
                                description="COMMAND_LONG/COMMAND_INT: accepted only once the target's COMMAND_ACK says so")
    home_placeholder: bool = option(False, show_default=False, description="ArduPilot: a seq-0 home item first")
    mission_type: str | int | None = option(None)
    timeout: float | None = option(None, description="seconds per answer before sending again")
    retries: int | None = option(None, schema={"minimum": 0})
    vehicle_timeout: float | None = option(None, description="seconds to wait for a vehicle not heard yet")
    in_progress_timeout: float | None = option(None)
    retry_delay: float | None = option(None)
