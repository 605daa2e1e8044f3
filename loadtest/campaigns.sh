#!/usr/bin/env bash
# The two network campaigns of issue 14 against a freshly started release fbbus: `mutate`
# (random-mutation campaign, 20,000 connections) and `churn` (100,000 short-lived
# connections), each on a fresh broker running the embedded default configuration with
# its two ports (MQTT 1883, admin 9883) moved to free loopback ports. With
# --compare-mosquitto, Debian's Mosquitto runs beside it on another port and gets the same
# campaign, rounds interleaved (fbbus A, Mosquitto B).
#
# Prints per campaign and broker: packets, connections, crashes (the process still alive,
# the broker still routing), resident memory before / after / after a 15 s idle settle.
# Outputs go to $OUT/<campaign>/ (report.json, batches.csv, charts, and the harness's
# table as summary.txt; the broker's log as fbbus.log); OUT defaults to target/loadtest,
# outside the source tree, and OUT=loadtest/results replaces the committed figures.
#
#   bash loadtest/campaigns.sh                      # both campaigns against fbbus
#   bash loadtest/campaigns.sh --compare-mosquitto  # and Mosquitto side by side
#   bash loadtest/campaigns.sh --no-build mutate    # only mutate, binaries already built
#   MUTATE_ARGS="--connections 2000" CHURN_ARGS="--connections 10000" bash loadtest/campaigns.sh
#
# Exit status: 0 when fbbus passed every campaign run (routing probes, alive, resident
# memory after the settle within --max-rss-ratio 2 of before), 1 otherwise. Mosquitto's
# verdict is printed, not counted.
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${OUT:-target/loadtest}
COMPARE=0
BUILD=1
SELECTED=()
for arg in "$@"; do
  case $arg in
    --compare-mosquitto) COMPARE=1 ;;
    --no-build) BUILD=0 ;;
    mutate|churn) SELECTED+=("$arg") ;;
    -h|--help) sed -n '2,22p' "$0"; exit 0 ;;
    *) echo "campaigns: unknown argument $arg (try --help)" >&2; exit 2 ;;
  esac
done
[ ${#SELECTED[@]} -eq 0 ] && SELECTED=(mutate churn)

if [ "$BUILD" = 1 ]; then
  nice -n 10 cargo build --release -p broker -p fbbus-loadtest
fi
FBBUS=$PWD/target/release/fbbus
LT=$PWD/target/release/fbbus-loadtest
for bin in "$FBBUS" "$LT"; do
  [ -x "$bin" ] || { echo "campaigns: $bin is missing (cargo build --release -p broker -p fbbus-loadtest)" >&2; exit 1; }
done
MOSQUITTO=
if [ "$COMPARE" = 1 ]; then
  MOSQUITTO=$(command -v mosquitto || { [ -x /usr/sbin/mosquitto ] && echo /usr/sbin/mosquitto; } || true)
  [ -n "$MOSQUITTO" ] || { echo "campaigns: --compare-mosquitto needs Debian's mosquitto (apt-get install mosquitto)" >&2; exit 1; }
fi

WORK=$(mktemp -d)
PIDS=()
cleanup() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$WORK"; }
trap cleanup EXIT

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
wait_port() { for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/"$1") 2>/dev/null && return 0; sleep 0.1; done; echo "campaigns: nothing listens on $1" >&2; tail -n 5 "$WORK"/*/*.log >&2; exit 1; }

# start_fbbus NAME: the embedded default configuration (broker/src/config.rs,
# DEFAULT_CONFIG) with the two ports moved; sets FB_PORT, FB_ADMIN, FB_PID.
start_fbbus() {
  local dir=$WORK/$1; mkdir -p "$dir"; FB_PORT=$(free_port); FB_ADMIN=$(free_port)
  cat > "$dir/fbbus.toml" <<TOML
[broker]
line = "line-1"

[[listener]]
name = "mqtt-loopback"
bind = "127.0.0.1:$FB_PORT"
allow_anonymous = true

[admin]
bind = "127.0.0.1:$FB_ADMIN"
TOML
  (cd "$dir" && exec "$FBBUS" serve --config fbbus.toml > fbbus.log 2>&1) &
  FB_PID=$!; PIDS+=("$FB_PID"); wait_port "$FB_PORT"
  for _ in $(seq 100); do
    curl -sf "http://127.0.0.1:$FB_ADMIN/readyz" >/dev/null 2>&1 && break; sleep 0.1
  done
}

# start_mosquitto NAME: Debian's Mosquitto, anonymous, TCP_NODELAY; sets MQ_PORT, MQ_PID.
start_mosquitto() {
  local dir=$WORK/$1; mkdir -p "$dir"; MQ_PORT=$(free_port)
  printf 'listener %s 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n' "$MQ_PORT" > "$dir/mosquitto.conf"
  "$MOSQUITTO" -c "$dir/mosquitto.conf" > "$dir/mosquitto.log" 2>&1 &
  MQ_PID=$!; PIDS+=("$MQ_PID"); wait_port "$MQ_PORT"
}

stop_all() { for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; PIDS=(); }

# The figures of one report.json, one line per broker; exit status 1 when A (fbbus) failed.
summarize() {
  python3 - "$1" "$2" <<'PY'
import json, sys
path, name = sys.argv[1], sys.argv[2]
r = json.load(open(path))
def fig(s, n):
    for f in s["figures"]:
        if f["name"] == n:
            return f["value"]
    return None
def kib(v):
    return "-" if v is None else f"{v/1024:.1f} MiB"
failed_a = False
for t in r["targets"]:
    s = next(x for x in r["summaries"] if x["target"] == t["label"])
    fails = [f for f in r.get("failures", []) if f.startswith(t["label"] + ":")]
    if t["label"] == "A" and fails:
        failed_a = True
    crashed = fig(s, "crashes")
    b, a, z = fig(s, "rss_before_kib"), fig(s, "rss_after_kib"), fig(s, "rss_settled_kib")
    ratio = fig(s, "rss_settled_ratio")
    print(f"{name} {t['label']} {t['name']}: connections {int(fig(s, 'connections') or 0):,}, "
          f"packets {int(fig(s, 'packets_sent') or 0):,} ({int(fig(s, 'packets_mutated') or 0):,} mutated), "
          f"accepted {int(fig(s, 'result_connack_accepted') or 0):,}, refused {int(fig(s, 'result_connack_refused') or 0):,}, "
          f"closed by the broker {int(fig(s, 'closed_by_broker') or 0):,}; "
          f"crashes {'?' if crashed is None else int(crashed)}, probes {int(fig(s, 'probes_ok') or 0)} ok / {int(fig(s, 'probes_failed') or 0)} failed; "
          f"RSS before {kib(b)}, after {kib(a)}, settled {kib(z)}"
          + ("" if ratio is None else f" ({ratio:.2f}x)")
          + f", peak (VmHWM) {kib(fig(s, 'rss_hwm_kib'))}")
    for f in fails:
        print(f"  FAILED: {f}")
sys.exit(1 if failed_a else 0)
PY
}

STATUS=0
for campaign in "${SELECTED[@]}"; do
  start_fbbus "$campaign"
  args=(--broker "mqtt://127.0.0.1:$FB_PORT" --out "$OUT/$campaign")
  extra=(--pid "$FB_PID" --metrics "http://127.0.0.1:$FB_ADMIN/metrics")
  if [ "$COMPARE" = 1 ]; then
    start_mosquitto "$campaign"
    args+=(--compare "mqtt://127.0.0.1:$MQ_PORT")
    extra+=(--compare-pid "$MQ_PID")
  fi
  case $campaign in
    mutate) read -r -a more <<< "${MUTATE_ARGS:-}" ;;
    churn) read -r -a more <<< "${CHURN_ARGS:-}" ;;
  esac
  mkdir -p "$OUT/$campaign"
  echo "== $campaign: fbbus-loadtest ${args[*]} $campaign ${extra[*]} ${more[*]:-}"
  set +e
  "$LT" "${args[@]}" "$campaign" "${extra[@]}" ${more[@]+"${more[@]}"} | tee "$OUT/$campaign/summary.txt"
  set -e
  alive=yes; kill -0 "$FB_PID" 2>/dev/null || alive=no
  cp "$WORK/$campaign/fbbus.log" "$OUT/$campaign/fbbus.log"
  panics=$(grep -ac 'panicked' "$OUT/$campaign/fbbus.log" || true)
  stop_all
  echo
  summarize "$OUT/$campaign/report.json" "$campaign" || STATUS=1
  echo "$campaign: fbbus process alive at the end: $alive; panics in its log: $panics"
  if [ "$alive" != yes ] || [ "$panics" != 0 ]; then STATUS=1; fi
  echo
done
exit $STATUS
