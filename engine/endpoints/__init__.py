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
}
PROTOCOLS: tuple[str, ...] = tuple(_MODULES)


def transport(protocol: str) -> Transport:
    try:
        module = importlib.import_module(_MODULES[protocol])
    except KeyError:
        raise EndpointError(f"unknown protocol {protocol!r}") from None
    except ImportError as exc:
        raise EndpointError(f"{protocol} support is not installed ({exc})") from exc
    return module.TRANSPORT
