"""The hot path's shortcuts give exactly what the libraries' own slow paths give.

``message_fields`` reads integer fields in one C call and ``PublishProperties`` encodes a
route's fixed AMQP properties once; both must stay byte-for-byte what pymavlink's
``format_attr`` and pamqp's ``Basic.Properties.marshal`` produce."""

from __future__ import annotations

import math

import pytest
from aiormq import spec
from pamqp.common import FieldTable

from engine.endpoints.amqp import PublishProperties
from engine.endpoints.mavlink.codec import MESSAGES, build_message, mavlink2, message_fields

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def _reference_fields(msg: mavlink2.MAVLink_message) -> dict:
    fields = {name: msg.format_attr(name) for name in msg.get_fieldnames()}
    for name, value in fields.items():
        if isinstance(value, float) and not math.isfinite(value):
            fields[name] = None
        elif isinstance(value, list):
            fields[name] = [None if isinstance(v, float) and not math.isfinite(v) else v for v in value]
    return fields


def _decoded(msg: mavlink2.MAVLink_message) -> mavlink2.MAVLink_message:
    sender, parser = mavlink2.MAVLink(None, 1, 1), mavlink2.MAVLink(None)
    (decoded,) = parser.parse_buffer(msg.pack(sender))
    return decoded


def test_message_fields_equal_format_attr_for_every_message_type() -> None:
    checked = 0
    for cls in MESSAGES.values():
        try:
            msg = _decoded(build_message(cls, {}))
        except Exception:  # a type pymavlink cannot pack with all-zero fields
            continue
        assert repr(message_fields(msg)) == repr(_reference_fields(msg)), cls.msgname
        checked += 1
    assert checked > 150


def test_message_fields_strings_floats_and_arrays() -> None:
    mav = mavlink2.MAVLink(None, 1, 1)
    for msg in (mav.statustext_encode(3, b"hello", 0, 0),
                mav.attitude_encode(1, float("nan"), 0.5, float("inf"), 0, 0, 0),
                mav.param_value_encode(b"ABC", float("nan"), 9, 10, 1),
                mav.tunnel_encode(1, 1, 2, 3, bytes(range(128)))):
        decoded = _decoded(msg)
        assert repr(message_fields(decoded)) == repr(_reference_fields(decoded))
    attitude = message_fields(_decoded(mav.attitude_encode(1, float("nan"), 0.5, float("inf"), 0, 0, 0)))
    assert attitude["roll"] is None and attitude["yaw"] is None and attitude["pitch"] == 0.5
    assert message_fields(_decoded(mav.statustext_encode(3, b"hello", 0, 0)))["text"] == "hello"


@pytest.mark.parametrize(("content_type", "delivery_mode", "route", "generation", "message_id"), [
    ("application/json", 2, "gnss", 1, "0123456789abcdef0123456789abcdef"),
    ("text/plain", 1, "é" * 60, 10**12, None),
    ("application/json", 2, "r", 0, "ü" * 80),
])
def test_publish_properties_encode_as_pamqp(content_type: str, delivery_mode: int, route: str,
                                            generation: int, message_id: str | None) -> None:
    headers: FieldTable = {"x-rabbitros-route": route, "x-rabbitros-generation": generation}
    fixed = PublishProperties.fixed(content_type, delivery_mode, headers)
    ours = PublishProperties(fixed, message_id)
    theirs = spec.Basic.Properties(content_type=content_type, delivery_mode=delivery_mode, headers=headers,
                                   message_id=message_id)
    assert ours.marshal() == theirs.marshal()
    assert ours == theirs
    decoded = spec.Basic.Properties()
    encoded = ours.marshal()
    decoded.unmarshal(int.from_bytes(encoded[:2], "big"), encoded[2:])
    assert decoded == theirs
