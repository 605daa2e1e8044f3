#!/usr/bin/env bash
# Reproduces loadtest/RESULTS.md on this machine: the JMeter study's three tests and the
# scenarios beyond it, fbbus against Mosquitto (Debian package, set_tcp_nodelay true) in
# compare mode, each scenario interleaved A B A B. Both brokers run here on free loopback
# ports; fresh brokers are started where memory is measured. Outputs go to
# $OUT/<scenario>/ (report.json, batches.csv, batches.jtl, SVG charts, and the terminal
# table as summary.txt); OUT defaults to target/loadtest, outside the source tree, and
# OUT=loadtest/results replaces the committed figures RESULTS.md quotes.
#
#   bash loadtest/study.sh            # everything (~30 min on a 2-core machine)
#   bash loadtest/study.sh stress perf   # only these
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${OUT:-target/loadtest}
cargo build --release -p broker -p fbbus-loadtest
FBBUS=$PWD/target/release/fbbus
LT=$PWD/target/release/fbbus-loadtest
if ! command -v mosquitto >/dev/null && [ ! -x /usr/sbin/mosquitto ]; then
  echo "study: installing mosquitto"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends mosquitto mosquitto-clients >/dev/null
  (systemctl stop mosquitto || pkill -x mosquitto) >/dev/null 2>&1 || true
fi
MOSQUITTO=$(command -v mosquitto || echo /usr/sbin/mosquitto)

WORK=$(mktemp -d)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$WORK"; }
trap cleanup EXIT

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
wait_port() { for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/"$1") 2>/dev/null && return 0; sleep 0.1; done; echo "study: nothing listens on $1" >&2; tail -n 5 "$WORK"/*/*.log >&2; exit 1; }

# start_fbbus NAME [extra TOML]: fbbus on a fresh registry; sets FB_PORT.
start_fbbus() {
  local dir=$WORK/$1; mkdir -p "$dir"; FB_PORT=$(free_port)
  cat > "$dir/fbbus.toml" <<TOML
${2:-}
[[listener]]
name = "line"
bind = "127.0.0.1:$FB_PORT"
allow_anonymous = ${3:-true}

[admin]
bind = "127.0.0.1:$(free_port)"

[fb]
registry_file = "$dir/registry.json"
TOML
  "$FBBUS" serve --config "$dir/fbbus.toml" > "$dir/fbbus.log" 2>&1 &
  PIDS+=($!); wait_port "$FB_PORT"
}

# start_mosquitto NAME [extra conf]: sets MQ_PORT.
start_mosquitto() {
  local dir=$WORK/$1; mkdir -p "$dir"; MQ_PORT=$(free_port)
  printf 'listener %s 127.0.0.1\nset_tcp_nodelay true\n%s\n' "$MQ_PORT" "${2:-allow_anonymous true}" > "$dir/mosquitto.conf"
  "$MOSQUITTO" -c "$dir/mosquitto.conf" > "$dir/mosquitto.log" 2>&1 &
  PIDS+=($!); wait_port "$MQ_PORT"
}

stop_all() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; PIDS=(); }

# run NAME ARGS...: fbbus (A) against Mosquitto (B).
run() {
  local name=$1; shift
  mkdir -p "$OUT/$name"
  echo "== $name: fbbus-loadtest $*"
  "$LT" --broker "mqtt://127.0.0.1:$FB_PORT" --compare "mqtt://127.0.0.1:$MQ_PORT" \
    --out "$OUT/$name" "$@" | tee "$OUT/$name/summary.txt"
}

want() { [ ${#SELECTED[@]} -eq 0 ] || [[ " ${SELECTED[*]} " == *" $1 "* ]]; }
SELECTED=("$@")

start_fbbus main; start_mosquitto main
want stress && run stress stress
want stress-81920 && run stress-81920 stress --max 81920
want loss-search && run loss-search loss-search
want loss-search-raw && run loss-search-raw --no-fb loss-search
want perf && run perf perf
want qos1 && run stress-qos1 --qos 1 stress --max 81920 --repeats 3
want fan-in && run fan-in fan-in --clients 10 --messages 10000
want steady && run steady fan-in --clients 10 --messages 5000 --rate 10000
want fan-out && run fan-out fan-out --clients 10 --messages 10000
want pairs && run pairs pairs --clients 10 --messages 10000
want conveyor && run conveyor conveyor --devices 2,5,10,20 --parts 200
stop_all

if want idle; then
  start_fbbus idle; start_mosquitto idle
  run idle idle --connections 1000 --hold-s 5
  stop_all
fi

if want storm; then
  # 1,045 devices with argon2id (fbbus) and PBKDF2-SHA512 (Mosquitto) passwords.
  pw=storm-$(date +%s)
  mkdir -p "$WORK/storm"
  : > "$WORK/storm/mosquitto.passwd"
  for i in $(seq 0 1044); do
    echo "$pw" | "$FBBUS" passwd "$WORK/storm/fbbus.passwd" add "dev-$i" --stdin >/dev/null
    mosquitto_passwd -b "$WORK/storm/mosquitto.passwd" "dev-$i" "$pw"
  done
  chmod 600 "$WORK/storm/fbbus.passwd"
  # Mosquitto started as root reads its password file as the user `mosquitto`.
  chmod 755 "$WORK" "$WORK/storm"
  chown mosquitto: "$WORK/storm/mosquitto.passwd" 2>/dev/null || chmod 644 "$WORK/storm/mosquitto.passwd"
  start_fbbus storm "[auth]
password_file = \"$WORK/storm/fbbus.passwd\"" false
  start_mosquitto storm "allow_anonymous false
password_file $WORK/storm/mosquitto.passwd"
  MQTT_PASSWORD=$pw run storm --username 'dev-{i}' storm --devices 1045 --repeats 3
  stop_all
fi

if want bridge; then
  # Line A -> zenoh -> line B, next to the same traffic within line A.
  za=$(free_port); zb=$(free_port)
  start_fbbus line-a "[broker]
line = \"line-a\"
[bridge]
listen = [\"tcp/127.0.0.1:$za\"]
connect = [\"tcp/127.0.0.1:$zb\"]"
  A=$FB_PORT
  start_fbbus line-b "[broker]
line = \"line-b\"
[bridge]
listen = [\"tcp/127.0.0.1:$zb\"]
connect = [\"tcp/127.0.0.1:$za\"]"
  B=$FB_PORT
  # First the traffic within line A alone (nobody on line B subscribes yet, so line A
  # exports nothing), then the same from line A to line B. Bursts for throughput,
  # open-loop rates for the hop's latency.
  for kind in local hop; do
    sub=$B; [ $kind = local ] && sub=$A
    for pace in burst rate; do
      args=(--messages 20000 --repeats 5); [ $pace = rate ] && args=(--messages 5000 --rate 1000,10000 --repeats 3)
      mkdir -p "$OUT/bridge-$kind-$pace"
      echo "== bridge ($kind, $pace)"
      "$LT" --broker "mqtt://127.0.0.1:$A" --out "$OUT/bridge-$kind-$pace" bridge \
        --subscribe-at "mqtt://127.0.0.1:$sub" "${args[@]}" | tee "$OUT/bridge-$kind-$pace/summary.txt"
    done
  done
  stop_all
fi
echo "study: results in $OUT"
