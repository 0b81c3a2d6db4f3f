#!/usr/bin/env bash
# Sets everything up, then runs the main job: the farm example (examples/farm_uav_gcs.yaml) with
# every part real on this machine: a simulated UAV on MAVLink 2 through an emulated SiK radio, a
# ROS 2 ground robot, the engine with a private RabbitMQ node, and the supervisory software that
# turns the UAV's weed detections into missions for the robot and calls the robot (its sprayer's
# service, a row action) over AMQP request/reply.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# RECORD=DIR records every route of the farm in MCAP files in DIR (docs/operations.md, Recording and replay).
exec timeout -s KILL 600 .venv/bin/python examples/farm_demo.py --duration "${DURATION:-30}" ${RECORD:+--record "$RECORD"}
