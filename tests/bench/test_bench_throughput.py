"""The throughput method of ``python -m bench`` (bench/throughput.py, issue 20) runs short and
loses nothing: interleaved rounds (A B, B A) of the engine and the MAVLink reference draining
a UDP receive buffer filled while each was stopped, the ratio taken per round, and the
report's table showing its median and spread. The figures are the benchmark's (bench/results/),
not this test's: it asserts only that every drain delivered every message and that the
summary and the table are built from the rounds."""

from __future__ import annotations

import asyncio
import math

from bench import throughput as tp
from bench.report import throughput_table


async def _rounds(url: str) -> dict:
    broker = tp.Broker(url)
    await broker.open()
    try:
        return await tp.interleaved(broker, "mavlink-amqp", {"reference": "ref-mavlink-amqp", "engine": "engine"},
                                    pairs=2, count=1500, domain=tp.domain_id())
    finally:
        await broker.close()


def test_interleaved_rounds_drain_everything_and_give_a_ratio_per_round(amqp_url: str) -> None:
    row = asyncio.run(_rounds(amqp_url))
    rounds = row["rounds"]
    assert [list(r)[1:] for r in rounds] == [["reference", "engine"], ["engine", "reference"]]  # A B, then B A
    for trial in rounds:
        for role in ("reference", "engine"):
            assert (trial[role]["delivered"], trial[role]["lost"], trial[role]["kernel_drops"]) == (1500, 0, 0), trial[role]
            cpu = trial[role]["cpu_us_per_msg"]
            assert trial[role]["msg_per_s"] > 0 and (cpu > 0 or math.isnan(cpu))  # nan: shorter than the CPU clock's ticks
    ratios = sorted(r["engine"]["msg_per_s"] / r["reference"]["msg_per_s"] for r in rounds)
    spread = row["vs_reference_spread"]
    assert (spread["min"], spread["max"], spread["n"]) == (ratios[0], ratios[1], 2)
    assert row["vs_reference"] == (ratios[0] + ratios[1]) / 2
    table = "\n".join(throughput_table({"mavlink-amqp": row}))
    assert f"**{row['vs_reference']:.2f}** ({ratios[0]:.2f}-{ratios[1]:.2f}" in table


def test_summary_of_rounds_leaves_failed_drains_out() -> None:
    good = {"msg_per_s": 100.0, "cpu_us_per_msg": 50.0, "lost": 0}
    rounds = [{"load": 1.0, "reference": good, "engine": {"msg_per_s": 90.0, "cpu_us_per_msg": 60.0, "lost": 0}},
              {"load": 1.0, "reference": good, "engine": {"msg_per_s": 95.0, "cpu_us_per_msg": 55.0, "lost": 3}},
              {"load": 1.0, "reference": {"error": "RuntimeError: no ready", "msg_per_s": float("nan")}, "engine": good}]
    row = tp.summarize(rounds, ["reference", "engine"], 3, {"reference": 10, "engine": 10})
    assert row["vs_reference_spread"]["n"] == 1 and row["vs_reference"] == 0.9  # only the first round is whole
    assert row["engine"]["lost"] == 3 and row["reference"]["n"] == 2
