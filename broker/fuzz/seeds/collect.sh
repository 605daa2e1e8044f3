#!/usr/bin/env bash
# Copies the repository's own example files into the seed corpora of the fuzz targets
# that read them, so the seeds follow the examples. Run from anywhere; idempotent.
#   config_load:         deploy/*.toml, deploy/multi-line/*.toml, the embedded default
#   acl_parse:           deploy/acl.example
# The MQTT packet seeds come from capture.py; the other seeds are hand-written files in
# this directory (see docs/fuzzing.md).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
mkdir -p "$here/config_load" "$here/acl_parse"
cp "$root/deploy/fbbus.example.toml" "$here/config_load/fbbus.example.toml"
for f in "$root"/deploy/multi-line/*.toml; do
    cp "$f" "$here/config_load/multi-line-$(basename "$f")"
done
# broker/src/config.rs DEFAULT_CONFIG, between its r#" and "#.
sed -n '/^pub const DEFAULT_CONFIG/,/^"#;/p' "$root/broker/src/config.rs" \
    | sed '1d;$d' > "$here/config_load/embedded-default.toml"
cp "$root/deploy/acl.example" "$here/acl_parse/acl.example"
# The example ACL with queries after a NUL: devices, the monitor, the MES, crafted ids.
{
    cat "$root/deploy/acl.example"
    printf '\0'
    printf '%s\n' \
        'plc-1 plc-1 fb/plc-1/CONV/SPEED' \
        'plc-1 plc-1 fb/#' \
        'monitor monitor $SYS/#' \
        'mes mes line1/plc-1/cmd/start' \
        '- a/b fb/a/b/x' \
        'x+ x+ line1/x+/cmd/#' \
        '$evil $evil $share/g/fb/#' \
        'plc-1 plc-1 Förderband/é'
} > "$here/acl_parse/acl.example-queries"
echo "collected into $here"
