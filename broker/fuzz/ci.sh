#!/usr/bin/env bash
# CI for fbbus's fuzz targets (docs/fuzzing.md): builds every target once, replays every
# crash ever found (broker/fuzz/regressions/<target>/*), then fuzzes each target briefly
# from its seeds (broker/fuzz/seeds/<target>/, copied into a fresh corpus). Fails on any
# crash. Idempotent: installs cargo-fuzz only when it is missing; without the nightly
# toolchain it says so and exits 0.
#
#   bash broker/fuzz/ci.sh                  # 20 s per target, 2 at a time
#   FUZZ_SECONDS=60 FUZZ_JOBS=1 bash broker/fuzz/ci.sh
#
# Builds with overflow checks and debug assertions (`-a`), without a sanitizer (`-s none`):
# the code under test is safe Rust, so what is looked for is panics, and ASan slows every
# execution. On 2 cores: 4.4 min from an empty target directory (3 min of it the
# build), 1.5 min once built.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"

seconds=${FUZZ_SECONDS:-20}
jobs=${FUZZ_JOBS:-2}
targets=(mqtt_decode topic_match typed_codec declaration acl_parse password_file_parse config_load profile_parse fboot_import store_replay sparkplug_metric bus_stamp)

if ! cargo +nightly --version >/dev/null 2>&1; then
  echo "fuzz ci: SKIPPED: the nightly toolchain is not installed (cargo-fuzz needs it:" \
       "rustup toolchain install nightly)"
  exit 0
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
  echo "fuzz ci: installing cargo-fuzz"
  cargo install cargo-fuzz --locked
fi
echo "fuzz ci: $(cargo +nightly --version); $(cargo fuzz --version)"

start=$(date +%s)
nice -n 10 cargo +nightly fuzz build -s none -a
triple=$(rustc +nightly -vV | sed -n 's/^host: //p')
bin="${CARGO_TARGET_DIR:-$here/target}/$triple/release"
echo "fuzz ci: built in $(( $(date +%s) - start )) s"

failed=()

# Every crash input ever found, through its target.
for t in "${targets[@]}"; do
  files=("$here/regressions/$t"/*)
  [ -e "${files[0]}" ] || continue
  if ! "$bin/$t" -runs=0 "${files[@]}" >"$here/regressions-$t.log" 2>&1; then
    echo "fuzz ci: FAILED: a regression input of $t crashes again; see regressions-$t.log"
    grep -m1 -A3 panicked "$here/regressions-$t.log" || true
    failed+=("$t regressions")
  else
    echo "fuzz ci: $t: ${#files[@]} regression inputs pass"
    rm -f "$here/regressions-$t.log"
  fi
done

scratch=$(mktemp -d "${TMPDIR:-/tmp}/fbbus-fuzz-ci.XXXXXX")
trap 'rm -rf "$scratch"' EXIT

run() {
  local t=$1 corpus="$scratch/corpus-$t" dict=()
  mkdir -p "$corpus" "$here/artifacts/$t"
  cp "$here/seeds/$t"/* "$corpus"/ 2>/dev/null || true
  [ -f "$here/dicts/$t.dict" ] && dict=("-dict=$here/dicts/$t.dict")
  nice -n 10 "$bin/$t" "${dict[@]}" -max_total_time="$seconds" -print_final_stats=1 \
    -artifact_prefix="$here/artifacts/$t/" "$corpus" >"$scratch/$t.log" 2>&1
}

declare -A pids=()
for t in "${targets[@]}"; do
  while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do wait -n || true; done
  run "$t" &
  pids[$t]=$!
done
for t in "${targets[@]}"; do
  if wait "${pids[$t]}"; then
    execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$scratch/$t.log")
    rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$scratch/$t.log")
    echo "fuzz ci: $t: ${seconds} s, ${execs:-?} executions (${rate:-?}/s), no crash"
  else
    echo "fuzz ci: FAILED: $t crashed; input in broker/fuzz/artifacts/$t/:"
    grep -E -m1 -A6 'panicked|ERROR: libFuzzer' "$scratch/$t.log" || tail -20 "$scratch/$t.log"
    cp "$scratch/$t.log" "$here/artifacts/$t/ci.log"
    failed+=("$t")
  fi
done

echo "fuzz ci: total $(( $(date +%s) - start )) s"
if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzz ci: FAILED: ${failed[*]} (reproduce: cargo +nightly fuzz run -s none -a <target> <input>;" \
       "keep the input in broker/fuzz/regressions/<target>/ once fixed)"
  exit 1
fi
echo "fuzz ci: ok"
