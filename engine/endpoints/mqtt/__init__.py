"""MQTT (5 and 3.1.1) endpoint on aiomqtt and paho-mqtt 2; see link.py for the session,
acknowledgement and dispatch, source.py and sink.py for the routes' two ends, errors.py for
the one table of library failures, broker.py for a private mosquitto.

aiomqtt because it is the maintained asyncio client on paho (the reference Python MQTT
implementation, both protocol versions, shared subscriptions, MQTT 5 properties), runs on
the engine's own event loop without a thread, and leaves paho reachable for what it does not
wrap yet (manual acknowledgement).
"""

from engine.endpoints.mqtt.transport import TRANSPORT

__all__ = ["TRANSPORT"]
