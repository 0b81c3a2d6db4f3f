#!/usr/bin/env bash
# Sets everything up, then runs the whole test suite against real RabbitMQ, rclpy and pymavlink.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec timeout -s KILL 1500 .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
