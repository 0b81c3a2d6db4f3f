"""Route files that cannot exhaust the engine (issue 32): the "billion laughs" (nine lines of
anchors, each list ten aliases of the one before: 10^9 nodes, 5.3 GB before the bounds) and
files past the size, node and depth bounds are refused with ``file:line`` within a second and a
few MB, by the loader, by ``check`` (a real subprocess, its peak RSS taken from ``wait4``) and in
route test and ``for_each`` files; a running engine refusing one on reload is in
tests/running/test_reload_edits.py."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import pytest

from engine.common.schemas import SchemaRegistry
from engine.language import yaml_bounds
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.route_tests import load_tests
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

SCHEMAS = SchemaRegistry(REPO / "schemas")
ROUTE = """routes:
  - name: r
    source: {amqp: {queue: q}}
    schema: raw_json
    sink: {amqp: {exchange: e, routing_key: k}}
"""


def laughs(levels: int = 9, key: str = "x") -> str:
    """``levels`` lines, each a list of ten aliases of the one before: 10^levels nodes."""
    lines = [f'{key}a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for level in range(1, levels):
        name, previous = chr(ord("a") + level), chr(ord("a") + level - 1)
        lines.append(f"{key}{name}: &{name} [" + ",".join([f"*{previous}"] * 10) + "]")
    return "\n".join(lines) + "\n"


BOMB = "routes: []\n" + laughs()


def refused(directory: Path) -> tuple[list[str], float, int]:
    """The problems loading ``directory``, the seconds it took and the peak bytes allocated."""
    tracemalloc.start()
    began = time.monotonic()
    try:
        with pytest.raises(RoutesInvalid) as caught:
            load_routes(directory, SCHEMAS, env={})
        elapsed = time.monotonic() - began
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return [str(problem) for problem in caught.value.problems], elapsed, peak


def test_the_billion_laughs_is_refused_at_its_alias_within_a_second_and_a_few_mb(tmp_path: Path):
    (tmp_path / "bomb.yaml").write_text(BOMB)
    problems, elapsed, peak = refused(tmp_path)
    print(f"billion laughs refused in {elapsed * 1e3:.1f} ms, peak {peak / 1e6:.2f} MB allocated")
    # the aliases of line 6 (each 11,111 nodes) take the copies past 100,000
    assert problems == [f"{tmp_path}/bomb.yaml:6: alias *d copies 11,111 nodes, and the file's aliases more than 100,000 "
                        "in all (a bound that keeps one file from exhausting the engine: anchors of aliases of aliases "
                        "grow tenfold per line, the 'billion laughs'); write the values out, or use a route template (for_each)"]
    assert elapsed < 1.0 and peak < 8e6


def test_check_refuses_the_billion_laughs_in_a_few_mb_more_than_a_clean_check(tmp_path: Path):
    """``check`` as an operator runs it; its peak RSS against that of a clean one-route check."""

    clean, bomb = tmp_path / "clean", tmp_path / "bomb"
    clean.mkdir()
    bomb.mkdir()
    (clean / "r.yaml").write_text(ROUTE)
    (bomb / "r.yaml").write_text(ROUTE)
    (bomb / "bomb.yaml").write_text(BOMB)
    clean_rc, _, clean_s, clean_kib = run_measured(clean)
    bomb_rc, output, bomb_s, bomb_kib = run_measured(bomb)
    print(f"check: clean {clean_s:.2f} s {clean_kib / 1024:.1f} MiB; billion laughs {bomb_s:.2f} s {bomb_kib / 1024:.1f} MiB")
    assert clean_rc == 0 and bomb_rc == 1, output
    assert f"{bomb}/bomb.yaml:6: alias *d copies 11,111 nodes" in output
    assert bomb_kib - clean_kib < 8 * 1024, "the refused file cost more than a few MB"
    # the process's start and imports take 2-4 s on a loaded 2-core machine (the refusal itself is
    # timed in process above); the unbounded loader was still running after 60 s
    assert bomb_s < 20


def run_measured(directory: Path) -> tuple[int, str, float, int]:
    """``rabbitros-engine check --routes directory``: exit status, output, seconds, peak RSS (KiB)."""
    began = time.monotonic()
    process = subprocess.Popen([sys.executable, "-m", "engine", "check", "--routes", str(directory)],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    assert process.stdout is not None
    output = process.stdout.read().decode()
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return process.returncode, output, time.monotonic() - began, usage.ru_maxrss


def test_a_file_over_the_size_bound_is_refused_without_reading_it_whole(tmp_path: Path):
    with open(tmp_path / "huge.yaml", "wb") as handle:
        handle.write(b"routes: []\n")
        handle.truncate(64 * 1024 * 1024)  # sparse: 64 MiB on paper
    problems, elapsed, peak = refused(tmp_path)
    assert problems == [f"{tmp_path}/huge.yaml:1: the file is 67,108,864 bytes, over the 4,194,304 bytes (4 MiB) a route, "
                        "test or for_each file may hold (a bound that keeps one file from exhausting the engine); "
                        "split it into several files"]
    assert peak < 2 * yaml_bounds.MAX_FILE_BYTES + 1e6 and elapsed < 1.0


def test_nodes_past_the_bound_are_refused_before_they_are_composed(tmp_path: Path):
    """One node past the bound; composing these 250,000 nodes would take ~4 s and ~75 MB."""
    lines = yaml_bounds.MAX_NODES // 8 + 1
    (tmp_path / "many.yaml").write_text("routes: []\nx:\n" + "  - [1, 2, 3, 4, 5, 6, 7]\n" * lines)
    began = time.monotonic()
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(tmp_path, SCHEMAS, env={})
    elapsed = time.monotonic() - began
    print(f"{yaml_bounds.MAX_NODES:,} nodes refused in {elapsed:.2f} s")
    # 5 nodes before the list's items, 8 per line: node 250,001 is on the list's line 31,250
    assert [str(p) for p in caught.value.problems] == [
        f"{tmp_path}/many.yaml:31252: more than 250,000 YAML nodes in one file (a bound that keeps one file from "
        "exhausting the engine); split it into several files"]
    assert elapsed < 3.0


def test_nesting_past_the_bound_is_refused_with_its_line(tmp_path: Path):
    depth = yaml_bounds.MAX_DEPTH
    (tmp_path / "deep.yaml").write_text("routes: []\nx:\n" + "".join(f"{'  ' * level}- \n" for level in range(1, depth)) + f"{'  ' * depth}- 1\n")
    (tmp_path / "flow.yaml").write_text("routes: []\ny: " + "[" * (depth + 1) + "]" * (depth + 1) + "\n")
    problems, _, _ = refused(tmp_path)
    assert problems == [f"{tmp_path}/deep.yaml:{depth + 2}: nested deeper than 100 levels (a bound that keeps one file from exhausting the engine)",
                        f"{tmp_path}/flow.yaml:2: nested deeper than 100 levels (a bound that keeps one file from exhausting the engine)"]


def test_a_recursive_alias_is_named_at_the_alias(tmp_path: Path):
    (tmp_path / "loop.yaml").write_text("routes: []\nx: &loop\n  - 1\n  - *loop\n")
    problems, _, _ = refused(tmp_path)
    assert problems == [f"{tmp_path}/loop.yaml:4: invalid YAML: alias *loop inside its own anchor &loop (a recursive structure has no end)"]


def test_aliases_within_the_bound_still_share_values(tmp_path: Path):
    """A sink written once and aliased into 200 routes copies ~1,600 nodes: loaded as written."""
    routes = "".join(f"  - name: r{index}\n    source: {{amqp: {{queue: q{index}}}}}\n    schema: raw_json\n    sink: *sink\n"
                     for index in range(1, 200))
    (tmp_path / "r.yaml").write_text("routes:\n  - name: r0\n    source: {amqp: {queue: q0}}\n    schema: raw_json\n"
                                     "    sink: &sink {amqp: {exchange: e, routing_key: k}}\n" + routes)
    config = load_routes(tmp_path, SCHEMAS, env={})
    assert len(config.routes) == 200 and config.routes["r199"].sink.options.exchange == "e"


def test_route_test_and_for_each_files_are_bounded_too(tmp_path: Path):
    (tmp_path / "r.yaml").write_text(ROUTE + """  - name: t-{n}
    for_each: items.yaml
    source: {amqp: {queue: "q{n}"}}
    schema: raw_json
    sink: {amqp: {exchange: e, routing_key: k}}
""")
    (tmp_path / "items.yaml").write_text("- n: 1\n  " + laughs(key="x").replace("\n", "\n  ").rstrip() + "\n")
    (tmp_path / "r.test.yaml").write_text("tests: []\n" + laughs())
    problems, _, _ = refused(tmp_path)
    assert problems[0].startswith(f"{tmp_path}/items.yaml:6: alias *d copies 11,111 nodes"), problems
    config_dir = tmp_path / "good"
    config_dir.mkdir()
    (config_dir / "r.yaml").write_text(ROUTE)
    (config_dir / "r.test.yaml").write_text("tests: []\n" + laughs())
    cases, test_problems = load_tests(config_dir, load_routes(config_dir, SCHEMAS, env={}), env={})
    assert cases == [] and [str(p) for p in test_problems] == [
        f"{config_dir}/r.test.yaml:6: alias *d copies 11,111 nodes, and the file's aliases more than 100,000 in all (a bound "
        "that keeps one file from exhausting the engine: anchors of aliases of aliases grow tenfold per line, the 'billion "
        "laughs'); write the values out, or use a route template (for_each)"]
