#!/bin/sh
# Lab container entry point: with no arguments, start the virtual station (`hookwatch sim`) and
# run the gateway's station against its pseudo-terminals until the test has ended; with
# arguments, run them instead (e.g. `hookwatch check --skip-local config`).
# SIGTERM/SIGINT (docker stop, Ctrl-C) stop the gateway cleanly (the test is closed as aborted).
set -u
if [ "$#" -gt 0 ]; then
    exec "$@"
fi
: "${SCENARIO:=config/scenarios/demo.yaml}" "${STATION:=config/demo/station.yaml}" "${SEED:=1}"
: "${LINK_DIR:=/tmp/hookwatch-sim}" "${RECORDS:=/var/lib/hookwatch/records}"
mkdir -p "$LINK_DIR" "$RECORDS"

hookwatch sim "$SCENARIO" --link-dir "$LINK_DIR" --seed "$SEED" --truth "$RECORDS/truth.json" &
sim=$!
i=0
while [ ! -e "$LINK_DIR/meter" ] || [ ! -e "$LINK_DIR/stm32" ]; do
    i=$((i + 1))
    if [ "$i" -gt 300 ] || ! kill -0 "$sim" 2>/dev/null; then
        echo "hookwatch-lab: the virtual station did not start" >&2
        kill "$sim" 2>/dev/null
        exit 1
    fi
    sleep 0.1
done

# the station file's ports are the links (config/demo/station.yaml: /tmp/hookwatch-sim/…)
hookwatch run "$STATION" --start --exit-when-done --no-northbound --records-dir "$RECORDS" &
gw=$!
trap 'kill -TERM "$gw" 2>/dev/null' INT TERM
wait "$gw"
rc=$?
if kill -0 "$gw" 2>/dev/null; then      # interrupted by a signal: let the gateway finish
    wait "$gw"
    rc=$?
fi
kill -TERM "$sim" 2>/dev/null
wait "$sim" 2>/dev/null
exit "$rc"
