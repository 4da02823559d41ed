#!/usr/bin/env bash
# Set up a runtime or development environment in ./.venv (idempotent), on a stock Debian 12
# (Python 3.11.2 and newer; other Debian-like systems with Python >= 3.11 likewise).
#   scripts/setup.sh           the product alone (runtime dependencies, no test tools)
#   scripts/setup.sh --demo    the product and what the demo's output promises: mosquitto (the
#                              demo's own broker), mosquitto_sub (the MES line), mbpoll (the PLC lines)
#   scripts/setup.sh --tools   the product, the test tools (pyproject extras `test`: pytest, mypy,
#                              ruff, Playwright, …) and the system tools and libraries the tests use
#                              (the demo's, socat, systemd, logrotate, openssl, prometheus, chromium,
#                              libatomic1 for Playwright's node)
# As root it installs the Debian packages it needs (apt-get), also what Debian splits off Python
# (python3-venv: venv's pip); as another user it says in one sentence what root must install.
# A .venv that is half-made (no pip), made by another interpreter, or broken is removed and made
# anew, and setup says so.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
mode=${1:-}
case "$mode" in
  ""|--demo|--tools) ;;
  *) echo "usage: scripts/setup.sh [--demo|--tools]" >&2; exit 2 ;;
esac

command -v "$PY" >/dev/null 2>&1 || {
  echo "setup: $PY not found: hookwatch needs Python >= 3.11 (Debian 12: apt-get install python3 python3-venv)" >&2
  exit 1
}
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || {
  echo "setup: $("$PY" -V 2>&1) is too old: hookwatch needs Python >= 3.11 (Debian 12 or newer)" >&2
  exit 1
}

need=()
want() {  # want COMMAND PACKAGE [ALTERNATIVE PATH]
  command -v "$1" >/dev/null 2>&1 || { [ -n "${3:-}" ] && [ -x "$3" ]; } || need+=("$2")
}
want_lib() {  # want_lib SONAME PACKAGE: a shared library a tool loads (ldconfig's cache)
  { /sbin/ldconfig -p 2>/dev/null || ldconfig -p 2>/dev/null || true; } | grep -q "^[[:space:]]*$1 " || need+=("$2")
}
# Debian splits venv's pip (ensurepip) off into python3-venv: without it `python3 -m venv` fails
"$PY" -c 'import ensurepip, venv' >/dev/null 2>&1 || need+=(python3-venv)
case "$mode" in
  --demo|--tools)
    want mosquitto mosquitto /usr/sbin/mosquitto
    want mosquitto_sub mosquitto-clients
    want mbpoll mbpoll ;;
esac
if [ "$mode" = "--tools" ]; then
  want socat socat
  # the site rollout tests (tests/deploy/test_ansible_site.py) sign the site repository's commits
  want ssh-keygen openssh-client
  want git git
  want systemd-analyze systemd
  want logrotate logrotate /usr/sbin/logrotate
  want openssl openssl
  # the offline-release test cuts the network with unshare -n and brings its loopback up with ip
  want ip iproute2 /usr/sbin/ip
  want unshare util-linux
  want setpriv util-linux
  want ps procps
  want prometheus prometheus
  want rabbitmq-server rabbitmq-server /usr/lib/rabbitmq/bin/rabbitmq-server
  # the console's browser tests: Playwright (PyPI, test extras) drives Debian's chromium; its
  # bundled node needs libatomic1 (without it Playwright only says "Connection closed while
  # reading from the driver")
  [ -x /usr/bin/chromium ] || need+=(chromium)
  want_lib libatomic.so.1 libatomic1
fi
if [ ${#need[@]} -gt 0 ]; then
  mapfile -t need < <(printf '%s\n' "${need[@]}" | awk '!seen[$0]++')
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing ${need[*]} (Debian packages)" >&2
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    echo "setup: installing ${need[*]} (Debian packages, sudo)" >&2
    sudo apt-get update -qq
    sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "setup: this needs Debian packages that are missing and this user cannot install; as root run: apt-get install ${need[*]}" >&2
    if [[ " ${need[*]} " == *" python3-venv "* ]]; then exit 1; fi
    echo "setup: going on without them (what needs them says so)" >&2
  fi
fi

# Is .venv usable? It must run, be made by this interpreter ($PY, same version), and have pip.
why=""
if [ -e .venv ] || [ -L .venv ]; then
  if [ ! -x .venv/bin/python ]; then
    why="it has no working bin/python"
  elif ! have=$(.venv/bin/python -c 'import sys; print(sys.base_prefix, *sys.version_info[:3])' 2>/dev/null); then
    why="its python does not run"
  elif [ "$have" != "$("$PY" -c 'import sys; print(sys.base_prefix, *sys.version_info[:3])')" ]; then
    why="it was made by another interpreter ($have, not $PY)"
  elif ! .venv/bin/python -m pip --version >/dev/null 2>&1; then
    why="it has no pip (half-made, e.g. by python3 -m venv without python3-venv)"
  fi
fi
if [ -n "$why" ]; then
  echo "setup: .venv is not usable, $why: removing it and making it anew" >&2
  rm -rf .venv
fi
if [ ! -e .venv ]; then
  # a venv that fails half-way is removed, not left for the next run to stumble on
  if ! "$PY" -m venv .venv; then
    rm -rf .venv
    echo "setup: $PY -m venv failed (Debian: apt-get install python3-venv)" >&2
    exit 1
  fi
fi

# the stamp says which set is installed: the product alone (runtime) or with the test tools (test)
extras=runtime spec=.
if [ "$mode" = "--tools" ]; then extras=test spec='.[test]'; fi
stamp=.venv/.hookwatch-installed
have=$(cat "$stamp" 2>/dev/null || true)
if [ -z "$have" ] || [ pyproject.toml -nt "$stamp" ] || { [ "$extras" = test ] && [ "$have" != test ]; }; then
  [ "$have" = test ] && extras=test spec='.[test]'     # never drop test tools already installed
  echo "setup: installing hookwatch ($extras dependencies) into .venv" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null 2>&1 || true
  # pip's and setuptools' chatter (an editable build's warning block) goes to a log, shown on failure
  if ! .venv/bin/python -m pip install -q --disable-pip-version-check -e "$spec" >.venv/pip-install.log 2>&1; then
    cat .venv/pip-install.log >&2
    echo "setup: pip install failed (log: .venv/pip-install.log)" >&2
    exit 1
  fi
  .venv/bin/python -c 'import gateway, drivers, numpy, pymodbus, paho.mqtt, pyarrow.csv, isal.isal_zlib'
  echo "$extras" >"$stamp"
fi
