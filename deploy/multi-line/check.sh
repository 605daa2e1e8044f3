#!/usr/bin/env bash
# Runs deploy/multi-line without containers and checks it: the plant's zenoh router
# (`zenohd` 1.10.2, the same as the compose file's image) and the two lines from
# line-a.toml and line-b.toml, as they are, on this host's loopback (ports 1883, 1884,
# 9883, 9884 and 7447 must be free). Only the registry files and the bus certificates
# move into a temporary directory (the examples name the container's /var/lib/fbbus and
# /etc/zenoh/tls; make-certs.sh creates the certificates there).
#
#   bash deploy/multi-line/check.sh [path/to/fbbus]
#
# Needs mosquitto_pub/mosquitto_sub and curl; zenohd from PATH, else from $ZENOHD, else
# installed with `cargo install zenohd --version 1.10.2 --locked` into
# target/zenohd (about 10 minutes of compiling, once).
#
# What it checks, in order:
#   1. both lines start while zenohd is down and serve their own devices;
#   2. zenohd starts: the lines link through it; a device on line A declared and
#      publishing, a subscriber on line B gets its messages (JSON and fbdk), line B's
#      registry lists the device with line-a;
#   3. zenohd stops: line B marks the device unreachable within the 3 s lease;
#   4. zenohd starts again: the device is online on line B and messages flow again.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
FBBUS=${1:-}
# shellcheck source=deploy/check-lib.sh
source "$ROOT/deploy/check-lib.sh"
ports_free 1883 1884 9883 9884 7447
status_on_b() { "$FBBUS" devices --admin 127.0.0.1:9884 | awk -v d="$1" '$1 == d { print $2, $3 }'; }
is() { [ "$(status_on_b plc-1)" = "line-a $1" ]; }

bash deploy/multi-line/make-certs.sh "$WORK/tls" "$FBBUS" >/dev/null
sed "s#/etc/zenoh/tls/#$WORK/tls/#" deploy/multi-line/zenohd.json5 >"$WORK/zenohd.json5"
zenohd_up() {
  "$ZENOHD" -c "$WORK/zenohd.json5" >>"$WORK/zenohd.log" 2>&1 &
  ZPID=$!
  PIDS+=("$ZPID")
}

for l in a b; do
  sed "s#/var/lib/fbbus/#$WORK/#" "deploy/multi-line/line-$l.toml" >"$WORK/line-$l.toml"
  "$FBBUS" serve --config "$WORK/line-$l.toml" >"$WORK/line-$l.log" 2>&1 &
  PIDS+=($!)
done
wait_for 10 "line A serves MQTT while zenohd is down" mosquitto_pub -p 1883 -t fb/probe -m 1
wait_for 10 "line B serves MQTT while zenohd is down" mosquitto_pub -p 1884 -t fb/probe -m 1
wait_for 10 "line A says it is alone" grep -q "zenoh router not reachable" "$WORK/line-a.log"

zenohd_up
# plc-1 on line A declares one FB, then stays connected (online while connected) and
# publishes each line written to its FIFO.
mosquitto_pub -p 1883 -i plc-1 -t fbbus/declare/plc-1 -q 1 \
  -m '{"fbs":{"CONV":{"data_out":{"SPEED":"INT"}}}}'
mkfifo "$WORK/plc-1"
mosquitto_pub -p 1883 -i plc-1 -t fb/plc-1/CONV/SPEED -q 1 -l <"$WORK/plc-1" &
PIDS+=($!)
exec 4>"$WORK/plc-1"
wait_for 20 "line B lists plc-1 of line-a online" is online
mosquitto_sub -p 1884 -t 'fb/plc-1/#' -t 'fbdk/plc-1/#' -v >"$WORK/sub.out" 2>"$WORK/sub.log" &
PIDS+=($!)
exported() { curl -s 127.0.0.1:9883/metrics | grep -q '^fbbus_bridge_remote_subscriptions [1-9]'; }
wait_for 10 "line A exports what line B subscribed to" exported
sleep 0.5
echo 3 >&4
wait_for 5 "line B's subscriber gets plc-1's SPEED as JSON" grep -qx "fb/plc-1/CONV/SPEED 3" "$WORK/sub.out"
wait_for 5 "and as fbdk (INT 3: 43 00 03)" grep -qa "^fbdk/plc-1/CONV/SPEED C" "$WORK/sub.out"

kill "$ZPID"
wait_for 8 "zenohd stopped: line B marks plc-1 unreachable" is unreachable
zenohd_up
wait_for 20 "zenohd back: plc-1 online on line B" is online
wait_for 10 "line A exports again" exported
sleep 0.5
echo 4 >&4
wait_for 5 "line B's subscriber gets SPEED again" grep -qx "fb/plc-1/CONV/SPEED 4" "$WORK/sub.out"
exec 4>&-
echo "check.sh: the multi-line example works (zenohd $("$ZENOHD" --version 2>/dev/null | tail -n 1))"
