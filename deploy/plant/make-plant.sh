#!/usr/bin/env bash
# Writes the configuration of a plant of N lines on one bus into DIR: two zenoh routers
# linked to each other, every line's fbbus a zenoh client of both, mutual TLS throughout.
#
#   bash deploy/plant/make-plant.sh [N] [DIR] [path/to/fbbus]     # N = 8, DIR = ./plant
#
#   DIR/tls/          the plant's bus CA, a certificate per line (line-1 .. line-N) and
#                     per router (router-1, router-2), made with `fbbus bus-cert`
#   DIR/router-1.json5, DIR/router-2.json5
#                     the routers (`zenohd -c`), made with `fbbus zenohd-config`: each
#                     holds every line to its own keys; router-2 connects to router-1
#   DIR/line-K.toml   line K: MQTT on 127.0.0.1:(1882+K), admin on 127.0.0.1:(9882+K),
#                     its registry in DIR/line-K/
#
# Everything binds 127.0.0.1 so the plant runs on one host as it is (check.sh). On a real
# plant each line and each router has its host: issue each certificate for the names the
# others reach it by (`--host`), bind the LAN addresses, give every line a password file
# (deploy/fbbus.example.toml), and see README.md here for sizing routers and leases.
# The ports move with MQTT_BASE, ADMIN_BASE (line K: BASE + K), ROUTER_1_PORT and
# ROUTER_2_PORT. Existing certificates are kept; the configuration files are rewritten.
set -euo pipefail
N=${1:-8}
DIR=${2:-plant}
FBBUS=${3:-$(command -v fbbus || echo target/release/fbbus)}
MQTT_BASE=${MQTT_BASE:-1882}
ADMIN_BASE=${ADMIN_BASE:-9882}
ROUTER_1_PORT=${ROUTER_1_PORT:-7447}
ROUTER_2_PORT=${ROUTER_2_PORT:-7448}
LEASE_MS=${LEASE_MS:-3000}
case $N in '' | *[!0-9]*) echo "make-plant.sh: N must be a number of lines" >&2; exit 2 ;; esac
[ "$N" -ge 1 ] || { echo "make-plant.sh: a plant has at least one line" >&2; exit 2; }
mkdir -p "$DIR/tls"
DIR=$(cd "$DIR" && pwd)
TLS=$DIR/tls

[ -f "$TLS/bus-ca.crt" ] || "$FBBUS" bus-cert ca --out "$TLS" --name "plant bus CA" >/dev/null
names=()
for k in $(seq 1 "$N"); do names+=("line-$k"); done
for name in "${names[@]}" router-1 router-2; do
  [ -f "$TLS/$name.crt" ] ||
    "$FBBUS" bus-cert issue --ca "$TLS" --name "$name" --host localhost --host 127.0.0.1 \
      --out "$TLS" >/dev/null
done
lines=$(IFS=,; echo "${names[*]}")

router() { # router NAME PORT OTHER [CONNECT]
  local connect=()
  [ -z "${4:-}" ] || connect=(--connect "$4")
  "$FBBUS" zenohd-config --name "$1" --listen "tls/127.0.0.1:$2" "${connect[@]}" \
    --root-ca "$TLS/bus-ca.crt" --cert "$TLS/$1.crt" --key "$TLS/$1.key" \
    --lines "$lines" --routers "$3" --lease-ms "$LEASE_MS" >"$DIR/$1.json5"
}
router router-1 "$ROUTER_1_PORT" router-2
router router-2 "$ROUTER_2_PORT" router-1 "tls/127.0.0.1:$ROUTER_1_PORT"

for k in $(seq 1 "$N"); do
  mkdir -p "$DIR/line-$k"
  cat >"$DIR/line-$k.toml" <<TOML
# Line $k of a plant of $N lines (deploy/plant/make-plant.sh). Every option is documented
# in deploy/fbbus.example.toml; deploy/multi-line/line-a.toml comments the bus ones.
[broker]
line = "line-$k"

[[listener]]
name = "mqtt"
bind = "127.0.0.1:$((MQTT_BASE + k))"
allow_anonymous = true

[admin]
bind = "127.0.0.1:$((ADMIN_BASE + k))"

[fb]
registry_file = "$DIR/line-$k/registry.json"

[bridge]
# A zenoh client of both routers, with a session on each: it puts through router-1
# while it is there and through router-2 when it is not, and takes what comes through
# either (each message once: the copy is dropped by its stamp). A cut of the link
# between the routers, or either router dying, leaves it on the bus.
mode = "client"
session_per_router = true
connect = ["tls/127.0.0.1:$ROUTER_1_PORT", "tls/127.0.0.1:$ROUTER_2_PORT"]
lease_ms = $LEASE_MS

[bridge.tls]
root_ca = "$TLS/bus-ca.crt"
cert = "$TLS/line-$k.crt"
key = "$TLS/line-$k.key"

[bridge.peers]
routers = ["router-1", "router-2"]
TOML
done
echo "make-plant.sh: $N lines and two routers in $DIR"
