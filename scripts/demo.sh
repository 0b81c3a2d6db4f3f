#!/usr/bin/env bash
# Sets everything up, then runs the main job: the engine on the shipped routes with a private
# RabbitMQ node, a generator publishing UAV weed detections and a consumer printing the
# canonical messages that come out.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

work=$(mktemp -d)
cleanup() {
  [ -n "${engine_pid:-}" ] && kill -TERM -- "-$engine_pid" 2>/dev/null && wait "$engine_pid" 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT

setsid timeout -s KILL 600 .venv/bin/rabbitros-engine --routes "${ROUTES:-routes/}" --local-broker \
  --broker-url-file "$work/url" --status-file "$work/status.json" &
engine_pid=$!
for _ in $(seq 120); do [ -s "$work/status.json" ] && break; sleep 0.5; done
[ -s "$work/status.json" ] || { echo "demo: engine did not start" >&2; exit 1; }

timeout -s KILL 120 .venv/bin/python examples/generator.py --url "$(cat "$work/url")" --count "${COUNT:-20}"
.venv/bin/rabbitros-engine status --status-file "$work/status.json"
