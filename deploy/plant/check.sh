#!/usr/bin/env bash
# Runs the plant of make-plant.sh natively on this host and checks it: N lines (default
# 8) as zenoh clients of two real `zenohd` 1.10.2 routers linked to each other, mutual
# TLS, on loopback (ports 1883.., 9883.., 7447 and 7448 must be free).
#
#   bash deploy/plant/check.sh [N] [DEVICES] [path/to/fbbus]      # N = 8, DEVICES = 50
#
# Needs mosquitto_pub/mosquitto_sub; zenohd from PATH, else from $ZENOHD, else installed
# with `cargo install zenohd --version 1.10.2 --locked` into target/zenohd (about 10
# minutes of compiling, once). What it checks, and how long each took:
#   1. every line lists all N x DEVICES devices online;
#   2. a device of line 1 publishes every 20 ms for 2 s to a subscriber on line N;
#   3. router-1 is killed: every line lists every device online again; 2 s more;
#   4. router-1 starts again; once every line has its session on it again
#      (fbbus_bridge_router_sessions_up), router-2 is killed: the same;
#   5. the subscriber got every message once, in order.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
N=${1:-8}
DEVICES=${2:-50}
FBBUS=${3:-}
# shellcheck source=deploy/check-lib.sh
source "$ROOT/deploy/check-lib.sh"
ports_free $(seq 1883 $((1882 + N))) $(seq 9883 $((9882 + N))) 7447 7448
online() { curl -s "127.0.0.1:$((9882 + $1))/metrics" | awk '$1 == "fbbus_registry_devices{status=\"online\"}" { print $2 }'; }
everyone_online() {
  for k in $(seq 1 "$N"); do [ "$(online "$k")" = "$((N * DEVICES))" ] || return 1; done
}

bash deploy/plant/make-plant.sh "$N" "$WORK/plant" "$FBBUS" >/dev/null
router_up() { # router_up NAME
  "$ZENOHD" -c "$WORK/plant/$1.json5" >>"$WORK/$1.log" 2>&1 &
  eval "PID_${1//-/_}=$!"
  PIDS+=($!)
}
router_up router-1
router_up router-2
for k in $(seq 1 "$N"); do
  # A line's devices all come from 127.0.0.1 here: its share per address must hold them.
  sed "s/^registry_file = .*/&\nmax_devices_per_identity = $((DEVICES + 10))/" \
    "$WORK/plant/line-$k.toml" >"$WORK/line-$k.toml"
  "$FBBUS" serve --config "$WORK/line-$k.toml" >"$WORK/line-$k.log" 2>&1 &
  PIDS+=($!)
done
for k in $(seq 1 "$N"); do
  wait_for 20 "line $k serves MQTT" mosquitto_pub -p $((1882 + k)) -t fb/probe -m 1
done

# DEVICES devices per line, each declared and then kept connected (a FIFO that never
# closes holds mosquitto_pub open).
decl='{"fbs":{"CONV":{"data_out":{"POSITION":"LINT"}}}}'
for k in $(seq 1 "$N"); do
  for d in $(seq 1 "$DEVICES"); do
    id="l$k-d$d"
    mkfifo "$WORK/$id"
    mosquitto_pub -p $((1882 + k)) -i "$id" -t "fbbus/declare/$id" -q 1 -m "$decl"
    mosquitto_pub -p $((1882 + k)) -i "$id" -t "fb/$id/CONV/POSITION" -q 1 -l <"$WORK/$id" &
    PIDS+=($!)
    eval "exec {fd}>\"$WORK/$id\""
    [ "$id" != l1-d1 ] || PUB_FD=$fd
  done
done
wait_for 60 "every line lists all $((N * DEVICES)) devices online" everyone_online
rss() { awk '$1 == "VmRSS:" { printf "%.1f MiB", $2 / 1024 }' "/proc/$1/status"; }
echo "   zenohd resident memory: router-1 $(rss "$PID_router_1"), router-2 $(rss "$PID_router_2")"

mosquitto_sub -p $((1882 + N)) -t fb/l1-d1/CONV/POSITION >"$WORK/sub.out" 2>"$WORK/sub.log" &
PIDS+=($!)
sleep 1
SENT=0
send() { # one message every 20 ms for 2 s
  for _ in $(seq 1 100); do
    SENT=$((SENT + 1))
    echo "$SENT" >&"$PUB_FD"
    sleep 0.02
  done
}
line_downs() { # how many times lines saw another line go, summed over the lines
  for k in $(seq 1 "$N"); do
    curl -s "127.0.0.1:$((9882 + k))/metrics" |
      awk '$1 == "fbbus_bridge_liveliness_changes_total{kind=\"line_down\"}" { print $2 }'
  done | awk '{ s += $1 } END { print s + 0 }'
}
failover() { # failover ROUTER: kill it, say how long until every line lists everyone again
  local before; before=$(line_downs)
  kill -9 "$(eval echo "\$PID_${1//-/_}")"
  wait_for 10 "$1 killed: every line lists every device online again" everyone_online
  sleep 0.5
  everyone_online || wait_for 10 "(a dip came late) every device online again" everyone_online
  echo "   lines saw another line go $(($(line_downs) - before)) times meanwhile"
}
send
failover router-1
send
router_up router-1
on_both_routers() { # every line's sessions are on their routers again
  for k in $(seq 1 "$N"); do
    curl -s "127.0.0.1:$((9882 + k))/metrics" | awk '$1 == "fbbus_bridge_router_sessions_up" { up = $2 }
      $1 == "fbbus_bridge_router_sessions" { all = $2 } END { exit !(all > 0 && up == all) }' || return 1
  done
}
wait_for 15 "router-1 back: every line has its session on it again" on_both_routers
sleep 1
failover router-2
send
sleep 1
got=$(wc -l <"$WORK/sub.out")
dups=$(sort -n "$WORK/sub.out" | uniq -d | wc -l)
ordered=$(sort -n -c "$WORK/sub.out" 2>/dev/null && echo yes || echo no)
echo "messages: line 1 -> line $N: sent $SENT, received $got, duplicated $dups, in order: $ordered"
[ "$dups" -eq 0 ] || fail "duplicates"
[ "$got" -eq "$SENT" ] || fail "lost $((SENT - got))"
[ "$ordered" = yes ] || fail "out of order"
echo "check.sh: the plant of $N lines and two zenohd routers works (zenohd $("$ZENOHD" --version 2>/dev/null | tail -n 1))"
