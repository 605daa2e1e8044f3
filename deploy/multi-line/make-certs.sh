#!/usr/bin/env bash
# Creates the bus certificates of the two-line example in deploy/multi-line/tls/ (or the
# directory given): the plant's bus CA, one certificate per line (common name = the
# line's name, `[broker] line`) and one for the zenoh router (`zenohd`), all for
# localhost/127.0.0.1 as the example runs on one host. Existing files are kept.
#
#   bash deploy/multi-line/make-certs.sh [DIR] [path/to/fbbus]
#
# On a real plant, create the CA once on an offline machine and issue each line's
# certificate for the names and addresses the others reach it by (docs/bus-security.md).
set -euo pipefail
DIR=${1:-$(dirname "$0")/tls}
FBBUS=${2:-$(command -v fbbus || echo target/release/fbbus)}
mkdir -p "$DIR"
[ -f "$DIR/bus-ca.crt" ] || "$FBBUS" bus-cert ca --out "$DIR" --name "example plant bus CA"
for name in line-a line-b zenohd; do
  [ -f "$DIR/$name.crt" ] ||
    "$FBBUS" bus-cert issue --ca "$DIR" --name "$name" --host localhost --host 127.0.0.1 --out "$DIR"
done
