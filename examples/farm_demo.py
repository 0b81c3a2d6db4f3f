"""The main job: the paper's farm, every part real and on this machine.

- a UAV (the simulated vehicle) speaks MAVLink 2 through an emulated SiK radio pair: telemetry
  at realistic rates and, every few seconds, weed detections as JSON over the radio;
- a ground robot is a plain ROS 2 node: GNSS fix, missions in, acknowledgements out;
- the engine runs ``examples/farm_uav_gcs.yaml`` against a private RabbitMQ node;
- the supervisory software speaks only AMQP: it prints the canonical messages and turns weed
  detections into spraying missions for the ground robot.

    .venv/bin/python examples/farm_demo.py [--duration 30]
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
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402

PYTHON = sys.executable


def spawn(argv: list[str], env: dict[str, str], log: Path | None = None) -> subprocess.Popen[bytes]:
    out = open(log, "wb") if log else None
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
            raise RuntimeError(f"{process.args} exited with {process.returncode}")
        time.sleep(0.2)
    if not path.exists():
        raise TimeoutError(f"{path} did not appear")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=30.0, help="seconds the supervisor watches")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rabbitros-farm-"))
    env = {**os.environ, "ROS_DOMAIN_ID": str(random.randint(1, 100)), "PYTHONPATH": str(REPO)}
    processes: list[subprocess.Popen[bytes]] = []
    with SikRadioPair(link_a=str(work / "radio-gcs"), link_b=str(work / "radio-uav"), seed=1) as radio:
        env["RABBITROS_RADIO"] = radio.link_a
        try:
            processes.append(spawn([PYTHON, "-m", "rabbitros_sim.vehicle", "--device", radio.link_b, "--baud", "57600",
                                    "--weeds-every", "6"], env, work / "vehicle.log"))
            processes.append(spawn([PYTHON, "examples/ground_robot.py", "--name", "robot1"], env))
            engine = spawn([str(Path(PYTHON).with_name("rabbitros-engine")), "--routes", "examples/farm_uav_gcs.yaml",
                            "--local-broker", "--broker-url-file", str(work / "url"),
                            "--status-file", str(work / "status.json")], env)
            processes.append(engine)
            wait_for(work / "status.json", engine, 120)
            url = (work / "url").read_text().strip()
            print(f"farm: engine up, broker {url.split('@')[-1]}, radio {radio.link_a} <-> {radio.link_b}", flush=True)
            supervisor = subprocess.run(
                ["timeout", "-s", "KILL", str(int(args.duration) + 60), PYTHON, "examples/gcs_supervisor.py",
                 "--url", url, "--duration", str(args.duration)], env=env, cwd=REPO,
            )
        finally:
            for process in reversed(processes):
                stop(process)
    status = json.loads((work / "status.json").read_text())
    print(f"engine generation {status['generation']} config {status['config_hash']}, final counters:")
    for name, route in status["routes"].items():
        print(f"  {name:22} received {route['received']:5}  delivered {route['delivered']:5}  failed {route['failed']}")
    return supervisor.returncode


if __name__ == "__main__":
    sys.exit(main())
