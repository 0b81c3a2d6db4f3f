"""Protocol endpoints. Each protocol is one module or package exposing ``TRANSPORT``; imported lazily
so that ``check`` of an AMQP-only directory does not need rclpy or pymavlink."""

from __future__ import annotations

import importlib

from engine.endpoints.base import EndpointError, Transport

_MODULES = {
    "amqp": "engine.endpoints.amqp",
    "ros2": "engine.endpoints.ros2",
    "mavlink": "engine.endpoints.mavlink",
    "mqtt": "engine.endpoints.mqtt",
    "zenoh": "engine.endpoints.zenoh",
    "memory": "engine.endpoints.memory",
}
PROTOCOLS: tuple[str, ...] = tuple(_MODULES)
MAPPING_FUNCTIONS: dict[str, tuple[str, ...]] = {
    "engine.endpoints.mavlink.functions": ("stamp_usec", "stamp_boot_ms", "mav_enum", "mav_enum_value", "mav_flags"),
}
"""Each module whose ``Functions`` class adds functions to mappings, with their names, so
engine/language/mapping.py imports it only for a mapping that calls one (tests/running/test_endpoint_contract.py checks
that the names match the class)."""
PRIVATE_BROKERS: dict[str, str] = {
    "amqp": "engine.endpoints.amqp.broker",
    "mqtt": "engine.endpoints.mqtt.broker",
}
"""The module of each protocol's ``--local-broker`` (engine/ops/local_broker.py): its
``private_broker(cluster)`` and ``CHECK_ENV``. Imported only under ``--local-broker``."""


def protocol_of(connection: object) -> str | None:
    """The protocol whose package made ``connection`` (by the module of its class), or None."""
    module = type(connection).__module__
    return next((protocol for protocol, package in _MODULES.items()
                 if module == package or module.startswith(package + ".")), None)


def transport(protocol: str) -> Transport:
    try:
        module = importlib.import_module(_MODULES[protocol])
    except KeyError:
        raise EndpointError(f"unknown protocol {protocol!r}") from None
    except ImportError as exc:
        raise EndpointError(f"{protocol} support is not installed ({exc})") from exc
    return module.TRANSPORT
