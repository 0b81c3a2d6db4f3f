"""The one place where aiomqtt's and paho's failures become the engine's two edge errors.

As httpx's ``map_httpcore_exceptions`` does for its transport, every call into the MQTT
libraries runs inside :func:`mapped` (exceptions) or goes through :func:`from_code` (paho's
return codes and the broker's MQTT 5 reason codes), and this module alone decides which
failure is transient (:class:`EndpointError`: the engine retries, the message is redelivered)
and which can never succeed for this message (:class:`MessageRejected`: dead-lettered).
"""

from __future__ import annotations

import asyncio

import aiomqtt
from paho.mqtt.enums import MQTTErrorCode
from paho.mqtt.reasoncodes import ReasonCode

from engine.common.redaction import redact_urls
from engine.endpoints.base import EndpointError, ExceptionTable, MessageRejected

_EXCEPTIONS: tuple[tuple[type[BaseException], type[EndpointError]], ...] = (
    (ValueError, MessageRejected),  # paho: a topic with wildcards or a NUL, a payload over 256 MiB
    (aiomqtt.MqttError, EndpointError),  # refused CONNACK, timeouts, a lost connection
    (OSError, EndpointError),  # DNS, TCP, TLS (TimeoutError and ssl.SSLError are OSErrors)
    (asyncio.TimeoutError, EndpointError),
    (RuntimeError, EndpointError),  # paho: a publish that failed for a reason it does not name
)
"""Library exception -> edge error, first match wins."""

RETURN_CODES: dict[int, type[EndpointError]] = {
    MQTTErrorCode.MQTT_ERR_PAYLOAD_SIZE: MessageRejected,
    MQTTErrorCode.MQTT_ERR_INVAL: MessageRejected,
}
"""paho return codes that no retry can fix; every other failing code is transient."""

REASON_CODES: dict[int, type[EndpointError]] = {
    0x87: MessageRejected,  # Not authorized (publishing on this topic)
    0x90: MessageRejected,  # Topic Name invalid
    0x95: MessageRejected,  # Packet too large
    0x99: MessageRejected,  # Payload format invalid
}
"""MQTT 5 reason codes (>= 0x80 is a failure) of a PUBACK/PUBREC that refuse this message for
good; the others (quota exceeded, server busy, unspecified) are transient."""


def describe(error: BaseException) -> str:
    """``Type: text`` with any URL password hidden."""
    text = str(error) or type(error).__name__
    return redact_urls(f"{type(error).__name__}: {text}" if type(error).__name__ not in text else text)


EXCEPTIONS = ExceptionTable(_EXCEPTIONS, describe=describe)
edge_error = EXCEPTIONS.edge_error
mapped = EXCEPTIONS.mapped
"""Run a library call; its exceptions leave as the edge error naming ``where``."""


def from_code(code: int | ReasonCode, where: str) -> EndpointError | None:
    """None for success, else the edge error for a paho return code or an MQTT reason code."""
    if isinstance(code, ReasonCode):
        if not code.is_failure:
            return None
        kind = REASON_CODES.get(code.value, EndpointError)
        return kind(f"{where}: the broker answered {code.getName()} (0x{code.value:02x})")
    if code == MQTTErrorCode.MQTT_ERR_SUCCESS:
        return None
    kind = RETURN_CODES.get(int(code), EndpointError)
    return kind(f"{where}: {aiomqtt.MqttCodeError(code)}")
