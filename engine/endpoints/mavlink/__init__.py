"""MAVLink 2 (pymavlink's dialect, our own asyncio link): the transport (transport.py, the
registry's face, which says how the endpoint works) and its parts, one module per concern
(options.py, errors.py, settings.py, links.py, port.py, connection.py, messages.py,
command.py, mission.py, tunnel/, ...; transport.py lists them). Besides ``TRANSPORT``, the
package names what tests, benches and the simulator build messages and links with."""

from engine.endpoints.mavlink.codec import MESSAGES, build_message, field_specs, mavlink2, message_fields
from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.endpoints.mavlink.settings import Address, LinkConfig, parse_address, settings_problems
from engine.endpoints.mavlink.signing import signing_now
from engine.endpoints.mavlink.transport import TRANSPORT, MavlinkTransport

__all__ = [
    "MESSAGES", "TRANSPORT", "Address", "LinkConfig", "MavlinkConnection", "MavlinkTransport",
    "build_message", "field_specs", "mavlink2", "message_fields", "parse_address", "settings_problems", "signing_now",
]
