"""An independent vehicle for tests and benchmarks: MAVSDK's C++ core (the ``mavsdk`` wheel) as
an autopilot with its MissionRawServer, ActionServer and TelemetryServer.

It listens on ``udpin://127.0.0.1:PORT`` when given a port, or on any MAVSDK connection URL,
e.g. ``serial:///dev/pts/7:57600`` for the vehicle end of the emulated SiK radio
(rabbitros_sim/sik_radio.py): MAVSDK opens the pseudo-terminal like a UART, so no forwarder
sits between the radio and the vehicle."""

from __future__ import annotations

import threading
from typing import Any

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action_server.action_server import ActionServer
from mavsdk.plugins.mission_raw_server.mission_raw_server import MissionRawServer, MissionRawServerResult
from mavsdk.plugins.telemetry_server.telemetry_server import Heading, Position, TelemetryServer, VelocityNed

LATITUDE_E7 = -220_000_000
STEP_E7 = 10  # a number is sent as LATITUDE_E7 + 10 n + 5: MAVSDK's rounding of degrees to degE7 cannot move it


class MavsdkAutopilot:
    """Records the missions uploaded to it, the transfers that did not complete (a lost answer
    over a lossy radio makes the ground station start again) and the arm commands it
    acknowledged (from MAVSDK's threads)."""

    def __init__(self, connection: int | str) -> None:
        self.missions: list[list[Any]] = []
        self.failed_transfers: list[MissionRawServerResult] = []
        self.arm_requests: list[Any] = []
        self._lock = threading.Lock()
        self._config = Configuration.create_with_component_type(ComponentType.AUTOPILOT)
        self.mavsdk = Mavsdk(self._config)
        self.mavsdk.add_any_connection(f"udpin://127.0.0.1:{connection}" if isinstance(connection, int) else connection)
        component = self.mavsdk.server_component(0)
        self.mission_server = MissionRawServer(component)
        self.action_server = ActionServer(component)
        self.telemetry_server = TelemetryServer(component)
        self.action_server.set_armable(True, True)
        self.action_server.set_disarmable(True, True)
        self.mission_server.subscribe_incoming_mission(self._on_mission)
        self.action_server.subscribe_arm_disarm(self._on_arm)

    def publish_position(self, number: int) -> None:
        """Send one GLOBAL_POSITION_INT now that carries ``number`` in its ``lat`` (:func:`position_number`
        reads it back): MAVSDK stamps ``time_boot_ms`` from its own clock, so a receiver that wants
        the send time looks ``number`` up in the sender's record."""
        latitude = (LATITUDE_E7 + STEP_E7 * number + STEP_E7 // 2) / 1e7
        self.telemetry_server.publish_position(Position(latitude, -47.9, 600.0, 20.0),
                                               VelocityNed(0.0, 0.0, 0.0), Heading(0.0))

    def _on_mission(self, result: Any, plan: Any, _: Any) -> None:
        with self._lock:
            if result == MissionRawServerResult.SUCCESS:
                self.missions.append(list(plan.mission_items))
            else:
                self.failed_transfers.append(result)

    def _on_arm(self, result: Any, arm: Any, _: Any) -> None:
        with self._lock:
            self.arm_requests.append(arm)

    def close(self) -> None:
        self.mission_server.destroy()
        self.action_server.destroy()
        self.telemetry_server.destroy()
        self.mavsdk.destroy()


def position_number(lat_e7: int) -> int:
    """The ``number`` a :meth:`MavsdkAutopilot.publish_position` sent, from the ``lat`` received."""
    return (lat_e7 - LATITUDE_E7) // STEP_E7
