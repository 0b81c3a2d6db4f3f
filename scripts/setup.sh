#!/usr/bin/env bash
# Idempotent set-up of a fresh machine: Debian's rabbitmq-server (run as private nodes by the
# engine and the tests), mosquitto (private MQTT brokers for the tests; the system service the
# package may start is not used), iproute2 (network namespaces for the two-host tests), chromium
# and chromium-driver (the web console's browser test, headless, driven by selenium), and a
# virtualenv in .venv with the package and all its dependencies, ROS 2 Jazzy wheels included.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
[ "$(id -u)" = 0 ] || SUDO=sudo
missing=()
ls /usr/lib/rabbitmq/lib/rabbitmq_server-*/sbin/rabbitmq-server >/dev/null 2>&1 || missing+=(rabbitmq-server)
command -v ip >/dev/null 2>&1 || missing+=(iproute2)
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || missing+=(mosquitto)
[ -x /usr/bin/chromium ] || missing+=(chromium)
[ -x /usr/bin/chromedriver ] || missing+=(chromium-driver)
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
stamp=.venv/.rabbitros-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing the package into .venv" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[ros2,test,fast,bench]' 2> >(grep -v 'is ignored: it is neither' >&2)
  echo "$want" > "$stamp"
fi
