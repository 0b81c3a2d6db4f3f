"""A fleet-sized load (issue 20): 100 agents through templated routes, against the same load
through routes shared by many agents and through one hand-written route per agent, in one run.

* 50 ROS 2 robots (``robot1`` ... ``robot50``), each publishing ``/robotN/fix`` and
  ``/robotN/battery`` (std_msgs/String JSON) at 10 Hz, from one or two child processes with
  rclpy (:func:`robots`);
* 50 MAVLink vehicles (system ids 1-50), each from its own UDP socket, on a few ``udpin``
  links of at most 8 vehicles each ("a few UDP links", as a farm's radios would be),
  sending GLOBAL_POSITION_INT and ATTITUDE at 10 Hz and a HEARTBEAT at 1 Hz, from one child
  process with pymavlink (:func:`vehicles`);
* everything to one RabbitMQ exchange, routing key ``<agent>.<stream>``; and the other way
  a 1 Hz command to each agent: AMQP -> ``/robotN/cmd`` (String) and AMQP -> COMMAND_LONG with
  ``target_system`` the vehicle's id.

Each message carries its send time (wall clock, one machine): telemetry latency is measured
where the bench consumes it from RabbitMQ (:func:`consumer`, its own process, reading the
socket with bench/amqp_reader.py: the aiormq consumer it replaced took 0.32 of the 2 cores and
put the machine at ~86 % busy; the same templated run's telemetry p99 went from 96-130 ms to
10.5-12.2 ms in three quiet full runs), command latency where the robot or vehicle receives it.
Loss is counted per stream from sequence numbers (every message sent in the measured period
must arrive). The engine runs alone in its own process; its CPU time during the measured
period over the messages it carried (both ways) is its CPU per message.

Three ways of writing the same routes (``--modes``): ``templated`` (``for_each``: one route per
agent and stream, 300 routes), ``shared`` (:func:`shared_routes`: discovery and one route per
link, 116 routes, of which the 100 command routes) and ``hand_written`` (the 300 routes written
out); and ``reference``: no engine, the same bridge written directly on the client libraries
(bench/systems.py ``ref_fleet``: rclpy, pymavlink, aiormq with confirms, one process, the engine's loop)
in the engine's place, on the same load, consumer and accounting ("engine" figures are then
the reference process's). The engine's figures are stated as ratios of the reference's,
measured in the same run: on a 2-core machine the broker, the load generators and the bench's
consumer bound the latency of any bridge, and the reference measures that bound.

    .venv/bin/python -m bench.fleet                   # 60 s for each of the four modes
    .venv/bin/python -m bench.fleet --duration 10 --modes templated
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import pickle
import selectors
import socket
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any, cast

from bench import throughput as tp

REPO = Path(__file__).resolve().parent.parent
ROBOT_STREAMS = ("fix", "battery")
VEHICLE_STREAMS = ("position", "attitude")
STREAM_KINDS = ("ros2 fix", "ros2 battery", "mavlink position", "mavlink attitude", "command amqp->ros2",
                "command amqp->mavlink")
AGENTS_NICE = 10
"""``--agents-nice`` alone: on a farm the 100 agents are 100 other machines; here their simulators
take 0.4 of the 2 cores the bridge and the broker run on. At a lower priority they yield the
CPU to the bridge, the broker and the consumer when both want it, which is as close to other
machines as one machine comes. Latency stays honest: each message carries the time it was
actually sent. Off by default; the report says when it was on."""
PEERS_PER_LINK = 8
"""Vehicles per link: 50 vehicles on 7 links. A ``udpin`` link remembers up to 256 peers
(engine/endpoints/mavlink/links.py; it was 8, which this bench found)."""
COMMAND = 31010
"""MAV_CMD_USER_1: a command no autopilot acts on."""
REFERENCE = "reference"
"""The mode that runs no engine: the same bridge written on rclpy, pymavlink and aiormq
(bench/systems.py ``ref_fleet``), in its place on the same load: the figure the engine's are
a ratio of (the project's rule), and what this machine allows a fleet bridge at all."""
MODES = ("templated", "shared", "hand_written", REFERENCE)
LABELS = {"templated": "Templated routes (for_each)", "shared": "Shared routes (discovery, one per link)",
          "hand_written": "One hand-written route per agent", REFERENCE: "Reference (rclpy, pymavlink, aiormq; no engine)"}


# ---------------------------------------------------------------- the routes

def robot_names(count: int) -> list[str]:
    return [f"robot{n}" for n in range(1, count + 1)]


def links_for(vehicles: int) -> list[list[int]]:
    """System ids 1..vehicles spread over as few links as hold at most PEERS_PER_LINK each."""
    count = max(1, -(-vehicles // PEERS_PER_LINK))
    return [[sid for sid in range(1, vehicles + 1) if (sid - 1) % count == link] for link in range(count)]


def header(url: str, domain: int, ports: list[int]) -> list[str]:
    lines = ["connections:", f"  gcs: {{amqp: \"{url}\"}}", f"  ros: {{ros2: {{domain_id: {domain}, node: fleet_engine}}}}"]
    lines += [f"  link{index}: {{mavlink: \"udpin:127.0.0.1:{port}\", heartbeat: 1}}" for index, port in enumerate(ports)]
    return lines


def _robot_commands(cmd: str) -> str:
    """The robots' command route (one per robot of robots.yaml), as every templated way writes it."""
    return f"""  - name: "{{agent}}-cmd"
    for_each: robots.yaml
    source: {{amqp: {{connection: gcs, exchange: {cmd}, binding_key: "{{agent}}", queue: "{cmd}-{{agent}}"}}}}
    schema: raw_json
    sink: {{ros2: {{connection: ros, topic: "/{{agent}}/cmd"}}}}
"""


def templated_routes(names: dict[str, str], robots: int, links: list[list[int]]) -> tuple[str, str]:
    """The fleet in five templated routes (and the agents file they name)."""
    out, cmd = names["out"], names["cmd"]
    agents = "".join(f"- {{agent: {agent}}}\n" for agent in robot_names(robots))
    vehicles = ", ".join(f"{{sys: {sid}, agent: uav{sid}, link: link{index}}}" for index, ids in enumerate(links) for sid in ids)
    routes = f"""
routes:
  - name: "{{agent}}-{{stream}}"
    for_each: [{", ".join(f"{{agent: {a}, stream: {s}}}" for a in robot_names(robots) for s in ROBOT_STREAMS)}]
    source: {{ros2: {{connection: ros, topic: "/{{agent}}/{{stream}}"}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "{{agent}}.{{stream}}"}}}}
{_robot_commands(cmd)}  - name: "uav{{sys}}-position"
    for_each: &vehicles [{vehicles}]
    source: {{mavlink: {{connection: "{{link}}", message: GLOBAL_POSITION_INT, system_id: "{{sys}}"}}}}
    mapping: "{{agent: meta('agent'), seq: lat, time_boot_ms: time_boot_ms, alt_msl: mm_to_m(alt), heading: heading_cdeg_to_deg(hdg)}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "uav{{sys}}.position"}}}}
  - name: "uav{{sys}}-attitude"
    for_each: *vehicles
    source: {{mavlink: {{connection: "{{link}}", message: ATTITUDE, system_id: "{{sys}}"}}}}
    mapping: "{{agent: meta('agent'), seq: roll, time_boot_ms: time_boot_ms, pitch: pitch, yaw: yaw}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "uav{{sys}}.attitude"}}}}
  - name: "uav{{sys}}-cmd"
    for_each: *vehicles
    source: {{amqp: {{connection: gcs, exchange: {cmd}, binding_key: "uav{{sys}}", queue: "{cmd}-uav{{sys}}"}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: "{{link}}", message: COMMAND_LONG, target_system: "{{sys}}", target_component: 1}}
      mapping: "{{command: `{COMMAND}`, param1: t_ms, param2: seq}}"
"""
    return routes, agents


def shared_routes(names: dict[str, str], robots: int, links: list[list[int]]) -> tuple[str, str]:
    """The fleet as a user who knows discovery and the agents table writes it: one route per
    robot stream for every robot (``/{agent}/fix`` discovered), one per link and MAVLink message
    for every vehicle on it (no ``system_id``: the agents table names the vehicle), so each
    route takes its agents' messages in batches; the commands stay one route per agent (a
    route's queue and its target are the agent's). Returns (routes, the agents file)."""
    out, cmd = names["out"], names["cmd"]
    robots_file = "".join(f"- {{agent: {agent}}}\n" for agent in robot_names(robots))
    table = "".join(f"  uav{sid}: {{connection: link{index}, system_id: {sid}}}\n"
                    for index, ids in enumerate(links) for sid in ids)
    link_items = ", ".join(f"{{link: link{index}}}" for index in range(len(links)))
    routes = f"""
agents:
{table}
routes:
  - name: "robots-{{stream}}"
    for_each: [{", ".join(f"{{stream: {s}}}" for s in ROBOT_STREAMS)}]
    source: {{ros2: {{connection: ros, topic: "/{{agent}}/{{stream}}"}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "{{agent}}.{{stream}}"}}}}
{_robot_commands(cmd)}  - name: "{{link}}-position"
    for_each: &links [{link_items}]
    source: {{mavlink: {{connection: "{{link}}", message: GLOBAL_POSITION_INT}}}}
    mapping: "{{agent: meta('agent'), seq: lat, time_boot_ms: time_boot_ms, alt_msl: mm_to_m(alt), heading: heading_cdeg_to_deg(hdg)}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "{{agent}}.position"}}}}
  - name: "{{link}}-attitude"
    for_each: *links
    source: {{mavlink: {{connection: "{{link}}", message: ATTITUDE}}}}
    mapping: "{{agent: meta('agent'), seq: roll, time_boot_ms: time_boot_ms, pitch: pitch, yaw: yaw}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: "{{agent}}.attitude"}}}}
  - name: "{{agent}}-cmd"
    for_each: agents
    source: {{amqp: {{connection: gcs, exchange: {cmd}, binding_key: "{{agent}}", queue: "{cmd}-{{agent}}"}}}}
    schema: raw_json
    sink:
      mavlink: {{message: COMMAND_LONG, target_system: "{{agent}}", target_component: 1}}
      mapping: "{{command: `{COMMAND}`, param1: t_ms, param2: seq}}"
"""
    return routes, robots_file


def hand_written_routes(names: dict[str, str], robots: int, links: list[list[int]]) -> str:
    """The same routes as :func:`templated_routes` expands to, written out one per agent."""
    out, cmd = names["out"], names["cmd"]
    lines = ["routes:"]
    for agent in robot_names(robots):
        for stream in ROBOT_STREAMS:
            lines += [f"  - name: {agent}-{stream}",
                      f"    source: {{ros2: {{connection: ros, topic: /{agent}/{stream}}}}}",
                      "    schema: raw_json",
                      f"    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: {agent}.{stream}}}}}"]
        lines += [f"  - name: {agent}-cmd",
                  f"    source: {{amqp: {{connection: gcs, exchange: {cmd}, binding_key: {agent}, queue: {cmd}-{agent}}}}}",
                  "    schema: raw_json",
                  f"    sink: {{ros2: {{connection: ros, topic: /{agent}/cmd}}}}"]
    for index, ids in enumerate(links):
        for sid in ids:
            for stream, message, fields in (
                    ("position", "GLOBAL_POSITION_INT", "seq: lat, time_boot_ms: time_boot_ms, alt_msl: mm_to_m(alt), "
                                                        "heading: heading_cdeg_to_deg(hdg)"),
                    ("attitude", "ATTITUDE", "seq: roll, time_boot_ms: time_boot_ms, pitch: pitch, yaw: yaw")):
                lines += [f"  - name: uav{sid}-{stream}",
                          f"    source: {{mavlink: {{connection: link{index}, message: {message}, system_id: {sid}}}}}",
                          f"    mapping: \"{{agent: 'uav{sid}', {fields}}}\"",
                          "    schema: raw_json",
                          f"    sink: {{amqp: {{connection: gcs, exchange: {out}, routing_key: uav{sid}.{stream}}}}}"]
            lines += [f"  - name: uav{sid}-cmd",
                      f"    source: {{amqp: {{connection: gcs, exchange: {cmd}, binding_key: uav{sid}, queue: {cmd}-uav{sid}}}}}",
                      "    schema: raw_json",
                      "    sink:",
                      f"      mavlink: {{connection: link{index}, message: COMMAND_LONG, target_system: {sid}, target_component: 1}}",
                      f"      mapping: \"{{command: `{COMMAND}`, param1: t_ms, param2: seq}}\""]
    return "\n".join(lines) + "\n"


def write_routes(directory: Path, mode: str, url: str, domain: int, ports: list[int], names: dict[str, str],
                 robots: int, links: list[list[int]]) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    head = "\n".join(header(url, domain, ports))
    if mode in ("templated", "shared"):
        routes, agents = (templated_routes if mode == "templated" else shared_routes)(names, robots, links)
        (directory / "robots.yaml").write_text(agents)
        (directory / "fleet.yaml").write_text(head + "\n" + routes)
    else:
        (directory / "fleet.yaml").write_text(head + "\n" + hand_written_routes(names, robots, links))
    return directory


# ---------------------------------------------------------------- the load generators (child processes)

def _wait_file(path: Path, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _ms24() -> int:
    """Wall-clock milliseconds modulo 2^24: exact in a float32 command parameter."""
    return (time.time_ns() // 1_000_000) % (1 << 24)


def _ms32() -> int:
    """Wall-clock milliseconds modulo 2^32: a MAVLink ``time_boot_ms``."""
    return (time.time_ns() // 1_000_000) % (1 << 32)


def _paced(period: float, count: int, began: float, send: Any, stop: Path) -> int:
    """Call ``send(slot)`` for ``count`` agents' slots, each every ``period`` s, staggered over
    the period (a fleet does not publish in lockstep), until the ``stop`` file exists;
    returns the rounds sent. ``send(slot, round)``."""
    rounds = 0
    while not stop.exists():
        for slot in range(count):
            due = began + rounds * period + slot * period / count
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            send(slot, rounds)
        rounds += 1
    return rounds


def robots(args: dict[str, Any]) -> None:
    """``args``: domain, agents (names), rate, go/stop file paths. Publishes each agent's
    streams (JSON with seq and the send time) once every engine subscription matched, records
    the commands on ``/<agent>/cmd``; prints ``matched``, then ``result {...}`` at the end."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from bench.systems import _ros_context

    context, node = _ros_context(int(args["domain"]))
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    agents: list[str] = args["agents"]
    publishers = [(agent, stream, node.create_publisher(String, f"/{agent}/{stream}", qos))
                  for agent in agents for stream in ROBOT_STREAMS]
    commands: dict[str, list[int]] = {agent: [] for agent in agents}
    latencies: list[float] = []
    lock = threading.Lock()

    def on_command(agent: str, msg: Any) -> None:
        now = time.time_ns()
        body = json.loads(msg.data)
        with lock:
            commands[agent].append(int(body["seq"]))
            latencies.append((now - int(body["t_ns"])) / 1e6)

    subscriptions = [node.create_subscription(String, f"/{agent}/cmd", lambda msg, a=agent: on_command(a, msg), qos)
                     for agent in agents]
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (all(p.get_subscription_count() > 0 for _, _, p in publishers)
                                               and all(s.get_publisher_count() > 0 for s in subscriptions)):
        time.sleep(0.05)
    unmatched = sum(p.get_subscription_count() == 0 for _, _, p in publishers)
    print(f"matched {unmatched}", flush=True)
    go, stop, done = Path(args["go"]), Path(args["stop"]), Path(args["done"])
    if not _wait_file(go, 300):
        return
    message = String()
    streams = len(publishers)

    def send(slot: int, round_: int) -> None:
        agent, stream, publisher = publishers[slot]
        message.data = json.dumps({"agent": agent, "stream": stream, "seq": round_, "t_ns": time.time_ns(),
                                   "lat": -22.4 + slot * 1e-4, "lon": -47.5, "level": 0.9})
        publisher.publish(message)

    rounds = _paced(1.0 / float(args["rate"]), streams, time.monotonic(), send, stop)
    _wait_file(done, 120)
    with lock:  # the result first: what follows is teardown, which must not be able to lose it
        result = {"sent": {f"{agent}.{stream}": rounds for agent, stream, _ in publishers},
                  "commands": {agent: sorted(seqs) for agent, seqs in commands.items()}, "command_ms": latencies}
    print("result " + json.dumps(result), flush=True)
    # the spinning thread ends before the node and context go: destroyed under a spin that had
    # not yet seen the shutdown (1 s was not enough on a loaded CI machine), the process
    # aborted in C++ ("terminate called without an active exception") before its result
    executor.shutdown(timeout_sec=10)
    spinner.join(10)
    node.destroy_node()
    context.try_shutdown()


def vehicles(args: dict[str, Any]) -> None:
    """``args``: links ([[port, [system ids]]...]), rate, go/stop/done file paths. Every vehicle
    sends a HEARTBEAT at 1 Hz from the start, and from ``go`` GLOBAL_POSITION_INT (``lat`` =
    seq) and ATTITUDE (``roll`` = seq) at ``rate`` with ``time_boot_ms`` = the send time;
    records the COMMAND_LONGs addressed to it. Prints ``ready``, then ``result {...}``."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import common as mavlink2

    fleet = []  # (system id, socket, MAVLink, engine address)
    selector = selectors.DefaultSelector()
    for port, ids in args["links"]:
        for sid in ids:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sock.setblocking(False)
            mav = mavlink2.MAVLink(None, srcSystem=sid, srcComponent=1)
            mav.robust_parsing = True
            fleet.append((sid, sock, mav, ("127.0.0.1", int(port))))
            selector.register(sock, selectors.EVENT_READ, (sid, mav))
    commands: dict[int, list[int]] = {sid: [] for sid, *_ in fleet}
    latencies: list[float] = []
    foreign = [0]
    lock = threading.Lock()
    finished = threading.Event()

    def receive() -> None:
        while not finished.is_set():
            for key, _ in selector.select(0.05):
                sid, mav = key.data
                sock = cast(socket.socket, key.fileobj)  # only sockets are registered (above)
                try:
                    data = sock.recv(65535)
                except OSError:
                    continue
                now = _ms24()
                for msg in mav.parse_buffer(data) or ():
                    if msg.get_type() != "COMMAND_LONG":
                        continue
                    with lock:
                        if msg.target_system != sid:
                            foreign[0] += 1
                            continue
                        commands[sid].append(int(msg.param2))
                        latencies.append(float((now - int(msg.param1)) % (1 << 24)))

    def heartbeat(slot: int, _round: int) -> None:
        _, sock, mav, engine = fleet[slot]
        msg = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC, 0, 0, mavlink2.MAV_STATE_ACTIVE)
        try:
            sock.sendto(msg.pack(mav), engine)
        except OSError:
            pass

    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    go, stop, done = Path(args["go"]), Path(args["stop"]), Path(args["done"])
    beating = threading.Thread(target=_paced, args=(1.0, len(fleet), time.monotonic(), heartbeat, done), daemon=True)
    beating.start()
    print("ready", flush=True)
    if not _wait_file(go, 300):
        return
    streams = [(slot, stream) for slot in range(len(fleet)) for stream in VEHICLE_STREAMS]
    errors = [0]

    def send(index: int, round_: int) -> None:
        slot, stream = streams[index]
        sid, sock, mav, engine = fleet[slot]
        if stream == "position":
            msg = mav.global_position_int_encode(_ms32(), round_, -475000000, 612340, 35000, 120, -35, 4, 27000)
        else:
            msg = mav.attitude_encode(_ms32(), float(round_), 0.01, 1.5, 0.0, 0.0, 0.0)
        try:
            sock.sendto(msg.pack(mav), engine)
        except OSError:
            errors[0] += 1

    rounds = _paced(1.0 / float(args["rate"]), len(streams), time.monotonic(), send, stop)
    _wait_file(done, 120)
    finished.set()
    receiver.join(2)
    with lock:
        result = {"sent": {f"uav{fleet[slot][0]}.{stream}": rounds for slot, stream in streams},
                  "commands": {str(sid): sorted(seqs) for sid, seqs in commands.items()}, "command_ms": latencies,
                  "foreign_commands": foreign[0], "send_errors": errors[0]}
    print("result " + json.dumps(result), flush=True)


# ---------------------------------------------------------------- the run

class Telemetry:
    """What the bench's consumer (:func:`consumer`, a child process) received: while it runs
    only how many (its ``count`` lines); then every arrival, of which :meth:`digest` gives per
    stream the sequence numbers seen and per stream kind the end-to-end latencies (ms) of every
    message: all were sent during the load (the robots and vehicles send telemetry from ``go``
    to ``stop`` only), and those still arriving in the drain are its slowest. (Before e3d0fbf,
    what arrived after the commands' last confirm was counted, not timed: the tail was cut.)"""

    def __init__(self, child: Any) -> None:
        self.child = child
        self.seqs: dict[str, set[int]] = {}
        self.latency: dict[str, list[float]] = {kind: [] for kind in STREAM_KINDS}

    @property
    def count(self) -> int:
        for line in reversed(self.child.lines):
            if line.startswith("count "):
                return int(line.split()[1])
        return 0

    def digest(self, arrived: list[tuple[int, str, bytes]]) -> None:
        """Parse what arrived into ``seqs`` and ``latency`` (after the run)."""
        for now_ns, key, body in arrived:
            data = json.loads(body)
            if key.startswith("robot"):
                latency = (now_ns - int(data["t_ns"])) / 1e6
            else:
                latency = float((now_ns // 1_000_000 - int(data["time_boot_ms"])) % (1 << 32))
            self.seqs.setdefault(key, set()).add(int(data["seq"]))
            kind = ("ros2 " if key.startswith("robot") else "mavlink ") + key.rsplit(".", 1)[1]
            self.latency[kind].append(latency)


def consumer(args: dict[str, Any]) -> None:
    """``args``: url, exchange, out (a file), finish (a file's path). Binds a queue of its own to
    ``exchange`` (every routing key) and reads it with :class:`bench.amqp_reader.QueueReader`
    (why not aiormq: its docstring) until ``finish`` exists; prints ``ready``, ``count N`` at
    most every 0.2 s, and at the end writes every arrival to ``out`` (pickle) and prints ``done``."""
    from bench.amqp_reader import QueueReader

    reader = QueueReader(args["url"])
    reader.consume(reader.bind(args["exchange"], "#"))
    print("ready", flush=True)
    arrivals: list[tuple[int, str, bytes]] = []
    finish = Path(args["finish"])
    reported = [0.0, 0]

    def until() -> bool:
        now = time.monotonic()
        if now - reported[0] >= 0.2 and len(arrivals) != reported[1]:
            reported[:] = [now, len(arrivals)]
            print(f"count {len(arrivals)}", flush=True)
        return finish.exists()

    reader.read(arrivals.append, until)
    reader.close()
    Path(args["out"]).write_bytes(pickle.dumps(arrivals, protocol=pickle.HIGHEST_PROTOCOL))
    print("done", flush=True)


def _pcts(samples: list[float]) -> dict[str, Any]:
    if not samples:
        return {"n": 0}
    ms = sorted(samples)
    return {"n": len(ms), "p50": ms[len(ms) // 2], "p99": ms[min(len(ms) - 1, int(len(ms) * 0.99))], "max": ms[-1],
            "mean": statistics.fmean(ms)}


def _route_kind(route: str) -> str:
    """The stream kind of a fleet route's name (robot7-fix: ros2 fix, uav3-cmd: command amqp->mavlink)."""
    agent, stream = route.split("-", 1)
    if stream == "cmd":
        return "command amqp->ros2" if agent.startswith("robot") else "command amqp->mavlink"
    return ("ros2 " if agent.startswith("robot") else "mavlink ") + stream


def _rss_kib(child: tp.Child) -> int:
    """The largest VmRSS among the child's process group (the engine's Python process)."""
    best = 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) != child.process.pid:
                continue
            for line in (entry / "status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    best = max(best, int(line.split()[1]))
        except OSError:
            continue
    return best


class EngineWorkers:
    """``rabbitros-engine run --workers N`` in the bridge's place (issue 34), started as
    bench/bench_workers.py starts it (its status file says when every worker runs). With
    ``--workers 1`` the CLI runs one engine process (no supervisor); with N > 1 a supervisor
    and N workers, each in its own session: their CPU is read per process, not per group."""

    def __init__(self, routes: Path, workers: int, work: Path, env: dict[str, str] | None = None) -> None:
        from bench.bench_workers import EngineRun

        self.run = EngineRun(routes, workers, work, stats_interval=1.0, env=env)
        self.workers = workers
        self.processes: dict[str, int] = {}

    async def start(self) -> float:
        """Wait until every worker runs; the seconds it took."""
        began = time.perf_counter()
        pids = await self.run.running(timeout=300)
        if self.workers == 1:
            self.processes = {"engine": pids[0]}
        else:
            self.processes = {"supervisor": self.run.process.pid, **{f"worker {k}": pid for k, pid in enumerate(pids)}}
        return time.perf_counter() - began

    def cpu_seconds(self) -> float:
        return sum(tp.process_cpu_seconds(pid) for pid in self.processes.values())

    async def stop(self) -> None:
        await self.run.stop()


def _pid_usage(pid: int) -> tuple[float, int]:
    """(CPU seconds, VmRSS KiB) of one process; (0, 0) once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        rss = next((int(line.split()[1]) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                    if line.startswith("VmRSS:")), 0)
    except OSError:
        return 0.0, 0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), rss


def _group_members(group: int) -> list[int]:
    """Every process of process group ``group`` (the RabbitMQ node: beam.smp, epmd, its shells)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int(entry.joinpath("stat").read_text().rsplit(")", 1)[1].split()[2]) == group:
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


def _usage(processes: dict[str, list[int]]) -> dict[str, tuple[float, int]]:
    """Per name: the CPU seconds and the RSS (KiB) summed over its processes."""
    out = {}
    for name, pids in processes.items():
        usages = [_pid_usage(pid) for pid in pids]
        out[name] = (sum(cpu for cpu, _ in usages), sum(rss for _, rss in usages))
    return out


def _machine_ticks() -> tuple[int, int, int]:
    """The machine's CPU ticks from /proc/stat (every process of the host, including other
    sessions' that this one cannot see): (busy, of which niced, idle)."""
    user, nice, system, idle, iowait, irq, softirq, steal = (int(x) for x in Path("/proc/stat").read_text().split()[1:9])
    return user + nice + system + irq + softirq + steal, nice, idle + iowait


def _machine(before: tuple[int, int, int], wall: float) -> dict[str, float]:
    """The whole machine's busy cores over the measured period, and how much of it ran niced."""
    after, tick = _machine_ticks(), os.sysconf("SC_CLK_TCK")
    return {"busy_cores": round((after[0] - before[0]) / tick / wall, 2), "niced_cores": round((after[1] - before[1]) / tick / wall, 2),
            "idle_cores": round((after[2] - before[2]) / tick / wall, 2)}


def _per_process(before: dict[str, tuple[float, int]], after: dict[str, tuple[float, int]], wall: float) -> dict[str, Any]:
    """Each process's CPU over the measured period (s and cores) and its RSS at its end (MiB)."""
    return {name: {"cpu_s": round(after[name][0] - before[name][0], 2),
                   "cores": round((after[name][0] - before[name][0]) / wall, 3), "rss_mib": round(after[name][1] / 1024, 1)}
            for name in before}


async def run_mode(url: str, mode: str, robots_n: int, vehicles_n: int, duration: float, rate: float = 10.0,
                   command_rate: float = 1.0, publishers: int = 2, domain: int | None = None,
                   agents_nice: int = 0, workers: int = 0, broker_group: int = 0,
                   engine_env: dict[str, str] | None = None) -> dict[str, Any]:
    """One measurement: the engine on the fleet's routes written ``mode`` (templated, shared or
    hand_written), or the reference bridge in its place (``reference``), the load for
    ``duration`` seconds, then everything drained and counted.
    ``domain``: the ROS 2 domain (the tests give each of their workers its own), else one
    derived from the pid and the mode. ``agents_nice``: the robots' and vehicles' processes
    run at this nice value (see :data:`AGENTS_NICE`). ``workers``: not 0, the routes run by
    ``rabbitros-engine run --workers N`` (:class:`EngineWorkers`; its in-engine latency probes
    are not read: they live in bench/systems.py's in-process engine). ``broker_group``: the
    RabbitMQ node's process group, whose CPU and RSS are reported with every other process's
    (``processes``: each engine process, the robots' and vehicles' generators, the consumer).
    ``engine_env``: more environment for ``run --workers`` (``RABBITROS_LOOP=uvloop``: uvloop
    in place of asyncio's loop, engine/running/loop.py)."""
    import aiormq

    from engine.common.schemas import SchemaRegistry
    from engine.language.routes import load_routes

    tag = uuid.uuid4().hex[:6]
    names = {"out": f"fleet-out-{tag}", "cmd": f"fleet-cmd-{tag}"}
    domain = domain if domain is not None else 60 + (os.getpid() + hash(mode)) % 40
    links = links_for(vehicles_n)
    ports = [tp.free_udp_port() for _ in links]
    agents = robot_names(robots_n)
    connection = await aiormq.connect(url)
    channel = await connection.channel()
    await channel.exchange_declare(names["out"], exchange_type="topic", durable=True)
    await channel.exchange_declare(names["cmd"], exchange_type="topic", durable=True)
    children: list[Any] = []
    result: dict[str, Any] = {"agents_nice": agents_nice, "mode": mode, "robots": robots_n, "vehicles": vehicles_n, "links": len(links),
                              "duration_s": duration, "rate_hz": rate, "command_hz": command_rate}
    with tempfile.TemporaryDirectory() as work:
        samples = {"latency_out": str(Path(work) / "latency.json"), "handed_out": str(Path(work) / "handed.json")}
        if mode == REFERENCE:  # no routes: the bridge written on the client libraries (bench/systems.py ref_fleet)
            result["check_s"] = result["routes"] = None
            bridge = ("ref-fleet", {"url": url, **names, "domain": domain, "robots": agents,
                                    "links": [[port, ids] for port, ids in zip(ports, links)], **samples})
        else:
            routes = write_routes(Path(work) / "routes", mode, url, domain, ports, names, robots_n, links)
            load_routes(routes, SchemaRegistry(REPO / "schemas"))  # the transports imported: not the config's cost
            began = time.perf_counter()
            config = load_routes(routes, SchemaRegistry(REPO / "schemas"))
            result["check_s"] = time.perf_counter() - began
            result["routes"] = len(config.routes)
            bridge = ("engine", {"routes": str(routes), "publish_out": str(Path(work) / "publish.json"), **samples})
        files = {name: str(Path(work) / name) for name in ("go", "stop", "done")}
        arrivals, finish = Path(work) / "arrivals.pickle", Path(work) / "finish"
        limit = duration + 600  # each child outlives the load by the set-up's and drain's bounds
        reader = tp.Child("fleet-consumer", {"url": url, "exchange": names["out"], "out": str(arrivals), "finish": str(finish)},
                          limit_s=limit)
        telemetry = Telemetry(reader)
        phases: dict[str, float] = result.setdefault("phases_s", {})
        mark = time.monotonic()

        def phase(name: str) -> None:
            nonlocal mark
            phases[name] = round(time.monotonic() - mark, 2)
            mark = time.monotonic()

        try:
            await reader.wait_for("ready", timeout=60)
            engine: Any
            if workers:
                engine = EngineWorkers(routes, workers, Path(work), engine_env)
                children.append(engine)
                result["workers"] = workers
                result["load_s"] = await engine.start()
                engine_processes = {name: [pid] for name, pid in engine.processes.items()}
                result["rss_after_load_mib"] = sum(rss for _, rss in _usage(engine_processes).values()) / 1024
            else:
                engine = tp.Child(*bridge, limit_s=limit)
                children.append(engine)
                started = await engine.wait_for("started", timeout=300)
                await engine.wait_for("ready", timeout=60)
                _, load_s, rss_kib = started.split()
                result["load_s"], result["rss_after_load_mib"] = float(load_s), int(rss_kib) / 1024
                engine_processes = {"reference" if mode == REFERENCE else "engine": engine.group_pids()}
            phase("engine")
            groups = [agents[index::publishers] for index in range(publishers)]
            ros = [tp.Child("fleet-robots", {"domain": domain, "agents": group, "rate": rate, **files}, limit_s=limit)
                   for group in groups if group]
            mav = tp.Child("fleet-vehicles", {"links": [[port, ids] for port, ids in zip(ports, links)], "rate": rate, **files},
                           limit_s=limit)
            children += [*ros, mav]
            for generator in (*ros, mav):
                os.setpriority(os.PRIO_PGRP, generator.process.pid, agents_nice)
            matched = [await child.wait_for("matched", timeout=180) for child in ros]
            result["unmatched_publishers"] = sum(int(line.split()[1]) for line in matched)
            await mav.wait_for("ready", timeout=60)
            phase("matched")
            await asyncio.sleep(1.2)  # every vehicle's first HEARTBEAT heard (sent within 1 s): its link knows where to send its commands
            processes = {**engine_processes, **{f"robots {k + 1}": child.group_pids() for k, child in enumerate(ros)},
                         "vehicles": mav.group_pids(), "consumer": reader.group_pids()}
            if broker_group:
                processes["rabbitmq"] = _group_members(broker_group)
            usage_before, machine_before = _usage(processes), _machine_ticks()
            cpu_before, wall_before = engine.cpu_seconds(), time.monotonic()
            received_before = telemetry.count
            Path(files["go"]).touch()
            sent_commands = await _commands(channel, names["cmd"], agents, vehicles_n, duration, command_rate, Path(files["stop"]))
            telemetry_sent = robots_n * len(ROBOT_STREAMS) * rate * duration + vehicles_n * len(VEHICLE_STREAMS) * rate * duration
            phase("load")
            await _drain(telemetry, received_before + telemetry_sent * 0.98)
            phase("drain")
            cpu = engine.cpu_seconds() - cpu_before
            wall = time.monotonic() - wall_before
            result["processes"] = _per_process(usage_before, _usage(processes), wall)
            result["machine"] = _machine(machine_before, wall)
            result["rss_end_mib"] = (sum(result["processes"][name]["rss_mib"] for name in engine_processes) if workers
                                     else _rss_kib(engine) / 1024)
            Path(files["done"]).touch()
            outputs = [json.loads((await child.wait_for("result ", timeout=120))[len("result "):]) for child in children[1:]]
            finish.touch()
            await reader.wait_for("done", timeout=120)
            received = pickle.loads(arrivals.read_bytes())
            phase("results")
        finally:
            for child in (*children, reader):
                await child.stop()
            await _forget(channel, names, agents + [f"uav{sid}" for sid in range(1, vehicles_n + 1)])
            await connection.close()
        phase("stop")
        internal = json.loads(Path(samples["latency_out"]).read_text()) if Path(samples["latency_out"]).exists() else {}
        handed = json.loads(Path(samples["handed_out"]).read_text()) if Path(samples["handed_out"]).exists() else {}
        published = Path(work) / "publish.json"
        if published.exists():  # the engine's AMQP publishes over the whole run, and the rounds (one write each) they took
            result["amqp_publish"] = json.loads(published.read_text())
    telemetry.digest(received)
    by_kind: dict[str, list[float]] = {}
    for route, samples in internal.items():
        by_kind.setdefault(_route_kind(route), []).extend(ns / 1e6 for ns in samples)
    result["engine_latency_ms"] = {kind: _pcts(samples) for kind, samples in by_kind.items()}
    to_sink: dict[str, list[float]] = {}
    for route, samples in handed.items():
        to_sink.setdefault(_route_kind(route), []).extend(ns / 1e6 for ns in samples)
    result["engine_to_sink_ms"] = {kind: _pcts(samples) for kind, samples in to_sink.items()}
    sent: dict[str, int] = {}
    for output in outputs:
        sent.update(output["sent"])
    lost = {key: count - len(telemetry.seqs.get(key, ())) for key, count in sent.items()}
    robot_commands = {agent: seqs for output in outputs[:-1] for agent, seqs in output["commands"].items()}
    vehicle_commands = {f"uav{sid}": seqs for sid, seqs in outputs[-1]["commands"].items()}
    commands_lost = {agent: count - len(set(robot_commands.get(agent, vehicle_commands.get(agent, []))))
                     for agent, count in sent_commands.items()}
    telemetry_total = sum(sent.values())
    commands_total = sum(sent_commands.values())
    latency = dict(telemetry.latency)
    latency["command amqp->ros2"] = [ms for output in outputs[:-1] for ms in output["command_ms"]]
    latency["command amqp->mavlink"] = outputs[-1]["command_ms"]
    result.update(
        telemetry_sent=telemetry_total, telemetry_lost=sum(max(0, n) for n in lost.values()),
        commands_sent=commands_total, commands_lost=sum(max(0, n) for n in commands_lost.values()),
        lost_streams={k: n for k, n in lost.items() if n}, lost_commands={k: n for k, n in commands_lost.items() if n},
        foreign_commands=outputs[-1]["foreign_commands"], udp_send_errors=outputs[-1]["send_errors"],
        latency_ms={kind: _pcts(samples) for kind, samples in latency.items()},
        engine_cpu_s=cpu, wall_s=wall, engine_cores=cpu / wall,
        engine_cpu_us_per_message=cpu / max(1, telemetry_total + commands_total) * 1e6,
    )
    result["lost"] = result["telemetry_lost"] + result["commands_lost"]
    return result


async def _forget(channel: Any, names: dict[str, str], agents: list[str]) -> None:
    """Delete the run's durable command queues and its exchanges: a later mode on the same
    broker must not carry 100 idle queues and their bindings from this one."""
    for agent in agents:
        await channel.queue_delete(f"{names['cmd']}-{agent}")
    for exchange in names.values():
        await channel.exchange_delete(exchange)


async def _commands(channel: Any, exchange: str, robots: list[str], vehicles: int, duration: float,
                    rate: float, stop: Path) -> dict[str, int]:
    """A command to every agent at ``rate``, staggered, for ``duration``: {agent: commands sent}.
    Each publish's confirm is not waited for before the next command is due (a loaded broker
    would stretch the load phase: a run was seen sending telemetry for 145 s instead of 60);
    at ``duration`` the ``stop`` file ends the telemetry, then every command is confirmed."""
    from pamqp.commands import Basic

    properties = Basic.Properties(delivery_mode=2, content_type="application/json")
    agents = robots + [f"uav{sid}" for sid in range(1, vehicles + 1)]
    sent = dict.fromkeys(agents, 0)
    confirming: list[asyncio.Future[Any]] = []
    began = time.monotonic()
    period = 1.0 / rate
    rounds = max(1, int(duration * rate))
    for round_ in range(rounds):
        for slot, agent in enumerate(agents):
            due = began + round_ * period + slot * period / len(agents)
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            body = json.dumps({"agent": agent, "seq": round_, "t_ns": time.time_ns(), "t_ms": _ms24()}).encode()
            confirming.append(asyncio.ensure_future(
                channel.basic_publish(body, exchange=exchange, routing_key=agent, properties=properties)))
            sent[agent] += 1
    delay = began + duration - time.monotonic()
    if delay > 0:
        await asyncio.sleep(delay)
    stop.touch()
    await asyncio.gather(*confirming)
    return sent


async def _drain(telemetry: Telemetry, at_least: float, stall: float = 1.5, timeout: float = 60.0) -> None:
    """Wait for the backlog to arrive: until no message came for ``stall`` s once ``at_least``
    arrived (or ``timeout``)."""
    deadline = time.monotonic() + timeout
    last, changed = telemetry.count, time.monotonic()
    while time.monotonic() < deadline:
        await asyncio.sleep(0.1)
        if telemetry.count != last:
            last, changed = telemetry.count, time.monotonic()
        elif telemetry.count >= at_least and time.monotonic() - changed > stall:
            return


async def fleet(url: str | None, modes: list[str], robots_n: int = 50, vehicles_n: int = 50, duration: float = 60.0,
                agents_nice: int = 0) -> dict[str, Any]:
    """Each way of writing the routes on the same load, one after the other, with the load
    average before and after each; ``url`` None: each on a fresh private RabbitMQ node, so no
    mode carries what another left in the broker (on one node for all, the mode that ran first
    had the lowest p99 in three runs of four). With the aiormq consumer the spread from run to
    run was large (templated telemetry p99 26-130 ms, the reference's 18-1,634 ms); with
    :func:`consumer` templated routes gave 10.5-37 ms in four full runs and the reference 20-45,
    and in a fifth, a bad stretch of the shared machine, both ~850
    (bench/results/2026-11-27/README.md); compare runs, not one."""
    from engine.endpoints.amqp.broker import LocalBroker

    out: dict[str, Any] = {}
    for mode in modes:
        node: LocalBroker | None = None
        if url:
            mode_url = url
        else:
            node = LocalBroker()
            mode_url = await asyncio.to_thread(node.start)
        try:
            before = os.getloadavg()
            print(f"  fleet: {mode} ({robots_n} robots, {vehicles_n} vehicles, {duration:.0f} s)", flush=True)
            out[mode] = await run_mode(mode_url, mode, robots_n, vehicles_n, duration, agents_nice=agents_nice)
            out[mode]["loadavg_before"], out[mode]["loadavg_after"] = before, os.getloadavg()
            out[mode]["fresh_broker"] = node is not None
        finally:
            if node is not None:
                await asyncio.to_thread(node.stop)
    return out


# ---------------------------------------------------------------- the report

def fleet_report(results: dict[str, Any]) -> list[str]:
    """The fleet section of a report: one column per way of writing the routes."""
    modes = [mode for mode in MODES if isinstance(results.get(mode), dict) and "lost" in results[mode]]
    if not modes:
        return [f"Fleet run failed: {results}"]
    first = results[modes[0]]
    reference = results.get(REFERENCE) if REFERENCE in modes else None
    lines = [f"{first['robots']} ROS 2 robots x {len(ROBOT_STREAMS)} topics and {first['vehicles']} MAVLink vehicles "
             f"x {len(VEHICLE_STREAMS)} messages ({first['links']} UDP links) at {first['rate_hz']:g} Hz each, a "
             f"{first['command_hz']:g} Hz command to each agent the other way, {first['duration_s']:.0f} s"
             + (f"; the robots' and vehicles' processes at nice {first['agents_nice']}" if first.get("agents_nice") else "")
             + ".", "",
             "| | " + " | ".join(LABELS[m] for m in modes) + " |", "|---|" + "---|" * len(modes)]

    def row(label: str, value: Any) -> None:
        lines.append(f"| {label} | " + " | ".join(value(results[m]) for m in modes) + " |")

    row("Routes (expanded)", lambda r: "-" if r["routes"] is None else str(r["routes"]))
    row("Telemetry lost / sent", lambda r: f"{r['telemetry_lost']} / {r['telemetry_sent']}")
    row("Commands lost / sent", lambda r: f"{r['commands_lost']} / {r['commands_sent']}")
    for kind in STREAM_KINDS:
        row(f"{kind} p50 / p99 (ms)", lambda r, k=kind: (f"{r['latency_ms'][k]['p50']:.1f} / {r['latency_ms'][k]['p99']:.1f}"
                                                         if r["latency_ms"][k].get("n") else "-"))
    for kind in STREAM_KINDS:
        row(f"{kind}: in the engine p50 / p99 (ms)", lambda r, k=kind: (
            f"{r['engine_latency_ms'][k]['p50']:.2f} / {r['engine_latency_ms'][k]['p99']:.2f}"
            if r.get("engine_latency_ms", {}).get(k, {}).get("n") else "-"))
    for kind in STREAM_KINDS:
        row(f"{kind}: in the engine until handed to its sink p50 / p99 (ms)", lambda r, k=kind: (
            f"{r['engine_to_sink_ms'][k]['p50']:.2f} / {r['engine_to_sink_ms'][k]['p99']:.2f}"
            if r.get("engine_to_sink_ms", {}).get(k, {}).get("n") else "-"))
    if reference is not None:
        for kind in STREAM_KINDS:
            row(f"{kind} p99 / the reference's", lambda r, k=kind: _ratio(r["latency_ms"][k], reference["latency_ms"][k], "p99"))
    row("Engine CPU per message (us)", lambda r: f"{r['engine_cpu_us_per_message']:.0f}")
    if reference is not None:
        row("Engine CPU per message / the reference's", lambda r: f"{r['engine_cpu_us_per_message'] / reference['engine_cpu_us_per_message']:.2f}")
    row("Engine CPU (cores)", lambda r: f"{r['engine_cores']:.2f}")
    row("AMQP publishes per round (one write, one confirm wait)", _per_round)
    row("RSS after load / at the end (MiB)", lambda r: f"{r['rss_after_load_mib']:.0f} / {r['rss_end_mib']:.0f}")
    row("check: parse, expand, compile (s)", lambda r: "-" if r["check_s"] is None else f"{r['check_s']:.3f}")
    row("load: Engine.start, or the reference's setup (s)", lambda r: f"{r['load_s']:.2f}")
    row("Load average before / after", lambda r: " / ".join(f"{x:.1f}" for x in r["loadavg_before"][:1] + r["loadavg_after"][:1]))
    lines += ["", "Latency is end to end on one machine's wall clock: from the robot's or vehicle's send to the bench's "
              "consumer of the RabbitMQ queue (telemetry), from the bench's AMQP publish to the robot's or vehicle's "
              "receipt (commands). Engine CPU per message = the engine process's CPU time during the load and its drain "
              "/ every message it carried, both ways. Targets: 0 lost, p99 <= 50 ms, under one core."]
    if reference is not None:
        lines += ["", "The reference column runs no engine: the same bridge written directly on rclpy, pymavlink and aiormq "
                  "(bench/systems.py ref_fleet) in its place, on the same load; its \"engine\" rows are that process's "
                  "(\"in the engine\": reception to the broker's confirm or to the command's send; \"until handed\": "
                  "reception to its publish). Ratios are each column's figure over the reference's, in the same run."]
    return lines


def _per_round(result: dict[str, Any]) -> str:
    """The engine's AMQP publishes over its publish rounds (engine/endpoints/amqp/publisher.py),
    over the whole run; "-" for the reference or a run without the counts."""
    counts = list((result.get("amqp_publish") or {}).values())
    rounds = sum(count["publish_rounds"] for count in counts)
    return f"{sum(count['published'] for count in counts) / rounds:.2f}" if rounds else "-"


def _ratio(value: dict[str, Any], reference: dict[str, Any], key: str) -> str:
    if not value.get("n") or not reference.get("n") or not reference[key]:
        return "-"
    return f"{value[key] / reference[key]:.2f}"


def main() -> None:
    from engine.running.loop import run as run_loop

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of load per mode")
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--vehicles", type=int, default=50)
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    parser.add_argument("--agents-nice", type=int, nargs="?", const=AGENTS_NICE, default=0,
                        help=f"the robots' and vehicles' processes at this nice value (alone: {AGENTS_NICE}; default 0)")
    parser.add_argument("--url", help="a running broker for every mode (default: a fresh private RabbitMQ node for each)")
    parser.add_argument("--out", help="output directory (default bench/results/<date>)")
    args = parser.parse_args()

    results = run_loop(fleet(args.url, args.modes.split(","), args.robots, args.vehicles, args.duration, args.agents_nice))
    out_dir = Path(args.out) if args.out else REPO / "bench" / "results" / datetime.date.today().isoformat()
    out_dir.mkdir(parents=True, exist_ok=True)
    commit = os.popen(f"git -C {REPO} rev-parse --short HEAD").read().strip()
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    (out_dir / "fleet.json").write_text(json.dumps({"date": stamp, "commit": commit, **results}, indent=1))
    text = [f"# Fleet benchmark\n\n{stamp}, commit {commit}, {os.cpu_count()} CPUs (shared: the load average is "
            "recorded with each run).\n", *fleet_report(results)]
    (out_dir / "fleet.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


if __name__ == "__main__":
    main()
