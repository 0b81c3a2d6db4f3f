"""Our servers' ports (private brokers, admin endpoints) come from below the kernel's ephemeral
range, so that no outgoing connection can hold one while its server is down, and no client
retrying a connection to it can connect to itself (CI once saw a killed broker fail to listen
again on its port: the 2026-11-27 run, tests/faults/test_outage.py)."""

from __future__ import annotations

import socket
from pathlib import Path

from engine.common.processes import PORT_FLOOR, ephemeral_low, listening_port
from engine.endpoints.amqp.broker import BrokerTls, LocalBroker
from engine.endpoints.mqtt.broker import LocalMosquitto


def test_listening_ports_are_free_below_the_ephemeral_range_and_spread() -> None:
    low = ephemeral_low()
    assert low - PORT_FLOOR >= 1000, f"this machine's ephemeral range starts at {low}: nothing to draw from"
    ports = [listening_port() for _ in range(200)]
    assert all(PORT_FLOOR <= port < low for port in ports), sorted(ports)[:5] + sorted(ports)[-5:]
    assert len(set(ports)) >= 190, "parallel workers would pick the same ports"
    for port in ports[:20]:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", port))


def test_udp_ports_for_udpin_links_are_free_below_the_ephemeral_range() -> None:
    low = ephemeral_low()
    ports = [listening_port(kind=socket.SOCK_DGRAM) for _ in range(50)]
    assert all(PORT_FLOOR <= port < low for port in ports), sorted(ports)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", ports[0]))
        assert ports[0] not in {listening_port(kind=socket.SOCK_DGRAM) for _ in range(300)}


def test_a_port_in_use_or_excluded_is_not_given() -> None:
    taken = listening_port()
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", taken))
        holder.listen()
        assert taken not in {listening_port() for _ in range(300)}
    excluded = set(range(PORT_FLOOR, ephemeral_low() - 50))  # all but the range's last 50 ports
    assert all(listening_port(exclude=excluded) >= ephemeral_low() - 50 for _ in range(20))


def test_private_brokers_listen_below_the_ephemeral_range(tmp_path: Path) -> None:
    low = ephemeral_low()
    node = LocalBroker(tls=BrokerTls(tmp_path / "ca", tmp_path / "cert", tmp_path / "key"))
    mosquitto = LocalMosquitto()
    try:
        ports = {"amqp": node.port, "distribution": node.dist_port, "amqps": node.tls_port, "mqtt": mosquitto.port}
        assert all(port is not None and PORT_FLOOR <= port < low for port in ports.values()), ports
        assert len(set(ports.values())) == len(ports), ports
    finally:
        node.stop()
        mosquitto.stop()
