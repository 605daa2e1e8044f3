#!/usr/bin/env bash
# CPU time per 100,000 messages of two fbbus lines linked by the zenoh bridge, for one or
# more fbbus binaries, alternating (RESULTS.md, "Where the CPU goes"). For each binary and
# round: start line A and line B on free loopback ports, send 5 bursts of 20,000 messages
# from A to a subscriber on B, then the same within A, and print the utime + stime each
# line's process spent (from /proc/<pid>/stat, in seconds).
#
#   bash loadtest/bridge-cpu.sh target/release/fbbus [other/fbbus ...]
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 FBBUS_BINARY [FBBUS_BINARY ...]" >&2; exit 2; }
cargo build --release -p fbbus-loadtest >/dev/null
LT=$PWD/target/release/fbbus-loadtest
ROUNDS=${ROUNDS:-3}
WORK=$(mktemp -d)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$WORK"; }
trap cleanup EXIT

. "$PWD/loadtest/bridge-lines.sh"
cpu_s() { awk '{printf "%.2f", ($14+$15)/100}' "/proc/$1/stat"; }
sub() { awk -v a="$1" -v b="$2" 'BEGIN{printf "%.2f", b-a}'; }

burst() { "$LT" --ceiling 0 --broker "mqtt://127.0.0.1:$1" --out "$WORK/out" bridge \
            --subscribe-at "mqtt://127.0.0.1:$2" --messages "${3:-20000}" --repeats "${4:-5}" >/dev/null; }

for round in $(seq "$ROUNDS"); do
  for bin in "$@"; do
    pa=$(free_port); pb=$(free_port); za=$(free_port); zb=$(free_port)
    line line-a "$pa" "$za" "$zb" "$bin"; A=${PIDS[-1]}
    line line-b "$pb" "$zb" "$za" "$bin"; B=${PIDS[-1]}
    wait_port "$pa"; wait_port "$pb"
    burst "$pa" "$pb" 1000 1            # warm-up: the bridge's routes exist
    a0=$(cpu_s "$A"); b0=$(cpu_s "$B")
    burst "$pa" "$pb"
    a1=$(cpu_s "$A"); b1=$(cpu_s "$B")
    burst "$pa" "$pa"
    a2=$(cpu_s "$A")
    echo "round $round $bin: across the bridge line A $(sub "$a0" "$a1") s, line B $(sub "$b0" "$b1") s; within line A $(sub "$a1" "$a2") s (per 100,000 messages)"
    kill "$A" "$B"; wait "$A" "$B" 2>/dev/null || true
    PIDS=()
  done
done
