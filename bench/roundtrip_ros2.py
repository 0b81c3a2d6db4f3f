"""The paper's first experiment: round trip between RabbitMQ and ROS 2 across two hosts.

A generator publishes JSON messages to RabbitMQ; the engine converts them to a ROS 2 topic;
a robot node on the second host (network namespace) stores and republishes them; the engine
converts them back to AMQP. Each message is recorded at the three points and compared byte
for byte; the three versions go to one CSV per run and size.

    python -m bench.roundtrip_ros2                      # the paper's settings: 5 runs x 100 msgs at 1 msg/s
    python -m bench.roundtrip_ros2 --runs 1 --rate 200  # fast
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.netns import DDS_OVER_UDP, Host, NamespacesUnavailable, TwoHosts

REPO = Path(__file__).resolve().parent.parent
TO_ROBOT, FROM_ROBOT = "/uav1/json_in", "/uav1/json_out"
ROUTES = f"""
routes:
  - name: gcs-to-uav
    source:
      amqp: {{exchange: roundtrip, binding_key: to_uav, queue: roundtrip-to-uav}}
    schema: raw_json
    sink:
      ros2: {{topic: {TO_ROBOT}}}
  - name: uav-to-gcs
    source:
      ros2: {{topic: {FROM_ROBOT}}}
    schema: raw_json
    sink:
      amqp: {{exchange: roundtrip, routing_key: from_uav}}
"""


def make_message(run: int, size: int, seq: int) -> bytes:
    """A JSON object of exactly ``size`` bytes, unique per (run, size, seq)."""
    head = json.dumps({"run": run, "seq": seq, "size": size, "pad": ""}, separators=(",", ":"))
    rng = random.Random(run * 100_000 + size * 1000 + seq)
    pad = "".join(rng.choice("abcdefghijklmnopqrstuvwxyz0123456789") for _ in range(size - len(head)))
    body = head[:-2] + pad + '"}'
    assert len(body) == size, (len(body), size)
    return body.encode()


async def gcs_side(args: argparse.Namespace) -> dict[str, Any]:
    """Runs inside the GCS namespace: private broker, engine, generator and recorder."""
    import aio_pika

    from engine.endpoints.amqp.broker import LocalBroker
    from engine.running.runtime import Engine

    out = Path(args.out)
    robot_store = Path(args.robot_store)
    with LocalBroker() as broker, tempfile.TemporaryDirectory() as routes:
        os.environ["RABBITROS_AMQP_URL"] = broker.url
        Path(routes, "roundtrip.yaml").write_text(ROUTES)
        engine = Engine(Path(routes), REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(broker.url)
        try:
            channel = await connection.channel()
            exchange = await channel.declare_exchange("roundtrip", aio_pika.ExchangeType.TOPIC, durable=True)
            back = await channel.declare_queue(exclusive=True)
            await back.bind(exchange, "from_uav")
            returned: list[bytes] = []
            await back.consume(lambda m: _append(returned, m), no_ack=True)
            await _wait_for_path(exchange, returned, timeout=60)
            results = []
            for run in range(1, args.runs + 1):
                for size in args.sizes:
                    returned.clear()
                    originals = [make_message(run, size, seq) for seq in range(args.count)]
                    started = time.monotonic()
                    for index, body in enumerate(originals):
                        await exchange.publish(aio_pika.Message(body, content_type="application/json"), "to_uav")
                        await asyncio.sleep(max(0.0, started + (index + 1) / args.rate - time.monotonic()))
                    deadline = time.monotonic() + 30
                    while len(returned) < args.count and time.monotonic() < deadline:
                        await asyncio.sleep(0.05)
                    await asyncio.sleep(0.2)
                    results.append(_record(out, run, size, originals, robot_store, list(returned)))
        finally:
            await connection.close()
            await engine.stop()
    return {"results": results}


async def _append(store: list[bytes], message: Any) -> None:
    store.append(message.body)


async def _wait_for_path(exchange: Any, returned: list[bytes], timeout: float) -> None:
    """Discovery across hosts takes a few seconds: probe until one message comes back."""
    import aio_pika

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        await exchange.publish(aio_pika.Message(b'{"probe":true}'), "to_uav")
        await asyncio.sleep(0.5)
        if returned:
            await asyncio.sleep(0.5)
            returned.clear()
            return
    raise TimeoutError("no message came back from the robot: DDS discovery across the hosts failed")


def _record(out: Path, run: int, size: int, originals: list[bytes], robot_store: Path, returned: list[bytes]) -> dict[str, Any]:
    key = lambda body: (json.loads(body)["run"], json.loads(body)["size"], json.loads(body)["seq"])  # noqa: E731
    at_robot: dict[tuple[Any, Any, Any], bytes] = {}
    for line in robot_store.read_bytes().splitlines():
        if b'"probe"' not in line and json.loads(line).get("run") == run and json.loads(line).get("size") == size:
            at_robot.setdefault(key(line), line)
    back: dict[tuple[Any, Any, Any], bytes] = {}
    for body in returned:
        back.setdefault(key(body), body)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"ros2_roundtrip_run{run}_{size}B.csv"
    identical = 0
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["seq", "original", "at_robot", "back_at_gcs", "identical"])
        for seq, original in enumerate(originals):
            robot = at_robot.get((run, size, seq), b"")
            station = back.get((run, size, seq), b"")
            same = original == robot == station
            identical += same
            writer.writerow([seq, original.decode(), robot.decode(), station.decode(), same])
    return {"run": run, "size": size, "sent": len(originals), "at_robot": len(at_robot), "back": len(back),
            "identical": identical, "csv": str(path)}


def run_experiment(runs: int, count: int, rate: float, sizes: list[int], out: Path) -> dict[str, Any]:
    """Create the two hosts, start the robot on one and the GCS side on the other."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **DDS_OVER_UDP, "ROS_DOMAIN_ID": str(random.randint(1, 100)), "PYTHONPATH": str(REPO)}
    robot_store = out / "robot_store.jsonl"
    robot_store.write_bytes(b"")
    budget = int(90 + runs * len(sizes) * (count / rate + 35))
    hosts = TwoHosts()
    with hosts as (gcs, uav):
        robot = subprocess.Popen(
            uav.command("timeout", "-s", "KILL", str(budget), sys.executable, str(REPO / "examples" / "robot_echo.py"),
                        "--in", TO_ROBOT, "--out", FROM_ROBOT, "--file", str(robot_store)),
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
        )
        try:
            station = _run_gcs(gcs, env, budget, runs, count, rate, sizes, out, robot_store)
            station["robot_link_rx_bytes"] = hosts.received_bytes(uav)
        finally:
            robot.terminate()
            try:
                robot.wait(10)
            except subprocess.TimeoutExpired:
                robot.kill()
    return station


def _run_gcs(gcs: Host, env: dict[str, str], budget: int, runs: int, count: int, rate: float,
             sizes: list[int], out: Path, robot_store: Path) -> dict[str, Any]:
    command = gcs.command(
        "timeout", "-s", "KILL", str(budget), sys.executable, "-m", "bench.roundtrip_ros2", "gcs-side",
        "--runs", str(runs), "--count", str(count), "--rate", str(rate),
        "--sizes", ",".join(map(str, sizes)), "--out", str(out), "--robot-store", str(robot_store),
    )
    result = subprocess.run(command, env=env, cwd=REPO, capture_output=True, text=True, timeout=budget + 10)
    if result.returncode != 0:
        raise RuntimeError(f"GCS side failed ({result.returncode}): {result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("role", nargs="?", default="orchestrate", choices=["orchestrate", "gcs-side"])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--rate", type=float, default=1.0)
    parser.add_argument("--sizes", type=lambda s: [int(x) for x in s.split(",")], default=[50, 150, 250])
    parser.add_argument("--out", type=Path, default=REPO / "results" / "ros2_roundtrip")
    parser.add_argument("--robot-store", type=Path)
    args = parser.parse_args()
    if args.role == "gcs-side":
        print(json.dumps(asyncio.run(gcs_side(args))))
        return 0
    try:
        summary = run_experiment(args.runs, args.count, args.rate, args.sizes, args.out)
    except NamespacesUnavailable as exc:
        print(f"cannot create the two hosts: {exc}", file=sys.stderr)
        return 2
    ok = True
    print(f"bytes received by the robot's host over the link: {summary['robot_link_rx_bytes']}")
    for row in summary["results"]:
        ok &= row["identical"] == row["sent"]
        print(f"run {row['run']} {row['size']:>3} B: sent {row['sent']}, at robot {row['at_robot']}, "
              f"back {row['back']}, byte-identical {row['identical']}  -> {row['csv']}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
