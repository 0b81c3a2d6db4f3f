"""report.md and the PNG plots of a ``python -m bench`` run, from its results.json."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

PAPER = {"CT-L1": {"50": 0.112, "150": 0.111, "250": 0.113}, "CT-L2": {"50": 0.832, "150": 0.838, "250": 0.831}}
TITLES = {"CT-L1": "CT-L1, AMQP -> ROS 2", "CT-L2": "CT-L2, ROS 2 -> AMQP"}


def _f(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _rate(result: dict[str, Any] | None) -> str:
    if not result:
        return "-"
    if "error" in result:
        return "error"
    text = f"{result.get('msg_per_s', float('nan')):.0f}"
    if result.get("lost"):
        text += f" (lost {result['lost']})"
    return text


def latency_tables(latency: dict[str, Any]) -> list[str]:
    lines = [f"## 1. Processing latency, the paper's method ({latency['runs']} x {latency['count']} messages "
             f"per size at {latency['rate']:g} msg/s), in milliseconds", ""]
    for setting, label in (("confirms_off", "publisher confirms off (the paper's configuration)"),
                           ("confirms_on", "publisher confirms on (the engine's default)")):
        for name, sizes in latency.get(setting, {}).items():
            lines += [f"**{TITLES[name]}, {label}**", "",
                      "| Size | Mean | Standard deviation | Minimum | Maximum | p50 | p99 | Paper mean |",
                      "|---|---|---|---|---|---|---|---|"]
            for size, s in sizes.items():
                lines.append(f"| {size} B | {_f(s.get('mean'))} | {_f(s.get('std'))} | {_f(s.get('min'))} | "
                             f"{_f(s.get('max'))} | {_f(s.get('p50'))} | {_f(s.get('p99'))} | {PAPER[name][size]:.3f} |")
            lines.append("")
        off = latency.get(setting, {})
        if "CT-L1" in off and "CT-L2" in off:
            ratios = [off["CT-L2"][size]["p50"] / off["CT-L1"][size]["p50"] for size in off["CT-L1"]
                      if off["CT-L1"][size].get("p50")]
            lines += [f"CT-L2 / CT-L1 median ratio ({label}): " + ", ".join(f"{r:.2f}" for r in ratios)
                      + " (the paper's: 7.4)", ""]
        lines += _parts_table(latency, setting, label)
    return lines


def _parts_table(latency: dict[str, Any], setting: str, label: str) -> list[str]:
    """Where t2 - t1 goes: the same message converted and sent again alone, at the same rate
    and back to back (the same calls, warm)."""
    parts = latency.get(f"{setting}_parts") or {}
    if not parts:
        return []
    lines = [f"The route's conversion and its sink's send timed alone ({label}), the same message again, "
             f"p50 in microseconds: one at a time at {latency['rate']:g} msg/s as above, then back to back", "",
             "| Route | Size | t2 - t1 (whole) | Conversion alone | Sink send alone | Conversion, back to back | Sink send, back to back |",
             "|---|---|---|---|---|---|---|"]
    for name, sizes in parts.items():
        for size, alone in sizes.items():
            whole = (latency.get(setting, {}).get(name, {}).get(size) or {}).get("p50")
            cells = [alone.get(part, {}).get("p50") for part in ("convert", "sink", "back_to_back_convert", "back_to_back_sink")]
            lines.append(f"| {name} | {size} B | {_us(whole)} | " + " | ".join(_us(c) for c in cells) + " |")
    return lines + [""]


def _us(ms: float | None) -> str:
    return "-" if ms is None else f"{ms * 1000:.0f}"


def _ratio(row: dict[str, Any], role: str, key: str = "vs") -> str:
    """The median per-round ratio with its min-max and interquartile range."""
    spread = row.get(f"{key}_{role}_spread")
    if not spread:
        return _f(row.get(f"vs_{role}"), 2)
    return (f"**{spread['median']:.2f}** ({spread['min']:.2f}-{spread['max']:.2f}; "
            f"IQR {spread['q1']:.2f}-{spread['q3']:.2f}; n={spread['n']})")


def _rates(result: dict[str, Any] | None) -> str:
    """The median rate of a role's drains, with its min-max."""
    if not result or "min" not in result:
        return _rate(result)
    text = f"{result['median']:.0f} ({result['min']:.0f}-{result['max']:.0f})"
    return text + (f" (lost {result['lost']})" if result.get("lost") else "")


def throughput_table(throughput: dict[str, Any]) -> list[str]:
    lines = ["## 2-3. Throughput against the references, interleaved rounds in the same run", "",
             "Each route kind: rounds of one drain per system of the same backlog, in alternating order (A B, B A, ...), "
             "the ratio taken within each round (bench/throughput.py). Ratios: median per round (min-max; interquartile "
             "range; rounds); rates: median msg/s (min-max).", "",
             "| Route kind (GNSS position route) | Engine / reference | Engine msg/s | Reference msg/s | "
             "CPU per message, reference / engine | Engine / paper | Paper's design msg/s | "
             "Engine latency at half rate p50 / p99 (ms) |",
             "|---|---|---|---|---|---|---|---|"]
    names = {"amqp-amqp": "AMQP -> AMQP", "amqp-ros2": "AMQP -> ROS 2", "ros2-amqp": "ROS 2 -> AMQP",
             "mavlink-amqp": "MAVLink (UDP) -> AMQP"}
    for kind, row in throughput.items():
        half = row.get("latency_half_rate") or {}
        latency = f"{_f(half.get('p50'))} / {_f(half.get('p99'))}" if "p50" in half else "-"
        loads = [r["load"] for r in row.get("rounds", []) if "load" in r]
        load = f" (load {min(loads):.1f}-{max(loads):.1f})" if loads else ""
        cpu = _ratio(row, "reference", "cpu_vs")
        if "cpu_us_per_msg" in (row.get("engine") or {}) and "cpu_us_per_msg" in (row.get("reference") or {}):
            cpu += f" [{row['reference']['cpu_us_per_msg']:.0f} / {row['engine']['cpu_us_per_msg']:.0f} us]"
        lines.append(f"| {names.get(kind, kind)}{load} | {_ratio(row, 'reference')} | {_rates(row.get('engine'))} | "
                     f"{_rates(row.get('reference'))} | {cpu} | {_ratio(row, 'paper')} | {_rates(row.get('paper'))} | {latency} |")
    lines += ["", "Drains (rate at the sink, from 10 % of the messages to the last; only the measured system runs, "
              "the others are stopped): AMQP sources a queue filled while the bridge was stopped; ROS 2 sources a "
              "burst held by DDS history; MAVLink a UDP receive buffer filled while the bridge was stopped. CPU per "
              "message: the bridge's processes' user + system time over the same window (medians in brackets, "
              "microseconds), the ratio per round, above 1 when the engine spends less. References: aiormq consume (prefetch 1,000) -> the route's conversion written by hand -> "
              "pipelined publish per batch on a confirm channel -> one ack(multiple) per batch; the same consumer -> "
              "rclpy String publish; an rclpy subscription taken in batches -> the batched aiormq publisher; UDP -> "
              "pymavlink parse_buffer -> the batched aiormq publisher. Paper's design: aio-pika, rclpy's default "
              "executor spun from the asyncio loop, jsonschema, synchronous logging, confirms off. Load: the 1-minute "
              "load average at each round's start.", ""]
    return lines


def sizes_table(rows: list[dict[str, Any]]) -> list[str]:
    lines = ["## Throughput against message size (AMQP -> AMQP identity raw_json route), msg/s", "",
             "| Size | Engine | aiormq pass-through | Engine / reference |", "|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['size']} B | {_rate(row.get('engine'))} | {_rate(row.get('ref-amqp-amqp'))} | {_f(row.get('ratio'), 2)} |")
    return lines + [""]


def routes_table(rows: list[dict[str, Any]]) -> list[str]:
    lines = ["## 4. Many routes (AMQP -> AMQP GNSS routes, one queue each)", "",
             "| Routes | check (s) | load, new queues (s) | load, queues exist (s) | RSS after load (MiB) | "
             "Per-message cost (us) | vs 1 route | Engine CPU per message (us) | vs 1 route |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row['routes']} | {_f(row['check_s'])} | {_f(row['load_s'])} | "
                     f"{_f(row.get('reload_existing_queues_s'))} | {_f(row['rss_mib'], 1)} | "
                     f"{_f(row['us_per_msg'], 1)} | {_f(row['cost_vs_one_route'], 2)} | "
                     f"{_f(row.get('cpu_us_per_msg'), 1)} | {_f(row.get('cpu_vs_one_route'), 2)} |")
    return lines + ["", "check = parse, validate and compile the directory in process (`rabbitros-engine check` "
                    "without interpreter start-up); load = Engine.start (connection, queue declarations, consumers); "
                    "per-message cost = 1 / drain rate of one route while all are loaded (wall clock: moves with the "
                    "machine's load); engine CPU per message = the engine process's CPU time during that drain / "
                    "messages (what the engine itself spends).", ""]


def sik_table(sik: dict[str, Any]) -> list[str]:
    lines = [f"## 5. JSON over the emulated SiK radio ({sik.get('loss', 0.0):.0%} loss)", "",
             "| Message | Messages back identical | Goodput each way (B/s) | Link payload capacity (B/s) | Fraction |",
             "|---|---|---|---|---|",
             f"| {sik['size']} B | {sik['identical']}/{sik['sent']} | {sik['goodput_bytes_per_s']:.0f} | "
             f"{sik['payload_bytes_per_s']:.0f} | {sik['fraction_of_capacity']:.2f} |", "",
             f"Capacity: TUNNEL payload one direction can carry at best on the emulator's timing "
             f"({sik['frames_per_packet']} frame(s) of {sik['tunnel_payload']} B payload per air packet).", ""]
    if "flood_payload_bytes_per_s" in sik:
        lines += ["| Reference, measured in this run | TUNNEL payload (B/s) | Goodput as a fraction |", "|---|---|---|",
                  f"| the radio flooded with {sik['tunnel_payload']} B payloads at the same loss | {sik['flood_payload_bytes_per_s']:.0f} | "
                  f"{sik['fraction_of_flood']:.2f} |",
                  f"| the same, with the vehicle's telemetry on the link (the way back) | "
                  f"{sik['flood_with_telemetry_bytes_per_s']:.0f} | {sik['fraction_of_flood_with_telemetry']:.2f} |"]
        if sik.get("forward_goodput_bytes_per_s"):
            lines += [f"| the way to the vehicle alone ({sik['forward_goodput_bytes_per_s']:.0f} B/s to the last message "
                      f"stored), against the plain flood | {sik['flood_payload_bytes_per_s']:.0f} | "
                      f"{sik['forward_fraction_of_flood']:.2f} |"]
        lines += ["", "The round trip is bounded by its way back, which the vehicle's telemetry shares: compare it with "
                  "the flood with telemetry. bench/goodput.py repeats these figures (median and spread).", "",
                  "The flood keeps the radio's buffer backlogged without overflowing it; it shows what the emulator "
                  "carries (each air packet starts at its next 4 ms tick, not the instant the window opens). "
                  "Goodput counts JSON bytes, the capacities TUNNEL payload (the tunnel's header included).", ""]
    return lines


def discovery_table(discovery: dict[str, Any]) -> list[str]:
    lines = ["## 6. ROS 2 topic discovery: a robot's topic appears -> its first message at RabbitMQ", "",
             f"Each robot publishes at {discovery['rate_hz']:.0f} Hz from its publisher's creation; the engine reads the "
             f"graph every {discovery['scan_interval_s']} s (bench/bench_discovery.py).", "",
             "| Robots | delivered | appear -> delivered p50 / max (ms) | appear -> matched p50 / max (ms) | "
             "matched -> delivered p50 / max (ms) |", "|---|---|---|---|---|"]
    for name in ("staggered", "burst"):
        row = discovery[name]
        cells = [f"{_f(row[key].get('p50'), 0)} / {_f(row[key].get('max'), 0)}"
                 for key in ("appear_to_delivered_ms", "appear_to_matched_ms", "matched_to_delivered_ms")]
        how = f"one every {row['stagger_s']} s" if row["stagger_s"] else "all at once"
        lines.append(f"| {row['robots']}, {how} | {row['delivered']}/{row['robots']} | " + " | ".join(cells) + " |")
    none, idle = discovery.get("idle_following_none", {}), discovery.get("idle_following", {})
    return lines + ["", f"Engine CPU with nothing published: {_f(none.get('engine_cpu_percent'), 2)} % following no topic, "
                    f"{_f(idle.get('engine_cpu_percent'), 2)} % following {idle.get('topics')}.", ""]


def calls_table(calls: dict[str, Any]) -> list[str]:
    engine, plain = calls["through_engine"], calls["plain_rclpy"]
    rpc = calls.get("plain_amqp_rpc")
    amqp = [f"| AMQP legs alone (an aio-pika RPC worker) | {rpc['calls']} | {_f(rpc['p50_ms'])} | {_f(rpc['p99_ms'])} |"] if rpc else []
    return ["## 7. A ROS 2 service call's round trip, one call at a time (bench/call_ros2.py)", "",
            "The same test_msgs/srv/BasicTypes server: called from AMQP through the engine (direct reply-to, "
            "AMQP -> ROS 2 -> AMQP) and by a plain rclpy client, in the same run.", "",
            "| Caller | calls | p50 (ms) | p99 (ms) |", "|---|---|---|---|",
            f"| through the engine | {engine['calls']} | {_f(engine['p50_ms'])} | {_f(engine['p99_ms'])} |",
            f"| plain rclpy client | {plain['calls']} | {_f(plain['p50_ms'])} | {_f(plain['p99_ms'])} |",
            f"| engine / rclpy | | {_f(calls['p50_ratio'], 1)} x | {_f(calls['p99_ratio'], 1)} x |", *amqp, "",
            "The engine's round trip holds two AMQP legs (each a broker hop) and one ROS 2 call; the AMQP legs alone "
            "are an aio-pika worker answering the same caller at once (aio-pika costs more per message than the "
            "engine's aiormq path: context, not a floor).", ""]


def radio_latency_table(rows: list[dict[str, Any]]) -> list[str]:
    from bench.radio_latency import HEADER, format_row

    return ["## 9. MAVLink latency over the emulated SiK radio: the engine against MAVSDK", "",
            "Telemetry: the vehicle's GLOBAL_POSITION_INT from its send to the ground station's consumer (the engine: "
            "an AMQP consumer behind a telemetry route; MAVSDK 4.1.0: its MavlinkDirect subscription). Command: an "
            "arm COMMAND_LONG to its COMMAND_ACK (the engine: an AMQP call answered by the ack; MAVSDK: Action.arm() "
            "returning). Two vehicles behind the same radio: the simulated one and MAVSDK's own (its C++ core as an "
            "autopilot on the radio's serial port). One clock stamps both ends. Loads: TUNNEL frames (the engine: a "
            "low route, paced; MAVSDK: MavlinkDirect at 2,880 B/s, it has no tunnel client and no priorities) and the "
            "engine's JSON tunnel (needs the simulated vehicle). MAVSDK has no MAVLink signing: signed rows are the "
            "engine's only (bench/radio_latency.py).",
            "", HEADER, *(format_row(row) for row in rows), ""]


def mission_table(rows: list[dict[str, Any]]) -> list[str]:
    from bench.mission_upload import HEADER, format_row

    return ["## 10. Mission upload over the emulated SiK radio: the engine against MAVSDK", "",
            "The engine's mission sink, a plain pymavlink loop and MAVSDK's MissionRaw client (the mavsdk wheel as the "
            "ground station, with its default 0.5 s timeout and with set_timeout_s(1.5), the engine's), one after the "
            "other through the same radio to the same vehicle: the simulated one and MAVSDK's own (MissionRawServer on "
            "the radio's serial port). Median of the runs; a client that gave up says so (bench/mission_upload.py).",
            "", HEADER, *(format_row(row) for row in rows), ""]


def write_report(results: dict[str, Any], out: Path) -> None:
    before, after = results.get("machine_before", {}), results.get("machine_after", {})
    lines = ["# RabbitROS engine benchmark", "",
             f"{before.get('date')}, commit {before.get('commit')}, {before.get('cpus')} CPUs, loop {before.get('loop')}; "
             f"load average before {_load(before)}, after {_load(after)} (the machine is shared: absolute figures "
             f"move with its load, ratios are measured in the same run). Total {results.get('seconds', 0):.0f} s.", ""]
    for key, render in (("latency", latency_tables), ("ct_l1", ct_l1_table), ("throughput", throughput_table), ("sizes", sizes_table),
                        ("routes", routes_table), ("sik", sik_table), ("discovery", discovery_table), ("sik5", sik_table),
                        ("calls", calls_table), ("fleet", fleet_table),
                        ("radio_latency", radio_latency_table), ("mission", mission_table), ("workers", workers_table)):
        value = results.get(key)
        if value is None:
            continue
        if isinstance(value, dict) and "error" in value:
            lines += [f"## {key}: failed", "", "```", value["error"], "```", ""]
            continue
        try:
            lines += render(value)
        except Exception as exc:  # a partial result must not lose the rest of the report
            lines += [f"## {key}: cannot render ({type(exc).__name__}: {exc})", ""]
    lines += ["Plots: " + ", ".join(f"`{p}`" for p in plots(results, out)), ""]
    (out / "report.md").write_text("\n".join(lines))


def ct_l1_table(result: dict[str, Any]) -> list[str]:
    from bench.ct_l1 import report

    return ["## 1b. CT-L1 at a robot's pace: the engine against the paper's design, same machine, same run", "",
            *report(result), ""]


def workers_table(result: dict[str, Any]) -> list[str]:
    from bench.bench_workers import report

    return ["## 11. A backlog drained AMQP -> AMQP by 1 and 2 engine workers (run --workers), same run", "", *report(result)]


def fleet_table(fleet: dict[str, Any]) -> list[str]:
    from bench.fleet import fleet_report

    return ["## 8. A fleet: 100 agents through templated, shared and hand-written routes, against the same bridge on the client libraries", "",
            *fleet_report(fleet), ""]


def _load(machine: dict[str, Any]) -> str:
    load = machine.get("loadavg")
    return "/".join(f"{x:.1f}" for x in load) if load else "-"


def plots(results: dict[str, Any], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    latency = results.get("latency")
    if isinstance(latency, dict) and "confirms_off" in latency:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, name in zip(axes, ("CT-L1", "CT-L2")):
            for setting, style in (("confirms_off", "-"), ("confirms_on", "--")):
                for size, s in latency.get(setting, {}).get(name, {}).items():
                    samples = sorted(s.get("samples") or [])
                    if samples:
                        ax.plot(samples, [i / len(samples) for i in range(len(samples))], style,
                                label=f"{size} B, {setting.replace('_', ' ')}")
            ax.set_xscale("log")
            ax.set_xlabel("t2 - t1 (ms)")
            ax.set_ylabel("fraction of messages")
            ax.set_title(TITLES[name])
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "latency_distributions.png", dpi=110)
        plt.close(fig)
        written.append("latency_distributions.png")
    sizes = results.get("sizes")
    if isinstance(sizes, list) and sizes:
        fig, ax = plt.subplots(figsize=(6, 4))
        xs = [row["size"] for row in sizes]
        for system, label in (("engine", "engine"), ("ref-amqp-amqp", "aiormq pass-through")):
            ax.plot(xs, [row[system].get("msg_per_s", float("nan")) for row in sizes], "o-", label=label)
        ax.set_xscale("log")
        ax.set_xlabel("message size (B)")
        ax.set_ylabel("msg/s (AMQP -> AMQP, zero loss)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "throughput_vs_size.png", dpi=110)
        plt.close(fig)
        written.append("throughput_vs_size.png")
    routes = results.get("routes")
    if isinstance(routes, list) and routes:
        fig, ax = plt.subplots(figsize=(6, 4))
        xs = [row["routes"] for row in routes]
        ax.plot(xs, [row["msg_per_s"] for row in routes], "o-", label="msg/s through one route")
        ax.set_xscale("log")
        ax.set_xlabel("routes loaded")
        ax.set_ylabel("msg/s")
        twin = ax.twinx()
        twin.plot(xs, [row["load_s"] for row in routes], "s--", color="tab:red", label="load (s)")
        twin.set_ylabel("load time (s)")
        fig.legend(loc="lower left")
        fig.tight_layout()
        fig.savefig(out / "throughput_vs_routes.png", dpi=110)
        plt.close(fig)
        written.append("throughput_vs_routes.png")
    throughput = results.get("throughput")
    if isinstance(throughput, dict) and throughput:
        fig, ax = plt.subplots(figsize=(8, 4))
        kinds = list(throughput)
        for offset, role in ((-0.27, "reference"), (0, "engine"), (0.27, "paper")):
            values = [(throughput[k].get(role) or {}).get("msg_per_s", 0) or 0 for k in kinds]
            ax.bar([i + offset for i in range(len(kinds))], values, width=0.27, label=role)
        ax.set_xticks(range(len(kinds)), kinds)
        ax.set_ylabel("msg/s, zero loss")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "throughput_by_route_kind.png", dpi=110)
        plt.close(fig)
        written.append("throughput_by_route_kind.png")
    return written
