"""Two hosts on one machine: network namespaces joined by a veth pair.

Used by the paper's round-trip experiments: the GCS (broker and engine) runs in one
namespace, the robot in the other, so ROS 2 traffic really crosses a network link. Fast
DDS is told to use UDP only (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``), otherwise it would
shortcut through shared memory, which both namespaces see.
"""

from __future__ import annotations

import json
import os
import subprocess
import uuid
from dataclasses import dataclass

DDS_OVER_UDP = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


class NamespacesUnavailable(RuntimeError):
    pass


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if result.returncode != 0:
        raise NamespacesUnavailable(f"ip {' '.join(args)}: {result.stderr.strip()}")


@dataclass
class Host:
    namespace: str
    address: str

    def command(self, *argv: str) -> list[str]:
        return ["ip", "netns", "exec", self.namespace, *argv]


class TwoHosts:
    """``with TwoHosts() as (gcs, uav):`` two namespaces on 10.213.<n>.0/24, torn down on exit."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:6]
        subnet = int(tag, 16) % 250 + 1
        self.gcs = Host(f"rr-gcs-{tag}", f"10.213.{subnet}.1")
        self.uav = Host(f"rr-uav-{tag}", f"10.213.{subnet}.2")
        self._veth = (f"vg{tag}", f"vu{tag}")

    def __enter__(self) -> tuple[Host, Host]:
        if os.geteuid() != 0:
            raise NamespacesUnavailable("network namespaces need root (ip netns add)")
        try:
            for host in (self.gcs, self.uav):
                _ip("netns", "add", host.namespace)
            _ip("link", "add", self._veth[0], "type", "veth", "peer", "name", self._veth[1])
            for host, veth in zip((self.gcs, self.uav), self._veth):
                _ip("link", "set", veth, "netns", host.namespace)
                _ip("-n", host.namespace, "addr", "add", f"{host.address}/24", "dev", veth)
                _ip("-n", host.namespace, "link", "set", veth, "up", "multicast", "on")
                _ip("-n", host.namespace, "link", "set", "lo", "up")
                _ip("-n", host.namespace, "route", "add", "224.0.0.0/4", "dev", veth)
        except (NamespacesUnavailable, OSError, subprocess.SubprocessError) as exc:
            self.__exit__()
            raise NamespacesUnavailable(str(exc)) from exc
        return self.gcs, self.uav

    def received_bytes(self, host: Host) -> int:
        """Bytes the host's end of the link has received: proof that traffic crossed it."""
        veth = self._veth[0] if host is self.gcs else self._veth[1]
        out = subprocess.run(["ip", "-n", host.namespace, "-s", "-j", "link", "show", "dev", veth],
                             capture_output=True, text=True, timeout=10, check=True).stdout
        return int(json.loads(out)[0]["stats64"]["rx"]["bytes"])

    def __exit__(self, *exc: object) -> None:
        for host in (self.gcs, self.uav):
            subprocess.run(["ip", "netns", "pids", host.namespace], capture_output=True, timeout=10)
            subprocess.run(["ip", "netns", "del", host.namespace], capture_output=True, timeout=20)
