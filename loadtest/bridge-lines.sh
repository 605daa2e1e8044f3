# Sourced by bridge-cpu.sh and bridge-hop.sh: two fbbus lines linked by the zenoh bridge
# on loopback. The sourcing script sets WORK (a temporary directory) and PIDS (an array);
# it kills the PIDS and removes WORK on exit.

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
wait_port() { for _ in $(seq 100); do (exec 3<>/dev/tcp/127.0.0.1/"$1") 2>/dev/null && return 0; sleep 0.1; done; echo "nothing listens on $1" >&2; exit 1; }

# line NAME MQTT_PORT ZENOH_LISTEN ZENOH_CONNECT BINARY: starts one line in the background
# (its PID appended to PIDS), anonymous MQTT on 127.0.0.1:MQTT_PORT, a fresh registry.
line() {
  cat >"$WORK/$1.toml" <<TOML
[broker]
line = "$1"
[bridge]
listen = ["tcp/127.0.0.1:$3"]
connect = ["tcp/127.0.0.1:$4"]
[[listener]]
name = "line"
bind = "127.0.0.1:$2"
allow_anonymous = true
[admin]
bind = "127.0.0.1:$(free_port)"
[fb]
registry_file = "$WORK/$1-registry.json"
TOML
  rm -f "$WORK/$1-registry.json"
  "$5" serve --config "$WORK/$1.toml" >"$WORK/$1.log" 2>&1 &
  PIDS+=($!)
}
