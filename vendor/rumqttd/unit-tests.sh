#!/usr/bin/env bash
# Runs the vendored rumqttd's own unit tests (upstream's and fbbus's: commit log, holds,
# freer, links) as FBBUS-CHANGES.md describes. The crate is not a workspace member, and its
# dev-dependencies (pretty_assertions, and config / pretty_env_logger for the examples) are
# not fbbus's, so the tests run on a copy without them, with the library only
# (`--lib --no-default-features`, the features fbbus builds it with).
#
#   bash vendor/rumqttd/unit-tests.sh            # from the repository root
#
# The copy builds into target/vendor-rumqttd-tests, so a second run is incremental.
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
copy="$(mktemp -d)"
trap 'rm -rf "$copy"' EXIT

cp -r "$root/vendor/rumqttd/." "$copy/"
# The workspace's lock file pins the versions fbbus builds the crate with.
cp "$root/Cargo.lock" "$copy/"
python3 - "$copy" <<'EOF'
import pathlib, re, sys
copy = pathlib.Path(sys.argv[1])
manifest = copy / "Cargo.toml"
text = manifest.read_text()
# Every [dev-dependencies.*] table, up to the next table or the end.
text = re.sub(r"(?m)^\[dev-dependencies\.[^\]]+\][^\[]*", "", text)
manifest.write_text(text)
mod = copy / "src/segments/mod.rs"
mod.write_text(mod.read_text().replace("use pretty_assertions::assert_eq;", ""))
EOF
if grep -q 'dev-dependencies' "$copy/Cargo.toml"; then
  echo "unit-tests.sh: could not strip the dev-dependencies of $copy/Cargo.toml" >&2
  exit 1
fi
cd "$copy"
CARGO_TARGET_DIR="$root/target/vendor-rumqttd-tests" cargo test --lib --no-default-features
