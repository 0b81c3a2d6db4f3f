"""Tunnel goodput against the emulated SiK radio's flood reference (issue 22), repeated.

Each repetition measures, at 0 % and at 5 % loss and in this order: the flood references
(bench/sections.py ``flood_capacity``: the radio flooded with 107-byte TUNNEL payloads, alone
and beside the simulated vehicle's telemetry), then the round trip of ``--count`` 250-byte JSON
messages (bench/roundtrip_mavlink.py: engine -> tunnel -> radio -> vehicle, stored, sent back)
published faster than the radio carries. Two goodputs per round trip:

* **to the vehicle**: JSON bytes from the first publish to the last message stored by the
  vehicle. That way carries no telemetry: compared with the plain flood.
* **round trip**: JSON bytes each way from the first publish to the last message back. The
  way back shares the radio with the vehicle's telemetry (about a tenth of the air), so the
  round trip is bounded by the flood *with* telemetry; both fractions are given.

``--ab`` adds the same round trip with one batch in flight (``TunnelSink.batches_in_flight = 1``,
as before the sink declared four), interleaved, for the before/after in the same run.
The machine's load average is recorded before and after every measurement.

    .venv/bin/python -m bench.goodput                        # 3 repetitions, about 5 minutes
    .venv/bin/python -m bench.goodput --reps 5 --ab --out /tmp/goodput
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import statistics
import subprocess
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench.sections import flood_capacity, link_payload_capacity

REPO = Path(__file__).resolve().parent.parent
SIZE = 250
LOSSES = (0.0, 0.05)


async def round_trip(url: str, count: int, loss: float, seed: int, batches_in_flight: int | None) -> dict[str, Any]:
    """One round trip; ``batches_in_flight`` overrides the tunnel sink's declaration."""
    from bench.roundtrip_mavlink import Settings, run_experiment
    from engine.endpoints.mavlink.tunnel import TunnelSink

    declared = TunnelSink.batches_in_flight
    if batches_in_flight is not None:
        TunnelSink.batches_in_flight = batches_in_flight
    try:
        with tempfile.TemporaryDirectory() as work:
            settings = Settings(runs=1, count=count, rate=40.0, sizes=(SIZE,), loss=loss, seed=seed, out=Path(work),
                                exchange=f"goodput-{uuid.uuid4().hex[:6]}")
            summary = await run_experiment(settings, amqp_url=url)
    finally:
        TunnelSink.batches_in_flight = declared
    batch = summary["batches"][0]
    forward, forward_span, back_span = batch["forward_seconds"], batch["forward_span_seconds"], batch["back_span_seconds"]
    return {"sent": batch["sent"], "at_vehicle": batch["at_robot"], "identical": batch["identical"],
            "seconds": batch["seconds"], "forward_seconds": forward,
            "goodput_bytes_per_s": batch["identical"] * SIZE / batch["seconds"],
            "forward_bytes_per_s": batch["at_robot"] * SIZE / forward if forward else None,
            # the steady pace: from the first message stored (back) to the last, as the flood
            # reference leaves its first second out
            "forward_steady_bytes_per_s": (batch["at_robot"] - 1) * SIZE / forward_span if forward_span else None,
            "steady_bytes_per_s": (batch["identical"] - 1) * SIZE / back_span if back_span else None,
            "vehicle_retransmissions": summary["vehicle"].get("tunnel_retransmissions"),
            "radio": summary["radio"]}


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


async def measure(url: str, reps: int, count: int, flood_seconds: float, ab: bool) -> dict[str, Any]:
    payload = int(link_payload_capacity()["tunnel_payload"])
    rows: list[dict[str, Any]] = []
    for rep in range(reps):
        for loss in LOSSES:
            row: dict[str, Any] = {"rep": rep, "loss": loss, "load_before": load()}
            print(f"rep {rep} loss {loss:.0%}: floods", flush=True)
            row["flood"] = await asyncio.to_thread(flood_capacity, payload, flood_seconds, loss=loss)
            row["flood_with_telemetry"] = await asyncio.to_thread(flood_capacity, payload, flood_seconds,
                                                                  telemetry=True, loss=loss)
            variants = [("engine", None)] + ([("one_batch", 1)] if ab else [])
            if ab and rep % 2:
                variants.reverse()  # interleaved: neither always runs first
            for name, in_flight in variants:
                print(f"rep {rep} loss {loss:.0%}: round trip ({name})", flush=True)
                result = await round_trip(url, count, loss, seed=rep + 1, batches_in_flight=in_flight)
                result["forward_fraction_of_flood"] = (result["forward_bytes_per_s"] or 0.0) / row["flood"]
                result["fraction_of_flood"] = result["goodput_bytes_per_s"] / row["flood"]
                result["fraction_of_flood_with_telemetry"] = result["goodput_bytes_per_s"] / row["flood_with_telemetry"]
                result["forward_steady_fraction_of_flood"] = (result["forward_steady_bytes_per_s"] or 0.0) / row["flood"]
                result["steady_fraction_of_flood_with_telemetry"] = (result["steady_bytes_per_s"] or 0.0) / row["flood_with_telemetry"]
                row[name] = result
            row["load_after"] = load()
            rows.append(row)
            print(f"  flood {row['flood']:.0f}, with telemetry {row['flood_with_telemetry']:.0f} B/s; " + "; ".join(
                f"{name}: to vehicle {row[name]['forward_fraction_of_flood']:.2f}, round trip "
                f"{row[name]['fraction_of_flood']:.2f} / {row[name]['fraction_of_flood_with_telemetry']:.2f}"
                for name, _ in variants), flush=True)
    return {"rows": rows, "summary": summarize(rows, ["engine"] + (["one_batch"] if ab else []))}


def summarize(rows: list[dict[str, Any]], variants: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for loss in LOSSES:
        mine = [row for row in rows if row["loss"] == loss]
        entry: dict[str, Any] = {"flood_bytes_per_s": spread([row["flood"] for row in mine]),
                                 "flood_with_telemetry_bytes_per_s": spread([row["flood_with_telemetry"] for row in mine])}
        for name in variants:
            entry[name] = {key: spread([row[name][key] for row in mine])
                           for key in ("forward_fraction_of_flood", "fraction_of_flood", "fraction_of_flood_with_telemetry",
                                       "forward_steady_fraction_of_flood", "steady_fraction_of_flood_with_telemetry",
                                       "forward_bytes_per_s", "goodput_bytes_per_s")}
            entry[name]["identical"] = [row[name]["identical"] for row in mine]
        out[f"{loss:.0%}"] = entry
    return out


def spread(values: list[float]) -> dict[str, float]:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def markdown(results: dict[str, Any]) -> str:
    m = results["machine"]
    lines = [f"# Tunnel goodput against the flood reference ({m['date']}, commit {m['commit']})", "",
             f"`python -m bench.goodput --reps {results['settings']['reps']} --count {results['settings']['count']}"
             f"{' --ab' if results['settings']['ab'] else ''}`: {results['settings']['count']} JSON messages of {SIZE} B "
             f"per round trip; floods of {results['settings']['flood_seconds']:g} s; load average "
             f"{m['load_before']} before, {m['load_after']} after ({m['cpus']} CPUs). Median [min-max] of the repetitions.", ""]
    variants = ["engine"] + (["one_batch"] if results["settings"]["ab"] else [])
    names = {"engine": "four batches in flight", "one_batch": "one batch in flight (before)"}
    lines += ["Whole transfer: from the first publish to the last message stored by the vehicle (to the vehicle) "
              "or back on AMQP (round trip), the first message's way through the empty pipeline included. Steady: from "
              "the first message stored (back) to the last, as the flood leaves its first second out.", "",
              "| Loss | Flood (B/s) | Flood with telemetry (B/s) | Variant | To the vehicle / flood | steady | "
              "Round trip / flood | Round trip / flood with telemetry | steady | Back identical |",
              "|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(s: dict[str, float]) -> str:
        return f"{s['median']:.2f} [{s['min']:.2f}-{s['max']:.2f}]"

    for loss, entry in results["summary"].items():
        for name in variants:
            v = entry[name]
            lines.append(f"| {loss} | {entry['flood_bytes_per_s']['median']:.0f} | "
                         f"{entry['flood_with_telemetry_bytes_per_s']['median']:.0f} | {names[name]} | "
                         f"**{fmt(v['forward_fraction_of_flood'])}** | {fmt(v['forward_steady_fraction_of_flood'])} | "
                         f"{fmt(v['fraction_of_flood'])} | **{fmt(v['fraction_of_flood_with_telemetry'])}** | "
                         f"{fmt(v['steady_fraction_of_flood_with_telemetry'])} | {', '.join(map(str, v['identical']))} |")
    lines += ["", "Per repetition (load average before/after):", "",
              "| Rep | Loss | Load | Flood | Flood+tel | Variant | To vehicle (B/s) | Round trip (B/s) | s to vehicle | s round trip |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for row in results["rows"]:
        for name in variants:
            r = row[name]
            lines.append(f"| {row['rep']} | {row['loss']:.0%} | {row['load_before'][0]}/{row['load_after'][0]} | "
                         f"{row['flood']:.0f} | {row['flood_with_telemetry']:.0f} | {names[name]} | "
                         f"{r['forward_bytes_per_s'] or 0:.0f} | {r['goodput_bytes_per_s']:.0f} | "
                         f"{r['forward_seconds'] or 0:.1f} | {r['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


async def main_async(args: argparse.Namespace) -> Path:
    from engine.endpoints.amqp.broker import LocalBroker

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    machine = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "commit": commit,
               "cpus": os.cpu_count(), "load_before": load()}
    node = LocalBroker()
    url = await asyncio.to_thread(node.start)
    began = time.monotonic()
    try:
        measured = await measure(url, args.reps, args.count, args.flood_seconds, args.ab)
    finally:
        await asyncio.to_thread(node.stop)
    machine["load_after"] = load()
    machine["seconds"] = round(time.monotonic() - began)
    results = {"machine": machine, "settings": {"reps": args.reps, "count": args.count,
                                                "flood_seconds": args.flood_seconds, "ab": args.ab}, **measured}
    (out / "goodput.json").write_text(json.dumps(results, indent=1, default=str))
    (out / "goodput.md").write_text(markdown(results))
    print(markdown(results))
    return out


def main() -> None:
    from engine.running.loop import run

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--count", type=int, default=200, help="250-byte messages per round trip")
    parser.add_argument("--flood-seconds", type=float, default=6.0)
    parser.add_argument("--ab", action="store_true", help="also one batch in flight (before), interleaved")
    parser.add_argument("--out", default=str(REPO / "bench" / "results" / datetime.date.today().isoformat() / "goodput"))
    run(main_async(parser.parse_args()))


if __name__ == "__main__":
    main()
