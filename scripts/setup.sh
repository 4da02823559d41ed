#!/usr/bin/env bash
# Set up a development/runtime environment in ./.venv (idempotent).
#   scripts/setup.sh           Python environment only
#   scripts/setup.sh --demo    also what the demo's output promises: mosquitto (the demo's own
#                              broker), mosquitto_sub (the MES line), mbpoll (the PLC lines)
#   scripts/setup.sh --tools   also the system tools the tests use (the demo's, socat, systemd,
#                              logrotate, openssl, prometheus, chromium)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

need=()
want() {  # want COMMAND PACKAGE [ALTERNATIVE PATH]
  command -v "$1" >/dev/null 2>&1 || { [ -n "${3:-}" ] && [ -x "$3" ]; } || need+=("$2")
}
case "${1:-}" in
  --demo|--tools)
    want mosquitto mosquitto /usr/sbin/mosquitto
    want mosquitto_sub mosquitto-clients
    want mbpoll mbpoll ;;
esac
if [ "${1:-}" = "--tools" ]; then
  want socat socat
  want systemd-analyze systemd
  want logrotate logrotate /usr/sbin/logrotate
  want openssl openssl
  want prometheus prometheus
  # the console's browser tests: Playwright (PyPI, test extras) drives Debian's chromium
  [ -x /usr/bin/chromium ] || need+=(chromium)
fi
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    echo "setup: installing ${need[*]} (Debian packages)" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo apt-get update -qq
    sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "setup: ${need[*]} missing and this user cannot install them; as root: apt-get install ${need[*]}" >&2
    echo "setup: going on without them (what needs them says so)" >&2
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.hookwatch-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null 2>&1 || true
  # pip's and setuptools' chatter (an editable build's warning block) goes to a log, shown on failure
  if ! .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]' >.venv/pip-install.log 2>&1; then
    cat .venv/pip-install.log >&2
    echo "setup: pip install failed (log: .venv/pip-install.log)" >&2
    exit 1
  fi
  .venv/bin/python -c 'import gateway, drivers, numpy, pymodbus, paho.mqtt' 
  touch "$stamp"
fi
