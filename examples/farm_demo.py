"""The main job: the paper's farm, every part real and on this machine.

- a UAV (the simulated vehicle) speaks MAVLink 2 through an emulated SiK radio pair: telemetry
  at realistic rates and, every few seconds, weed detections as JSON over the radio;
- a ground robot is a plain ROS 2 node: GNSS fix, missions in, acknowledgements out, a sprayer
  service and a row action;
- the engine runs ``examples/farm_uav_gcs.yaml`` against a private RabbitMQ node;
- the supervisory software speaks only AMQP: it prints the canonical messages, turns weed
  detections into spraying missions for the ground robot, and calls the robot (AMQP
  request/reply): sprayer on through its service, along a row with an action goal (accepted,
  feedback per stop, result), sprayer off.

On a terminal the demo shows, in place, each route's rates and counts and its last canonical
message (from the engine's admin endpoint); otherwise (or with ``--plain``) it prints plain lines.

It exits 0 only when every flow it promises carried messages: the supervisor saw every canonical
flow, and every route of ``farm_uav_gcs.yaml`` delivered at least one message and dead-lettered
none (the engine's final status); otherwise it names the flows that did not and exits 1.

With ``--record DIR`` the engine records what every route received and sent (MCAP, engine
``--record``; ``rabbitros-engine replay DIR --routes examples/farm_uav_gcs.yaml`` checks a
mapping edit against it); ``--admin PORT`` fixes the admin port (the web console at ``/``).

    .venv/bin/python examples/farm_demo.py [--duration 30] [--work DIR] [--plain] [--record DIR] [--admin PORT]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from engine.common.processes import listening_port  # noqa: E402
from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402

PYTHON = sys.executable


def spawn(argv: list[str], env: dict[str, str], log: Path | None = None, pipe: bool = False) -> subprocess.Popen[bytes]:
    out: Any = open(log, "wb") if log else (subprocess.PIPE if pipe else None)
    return subprocess.Popen(["timeout", "-s", "KILL", "900", *argv], env=env, cwd=REPO, stdout=out,
                            stderr=subprocess.STDOUT if out else None, start_new_session=True)


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


def wait_for(path: Path, process: subprocess.Popen[bytes], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and path.stat().st_size) and time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"{process.args!r} exited with {process.returncode}")
        time.sleep(0.2)
    if not path.exists():
        raise TimeoutError(f"{path} did not appear")


def follow(process: subprocess.Popen[bytes], lines: deque[str]) -> threading.Thread:
    """Collect a child's output lines for the live view."""
    def read() -> None:
        assert process.stdout is not None
        for raw in process.stdout:
            lines.append(raw.decode("utf-8", errors="replace").rstrip())

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def live_view(admin: tuple[str, int], supervisor: subprocess.Popen[bytes], lines: deque[str]) -> None:
    """In place in the terminal: each route's rates and counts and its last canonical message,
    and the latest lines of the supervisor and the robot, until the supervisor is done."""
    from rich.console import Group
    from rich.live import Live
    from rich.panel import Panel

    from engine.ops.opsview import fetch_status, status_table

    def render() -> Group:
        try:
            table: Any = status_table(fetch_status(admin, timeout=2), last_canonical=True, width=70)
        except OSError as exc:
            table = f"engine status unavailable: {exc}"
        return Group(table, Panel("\n".join(lines) or "...", title="supervisor and robot", title_align="left"))

    with Live(render(), refresh_per_second=2, transient=False) as live:
        while supervisor.poll() is None:
            time.sleep(1.0)
            live.update(render())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=30.0, help="seconds the supervisor watches")
    parser.add_argument("--work", type=Path, help="directory for logs, the status file and the supervisor's record "
                        "of every canonical message (default: a new temporary directory)")
    parser.add_argument("--plain", action="store_true", help="plain lines even on a terminal")
    parser.add_argument("--ros-domain", type=int, default=random.randint(1, 100),
                        help="ROS 2 domain of the engine and the robot (default: a random one, 1..100, so the "
                        "demo does not meet other ROS 2 programs on the machine)")
    parser.add_argument("--record", type=Path, metavar="DIR", help="the engine records every route in MCAP files in DIR")
    parser.add_argument("--admin", type=int, metavar="PORT", help="the engine's admin port on 127.0.0.1 (default: a free one)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="rabbitros-farm-"))
    work.mkdir(parents=True, exist_ok=True)
    live = sys.stdout.isatty() and not args.plain
    env = {**os.environ, "ROS_DOMAIN_ID": str(args.ros_domain), "PYTHONPATH": str(REPO)}
    processes: list[subprocess.Popen[bytes]] = []
    lines: deque[str] = deque(maxlen=12)
    admin = ("127.0.0.1", args.admin or listening_port())
    recording = ["--record", str(args.record)] if args.record else []
    with SikRadioPair(link_a=str(work / "radio-gcs"), link_b=str(work / "radio-uav"), seed=1) as radio:
        env["RABBITROS_RADIO"] = radio.link_a
        try:
            engine = spawn([str(Path(PYTHON).with_name("rabbitros-engine")), "--routes", "examples/farm_uav_gcs.yaml",
                            "--local-broker", "--broker-url-file", str(work / "url"), "--admin", f"{admin[0]}:{admin[1]}",
                            "--status-file", str(work / "status.json"), "--stats-interval", "2", *recording], env, work / "engine.log")
            processes.append(engine)
            wait_for(work / "status.json", engine, 120)
            url = (work / "url").read_text().strip()
            print(f"farm: engine up, broker {url.split('@')[-1]}, admin http://{admin[0]}:{admin[1]}/, "
                  f"radio {radio.link_a} <-> {radio.link_b}", flush=True)
            robot = spawn([PYTHON, "examples/ground_robot.py", "--name", "robot1"], env, pipe=live)
            processes.append(robot)
            supervisor = spawn(
                [PYTHON, "examples/gcs_supervisor.py", "--url", url, "--duration", str(args.duration),
                 "--record", str(work / "canonical.jsonl"), "--ready-file", str(work / "supervisor.ready")],
                env, pipe=live)
            processes.append(supervisor)
            wait_for(work / "supervisor.ready", supervisor, 60)
            # The UAV comes up once the ground station watches, so every detection it sends can be counted.
            # Its weed detector starts when the supervisor's command reaches it (route uav1-commands).
            processes.append(spawn([PYTHON, "-m", "rabbitros_sim.vehicle", "--device", radio.link_b, "--baud", "57600",
                                    "--weeds-on-command"], env, work / "vehicle.log"))
            if live:
                follow(robot, lines)
                reader = follow(supervisor, lines)
                live_view(admin, supervisor, lines)
                reader.join(5)
            supervisor.wait(args.duration + 60)
        finally:
            for process in reversed(processes):
                stop(process)
    status = json.loads((work / "status.json").read_text())
    print(f"engine generation {status['generation']} config {status['config_hash']}, final counters:")
    for name, route in status["routes"].items():
        print(f"  {name:22} received {route['received']:5}  delivered {route['delivered']:5}  failed {route['failed']}")
    print(f"farm: logs and records in {work}")
    broken = unkept_promises(status["routes"])
    for line in broken:
        print(f"farm: {line}", file=sys.stderr)
    if supervisor.returncode:
        print(f"farm: the supervisor exited {supervisor.returncode} (flows it did not see are above)", file=sys.stderr)
    return 1 if broken or supervisor.returncode else 0


def unkept_promises(routes: dict[str, Any]) -> list[str]:
    """Every route of the farm is a flow the demo shows working: one that delivered nothing, or
    dead-lettered a message, is a failure of the demo (not something to find in its output)."""
    idle = [name for name, route in routes.items() if not route["delivered"]]
    dead = [f"{name} ({route['failed']})" for name, route in routes.items() if route["failed"]]
    return ([f"flows that carried nothing: {', '.join(idle)}"] if idle else []) + \
        ([f"flows that dead-lettered messages: {', '.join(dead)}"] if dead else [])


if __name__ == "__main__":
    sys.exit(main())
