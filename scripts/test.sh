#!/usr/bin/env bash
# Sets everything up, then runs the whole test suite against real RabbitMQ, rclpy and pymavlink,
# in three pytest runs sharing one 1500 s bound:
#   1. the fast tier: the tests marked `fast` (no broker, no network peer, no ROS 2 node: the route
#      language, check, test, plan, mappings, schemas, codecs; about 490 tests, 54 s on 3 workers), on
#      $RABBITROS_TEST_WORKERS workers. When it fails the run stops there, its failures first and
#      alone, without waiting out the broker tests;
#   2. every other test but the `alone` ones, on $RABBITROS_TEST_WORKERS pytest-xdist workers
#      (default 3: most tests wait on brokers, ROS 2 and sockets, so more workers than cores pay).
#      Each worker has its own RabbitMQ node, ROS 2 domains and ports (tests/support/workers.py). A
#      module's tests share a worker (--dist loadfile: module-scoped fixtures and the cluster start
#      once), and the modules with `soak` tests go first (tests/conftest.py; --no-loadscope-reorder
#      keeps that order);
#   3. the tests marked `alone` (timing-sensitive), one after another, with nothing beside them.
# Every test has its own timeout (pyproject.toml, pytest-timeout): a hung test fails by name.
# Arguments go to every run (test files, -k, -x, --durations=N ...); a run that selects no test
# is not a failure unless none selects any. RABBITROS_TEST_WORKERS=0: no workers (one process).
# Before the tests, the static checks (configured in pyproject.toml; seconds with their caches):
# ruff's lint over engine/, tests/, bench/, rabbitros_sim/ and mypy over engine/, tests/support/,
# bench/, rabbitros_sim/ (and the test modules these import). A finding fails the run before any
# broker starts.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

.venv/bin/ruff check
.venv/bin/mypy

workers=${RABBITROS_TEST_WORKERS:-3}
deadline=$((SECONDS + 1500))
pytest() {
  local left=$((deadline - SECONDS))
  [ "$left" -gt 0 ] || { echo "test.sh: the 1500 s are up" >&2; return 124; }
  timeout -s KILL "$left" .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
}

NO_TESTS=5
fast=0 parallel=0 alone=0
pytest -n "$workers" --dist load --fast only "$@" || fast=$?
if [ "$fast" != 0 ] && [ "$fast" != $NO_TESTS ]; then
  echo "test.sh: the fast tier failed (exit $fast); the broker tests did not run" >&2
  exit "$fast"
fi
pytest -n "$workers" --dist loadfile --no-loadscope-reorder --fast exclude --alone exclude "$@" || parallel=$?
pytest --fast exclude --alone only "$@" || alone=$?

if [ "$fast" = $NO_TESTS ] && [ "$parallel" = $NO_TESTS ] && [ "$alone" = $NO_TESTS ]; then exit $NO_TESTS; fi
[ "$parallel" = $NO_TESTS ] && parallel=0
[ "$alone" = $NO_TESTS ] && alone=0
exit $((parallel > alone ? parallel : alone))
