#!/usr/bin/env bash
# Sets everything up, then runs the whole test suite against real RabbitMQ, rclpy and pymavlink,
# in two pytest runs sharing one 1500 s bound:
#   1. every test but the `alone` ones, on $RABBITROS_TEST_WORKERS pytest-xdist workers (default 3:
#      most tests wait on brokers, ROS 2 and sockets, so more workers than cores pay). Each worker
#      has its own RabbitMQ node, ROS 2 domains and ports (tests/support/workers.py). A module's tests
#      share a worker (--dist loadfile: module-scoped fixtures and the cluster start once), and the
#      modules with `soak` tests go first (tests/conftest.py; --no-loadscope-reorder keeps that order);
#   2. the tests marked `alone` (timing-sensitive), one after another, with nothing beside them.
# Arguments go to both runs (test files, -k, -x, --durations=N ...); a run that selects no test
# is not a failure unless neither selects any. RABBITROS_TEST_WORKERS=0: no workers (one process).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

workers=${RABBITROS_TEST_WORKERS:-3}
deadline=$((SECONDS + 1500))
pytest() {
  local left=$((deadline - SECONDS))
  [ "$left" -gt 0 ] || { echo "test.sh: the 1500 s are up" >&2; return 124; }
  timeout -s KILL "$left" .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
}

parallel=0 alone=0
pytest -n "$workers" --dist loadfile --no-loadscope-reorder --alone exclude "$@" || parallel=$?
pytest --alone only "$@" || alone=$?

NO_TESTS=5
if [ "$parallel" = $NO_TESTS ] && [ "$alone" = $NO_TESTS ]; then exit $NO_TESTS; fi
[ "$parallel" = $NO_TESTS ] && parallel=0
[ "$alone" = $NO_TESTS ] && alone=0
exit $((parallel > alone ? parallel : alone))
