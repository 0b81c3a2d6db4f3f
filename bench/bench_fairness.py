"""Fairness under one agent's flood: the quiet agents' latency and losses with and without
``fair: {per: system_id}``, in the same run (tests/support/fairness_load.py describes the load: ten
vehicles at 10 Hz and one at 1,000 Hz on one UDP link, through one route into a link capped at
~500 frames/s; the engine a child process).

    .venv/bin/python -m bench.bench_fairness [--seconds 6] [--repeat 1] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

from tests.support.fairness_load import flood


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_fairness", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=6.0, help="seconds of flood per run")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--scale", type=float, default=1.0, help="multiply every rate, the sink's included")
    parser.add_argument("--out", type=Path, help="write the outcomes as JSON here")
    args = parser.parse_args(argv)
    results: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as work:
        for run in range(args.repeat):
            for fair in (True, False):
                outcome = flood(Path(work) / f"{run}", fair, seconds=args.seconds, drain=10.0, scale=args.scale)
                print(f"{'fair' if fair else 'fifo'}: {outcome.summary()}")
                results.append({"fair": fair, **dataclasses.asdict(outcome)})
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
