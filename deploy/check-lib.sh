# What deploy/multi-line/check.sh and deploy/plant/check.sh share; sourced, not run.
# Expects ROOT (the repository) and FBBUS (an fbbus binary, or empty); sets FBBUS, ZENOHD,
# WORK (a temporary directory removed at exit, with every process in PIDS killed) and
# defines fail, wait_for and ports_free.

if [ -z "$FBBUS" ]; then
  cargo build --release -p broker --bin fbbus >/dev/null
  FBBUS=$ROOT/target/release/fbbus
fi
ZENOHD=${ZENOHD:-$(command -v zenohd || true)}
if [ -z "$ZENOHD" ]; then
  ZENOHD=$ROOT/target/zenohd/bin/zenohd
  [ -x "$ZENOHD" ] || cargo install zenohd --version 1.10.2 --locked --root "$ROOT/target/zenohd"
fi

ports_free() { # ports_free PORT...: exits if one is in use
  for port in "$@"; do
    if (exec 3<>/dev/tcp/127.0.0.1/"$port") 2>/dev/null; then
      echo "check.sh: port $port is in use; the example's ports must be free" >&2
      exit 1
    fi
  done
}

WORK=$(mktemp -d)
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT
fail() {
  echo "FAIL: $*" >&2
  for f in "$WORK"/*.log; do echo "--- $f" >&2; tail -n 20 "$f" >&2; done
  exit 1
}
now() { date +%s.%N; }
wait_for() { # wait_for SECONDS DESCRIPTION COMMAND...: says how long it took
  local until=$((SECONDS + $1)) what=$2 from; from=$(now); shift 2
  until "$@" >/dev/null 2>&1; do
    [ $SECONDS -lt $until ] || fail "$what"
    sleep 0.1
  done
  printf 'ok: %s (%.2f s)\n' "$what" "$(awk -v a="$(now)" -v b="$from" 'BEGIN { print a - b }')"
}
