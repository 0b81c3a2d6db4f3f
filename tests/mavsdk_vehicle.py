"""An independent vehicle for tests: MAVSDK's C++ core (the ``mavsdk`` wheel) as an autopilot
with its MissionRawServer and ActionServer, listening on ``udpin://127.0.0.1:PORT``."""

from __future__ import annotations

import threading
from typing import Any

from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action_server.action_server import ActionServer
from mavsdk.plugins.mission_raw_server.mission_raw_server import MissionRawServer


class MavsdkAutopilot:
    """Records the missions uploaded to it and the arm commands it acknowledged (from MAVSDK's threads)."""

    def __init__(self, port: int) -> None:
        self.missions: list[list[Any]] = []
        self.arm_requests: list[Any] = []
        self._lock = threading.Lock()
        self._config = Configuration.create_with_component_type(ComponentType.AUTOPILOT)
        self.mavsdk = Mavsdk(self._config)
        self.mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        component = self.mavsdk.server_component(0)
        self.mission_server = MissionRawServer(component)
        self.action_server = ActionServer(component)
        self.action_server.set_armable(True, True)
        self.action_server.set_disarmable(True, True)
        self.mission_server.subscribe_incoming_mission(self._on_mission)
        self.action_server.subscribe_arm_disarm(self._on_arm)

    def _on_mission(self, result: Any, plan: Any, _: Any) -> None:
        with self._lock:
            self.missions.append(list(plan.mission_items))

    def _on_arm(self, result: Any, arm: Any, _: Any) -> None:
        with self._lock:
            self.arm_requests.append(arm)

    def close(self) -> None:
        self.mission_server.destroy()
        self.action_server.destroy()
        self.mavsdk.destroy()
