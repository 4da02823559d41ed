#!/usr/bin/env bash
# Set up a development/runtime environment in ./.venv (idempotent).
#   scripts/setup.sh           Python environment only
#   scripts/setup.sh --tools   also the system tools the tests use (mosquitto, mbpoll, socat, systemd,
#                              logrotate, openssl, prometheus, chromium)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

if [ "${1:-}" = "--tools" ]; then
  need=()
  command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || need+=(mosquitto)
  command -v mosquitto_sub >/dev/null 2>&1 || need+=(mosquitto-clients)
  command -v mbpoll >/dev/null 2>&1 || need+=(mbpoll)
  command -v socat >/dev/null 2>&1 || need+=(socat)
  command -v systemd-analyze >/dev/null 2>&1 || need+=(systemd)
  command -v logrotate >/dev/null 2>&1 || [ -x /usr/sbin/logrotate ] || need+=(logrotate)
  command -v openssl >/dev/null 2>&1 || need+=(openssl)
  command -v prometheus >/dev/null 2>&1 || need+=(prometheus)
  # the console's browser tests: Playwright (PyPI, test extras) drives Debian's chromium
  [ -x /usr/bin/chromium ] || need+=(chromium)
  if [ ${#need[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ]; then
      echo "setup: installing ${need[*]}" >&2
      apt-get update -qq
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
    elif command -v sudo >/dev/null 2>&1; then
      sudo apt-get update -qq
      sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
    else
      echo "setup: missing ${need[*]}; install them (Debian: apt-get install ${need[*]})" >&2
    fi
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.hookwatch-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null 2>&1 || true
  .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]' 2>&1 | grep -v '^WARNING: Location' >&2 || true
  .venv/bin/python -c 'import gateway, drivers, numpy, pymodbus, paho.mqtt, pyarrow.csv, isal.isal_zlib'
  touch "$stamp"
fi
