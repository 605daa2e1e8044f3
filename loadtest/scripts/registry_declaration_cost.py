# Cost of one declaration with 50,000 devices registered (issue 21): a registry pre-filled
# with 50,000 records, then N connect+declare+disconnect cycles by distinct devices (one
# journal line each). Usage: python3 registry_declaration_cost.py FBBUS_BINARY N [old]
# ("old": a binary without [fb] declarations_per_minute). Reports the broker's CPU and the
# bytes it wrote (/proc/<pid>/io wchar) over the run plus 6 s.
import json, os, socket, struct, subprocess, sys, tempfile, time

binary, n = sys.argv[1], int(sys.argv[2])
d = tempfile.mkdtemp(prefix="decl-measure-")
CONV = {"fbs": {"CONV": {"type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "events_in": {"START": {"with": ["SPEED"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING", "CONNECT": "BOOL"},
    "data_in": {"SPEED": "REAL"}}}}
recs = [{"id": f"dev-{i}", "line": "m", "status": "offline", "session": i + 1,
         "since": "2026-11-26T00:00:00.000Z", "last_will_reason": "clean disconnect",
         "interface": CONV} for i in range(50000)]
json.dump({"version": 1, "devices": recs}, open(f"{d}/registry.json", "w"), indent=2)
port = 18830 + os.getpid() % 1000
open(f"{d}/fbbus.toml", "w").write(f"""[broker]
line = "m"
[fb]
registry_file = "registry.json"
{"declarations_per_minute = 1000000" if len(sys.argv) < 4 else ""}
[[listener]]
name = "main"
bind = "127.0.0.1:{port}"
[admin]
bind = "127.0.0.1:{port + 1}"
[persistence]
enabled = false
""")
log = open(f"{d}/broker.log", "w")
p = subprocess.Popen([binary, "serve", "--config", f"{d}/fbbus.toml"], stdout=log, stderr=log)

def mqtt_str(s):
    b = s.encode(); return struct.pack(">H", len(b)) + b
def remaining(n):
    out = b""
    while True:
        byte = n % 128; n //= 128
        out += bytes([byte | (0x80 if n else 0)])
        if not n: return out
def connect(cid):
    body = mqtt_str("MQTT") + bytes([4, 2]) + struct.pack(">H", 60) + mqtt_str(cid)
    return bytes([0x10]) + remaining(len(body)) + body
def publish1(topic, payload, pkid):
    body = mqtt_str(topic) + struct.pack(">H", pkid) + payload
    return bytes([0x32]) + remaining(len(body)) + body
def read_packet(s):
    h = s.recv(1)
    if not h: raise EOFError
    mult, n = 1, 0
    while True:
        b = s.recv(1)[0]; n += (b & 127) * mult; mult *= 128
        if not b & 128: break
    data = b""
    while len(data) < n: data += s.recv(n - len(data))
    return h[0], data

deadline = time.time() + 300
while True:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close(); break
    except OSError:
        if time.time() > deadline or p.poll() is not None: sys.exit("broker did not start")
        time.sleep(0.2)
time.sleep(2)
def cpu():
    f = open(f"/proc/{p.pid}/stat").read().split(")")[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
def written():
    for l in open(f"/proc/{p.pid}/io"):
        if l.startswith("wchar"): return int(l.split()[1])
payload = json.dumps(CONV).encode()
c0, w0, t0 = cpu(), written(), time.time()
for i in range(n):
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(connect(f"dev-{i}"))
    assert read_packet(s)[0] == 0x20
    s.sendall(publish1(f"fbbus/declare/dev-{i}", payload, 1))
    while read_packet(s)[0] != 0x40: pass
    s.sendall(b"\xe0\x00"); s.close()
time.sleep(6.0)
c1, w1, t1 = cpu(), written(), time.time()
jl = os.path.getsize(f"{d}/registry.json.log") if os.path.exists(f"{d}/registry.json.log") else 0
print(f"{binary}: {n} declarations (connect+declare+disconnect, distinct devices) with 50,000 registered:"
      f" wall {t1 - t0:.2f} s, broker CPU {c1 - c0:.2f} s ({(c1 - c0) / n * 1000:.2f} ms per declaration),"
      f" bytes written (wchar) {(w1 - w0) / 1e6:.1f} MB ({(w1 - w0) / n / 1e3:.1f} KB per declaration), journal {jl} bytes,"
      f" snapshot {os.path.getsize(f'{d}/registry.json')} bytes")
p.terminate(); p.wait()
import shutil
shutil.rmtree(d, ignore_errors=True)
