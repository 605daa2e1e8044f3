#!/usr/bin/env bash
# Issue 5's two figures, alternating so machine noise hits both sides alike: two fbbus
# lines linked by the zenoh bridge on loopback; each round runs the same traffic from a
# publisher on line A to a subscriber on line A (within one broker) and to a subscriber
# on line B (across the hop), as bursts (throughput) and at open-loop rates (latency).
# Prints every round, then the medians: throughput across / within and the p50 the hop
# adds at each rate.
#
#   bash loadtest/bridge-hop.sh [FBBUS_BINARY] [ROUNDS]     # default: release build, 6
#
# Bursts: 5 x 20,000 messages (median msg/s of the 5); rates: 3 x 5,000 messages at
# 1,000 and 10,000 msg/s (p50 over the 15,000). Every run is bounded by the harness's
# own limits (--batch-limit-s, --time-limit-s defaults).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -p broker -p fbbus-loadtest >/dev/null
BIN=${1:-$PWD/target/release/fbbus}
ROUNDS=${2:-6}
LT=$PWD/target/release/fbbus-loadtest
WORK=$(mktemp -d)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; rm -rf "$WORK"; }
trap cleanup EXIT
. "$PWD/loadtest/bridge-lines.sh"
pa=$(free_port); pb=$(free_port); za=$(free_port); zb=$(free_port)
line line-a "$pa" "$za" "$zb" "$BIN"
line line-b "$pb" "$zb" "$za" "$BIN"
wait_port "$pa"; wait_port "$pb"

run() { "$LT" --ceiling 0 --broker "mqtt://127.0.0.1:$pa" --out "$WORK/out" bridge --subscribe-at "mqtt://127.0.0.1:$1" "${@:2}"; }
# Summary row "A fbbus ...": field 9 is the median msg/s. Rate rows: field 11 is p50 ms.
burst() { run "$1" --messages 20000 --repeats 5 | awk '/^A fbbus/ { v = $9; sub(/k$/, "", v); if ($9 ~ /k$/) v *= 1000; print v }'; }
rates() { run "$1" --messages 5000 --rate 1000,10000 --repeats 3 | awk '/^rate/ { printf "%s ", $11 } END { print "" }'; }
median() { sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

burst "$pb" >/dev/null # warm-up: the bridge's routes exist
: >"$WORK/rounds"
for r in $(seq "$ROUNDS"); do
  lb=$(burst "$pa"); hb=$(burst "$pb")
  read -r l1 l10 < <(rates "$pa"); read -r h1 h10 < <(rates "$pb")
  echo "$lb $hb $l1 $h1 $l10 $h10" >>"$WORK/rounds"
  printf 'round %d: bursts within %.0f msg/s, across %.0f msg/s (%.2f x); p50 at 1,000 msg/s %s -> %s ms, at 10,000 msg/s %s -> %s ms\n' \
    "$r" "$lb" "$hb" "$(awk -v a="$hb" -v b="$lb" 'BEGIN { print a / b }')" "$l1" "$h1" "$l10" "$h10"
done
col() { awk -v c="$1" '{ print $c }' "$WORK/rounds" | median; }
ratio=$(awk '{ print $2 / $1 }' "$WORK/rounds" | median)
add1=$(awk '{ print $4 - $3 }' "$WORK/rounds" | median)
add10=$(awk '{ print $6 - $5 }' "$WORK/rounds" | median)
printf 'medians of %d rounds: bursts within %.0f msg/s, across %.0f msg/s, ratio %.2f x (median of the rounds'"'"' ratios)\n' \
  "$ROUNDS" "$(col 1)" "$(col 2)" "$ratio"
printf '                  hop adds at p50: %.3f ms at 1,000 msg/s, %.3f ms at 10,000 msg/s\n' "$add1" "$add10"
