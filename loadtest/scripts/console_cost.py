# The line console's cost (issue 18), on a broker of its own on loopback:
#   1. page weight: every asset's bytes, raw (as served) and gzip -9;
#   2. time to first render of the devices view with 1,000 registered devices (declared
#      one by one over MQTT), in headless Chromium: navigation start to the first row
#      drawn (window.__fbbusFirstRows, performance.now()), median of 5 fresh loads;
#   3. the broker's CPU (utime+stime of /proc/<pid>/stat) and peak RSS during a bounded
#      `fbbus-loadtest pairs` run with no page open, then with 10 pages' live feeds open
#      (each: the device list loaded, then /api/v1/events read; half of them watching a
#      device as the device view does), and the ratio.
#
# Usage: python3 console_cost.py FBBUS_BINARY FBBUS_LOADTEST_BINARY
import gzip, json, os, socket, statistics, struct, subprocess, sys, tempfile, threading, time
import urllib.request

binary, loadtest = sys.argv[1], sys.argv[2]
d = tempfile.mkdtemp(prefix="console-cost-")
port = 21000 + os.getpid() % 1000
admin = f"127.0.0.1:{port + 1}"
open(f"{d}/fbbus.toml", "w").write(f"""[broker]
line = "m"
[fb]
max_devices_per_identity = 100000
[[listener]]
name = "main"
bind = "127.0.0.1:{port}"
[admin]
bind = "{admin}"
[persistence]
enabled = false
""")
log = open(f"{d}/broker.log", "w")
broker = subprocess.Popen([binary, "serve", "--config", f"{d}/fbbus.toml"], stdout=log, stderr=log)
TICK = os.sysconf("SC_CLK_TCK")


def get(path):
    with urllib.request.urlopen(f"http://{admin}{path}", timeout=10) as r:
        return r.read()


for _ in range(200):
    try:
        if get("/readyz").startswith(b"ready"):
            break
    except OSError:
        pass
    time.sleep(0.05)

# ------------------------------------------------------------ devices, declared over MQTT
CONV = json.dumps({"fbs": {"CONV": {"type": "CONVEYOR",
    "events_out": {"MOVED": {"with": ["POSITION", "SENSOR_IN"]}, "TICK": {"with": []}},
    "events_in": {"START": {"with": ["SPEED"]}},
    "data_out": {"POSITION": "INT", "SENSOR_IN": "BOOL", "ID": "STRING"},
    "data_in": {"SPEED": "REAL"}}}}).encode()


def mqtt_str(s):
    b = s.encode()
    return struct.pack(">H", len(b)) + b


def remaining(n):
    out = b""
    while True:
        byte = n % 128
        n //= 128
        out += bytes([byte | (0x80 if n else 0)])
        if not n:
            return out


def packet(kind, body):
    return bytes([kind]) + remaining(len(body)) + body


def read_packet(s):
    h = s.recv(1)
    mult, n = 1, 0
    while True:
        b = s.recv(1)[0]
        n += (b & 127) * mult
        mult *= 128
        if not b & 128:
            break
    data = b""
    while len(data) < n:
        data += s.recv(n - len(data))
    return h[0], data


def declare(i):
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(packet(0x10, mqtt_str("MQTT") + bytes([4, 2]) + struct.pack(">H", 60) + mqtt_str(f"dev-{i:04}")))
    read_packet(s)
    s.sendall(packet(0x32, mqtt_str(f"fbbus/declare/dev-{i:04}") + struct.pack(">H", 1) + CONV))
    while read_packet(s)[0] >> 4 != 4:
        pass
    s.sendall(bytes([0xE0, 0]))
    s.close()


t0 = time.time()
for i in range(1000):
    declare(i)
devices = json.loads(get("/api/v1/devices?limit=1"))
print(f"1,000 devices declared in {time.time() - t0:.1f} s")

# ------------------------------------------------------------ 1. page weight
raw = gz = 0
for name in ["/", "/console/console.js", "/console/console.css", "/console/icon.svg"]:
    body = get(name)
    raw += len(body)
    gz += len(gzip.compress(body, 9))
    print(f"  {name}: {len(body)} bytes, {len(gzip.compress(body, 9))} gzipped")
print(f"page weight: {raw} bytes raw (as served), {gz} bytes gzipped")

# ------------------------------------------------------------ 2. first render, 1,000 devices
os.environ.setdefault("SE_OFFLINE", "true")
try:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait
    times = []
    for _ in range(5):
        profile = tempfile.mkdtemp(prefix="console-cost-chromium-")
        o = webdriver.ChromeOptions()
        o.binary_location = "/usr/bin/chromium"
        for f in ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1280,1000", "--user-data-dir=" + profile]:
            o.add_argument(f)
        drv = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=o)
        drv.get(f"http://{admin}/#/devices")
        WebDriverWait(drv, 20, 0.05).until(lambda x: x.execute_script("return window.__fbbusFirstRows"))
        times.append(drv.execute_script("return window.__fbbusFirstRows"))
        shown = drv.execute_script("return document.getElementById('devices-shown').textContent")
        drv.quit()
    print(f"first render of the devices view, 1,000 devices: median {statistics.median(times):.0f} ms "
          f"(runs: {', '.join('%.0f' % t for t in times)} ms; '{shown}')")
except ImportError:
    print("first render: selenium missing, skipped")


# ------------------------------------------------------------ 3. CPU and memory of the feed
def cpu_s():
    f = open(f"/proc/{broker.pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / TICK


def rss_mib():
    for line in open(f"/proc/{broker.pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024


stop = threading.Event()
feed_bytes = [0]


def page(watch):
    # What one open page costs the broker: the list, then the feed, reconnected when it ends.
    while not stop.is_set():
        get("/api/v1/devices?limit=1000")
        if watch:
            get("/api/v1/devices/dev-0001/activity")
        s = socket.create_connection(("127.0.0.1", port + 1))
        path = "/api/v1/events" + ("?device=dev-0001" if watch else "")
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        s.settimeout(1)
        while not stop.is_set():
            try:
                chunk = s.recv(65536)
            except socket.timeout:
                continue
            if not chunk:
                break
            feed_bytes[0] += len(chunk)
        s.close()


def run(pages, seconds):
    global stop
    stop = threading.Event()
    threads = [threading.Thread(target=page, args=(i % 2 == 1,), daemon=True) for i in range(pages)]
    for t in threads:
        t.start()
    time.sleep(2)
    peak = [rss_mib()]
    done = threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], rss_mib())
            time.sleep(0.2)
    threading.Thread(target=sample, daemon=True).start()
    before, t0 = cpu_s(), time.time()
    out = subprocess.run([loadtest, "--broker", f"mqtt://127.0.0.1:{port}", "--time-limit-s", str(seconds),
                          "--ceiling", "0", "--out", f"{d}/lt-{pages}", "pairs", "--clients", "10",
                          "--messages", "2000", "--rate", "2000", "--repeats", "3"],
                         capture_output=True, text=True, timeout=seconds + 120)
    cpu, wall = cpu_s() - before, time.time() - t0
    done.set()
    stop.set()
    for t in threads:
        t.join(timeout=3)
    # The loadtest's summary: its header line and the line after it (the figures).
    lines = out.stdout.splitlines()
    at = next((i for i, l in enumerate(lines) if l.strip().startswith("summary")), None)
    delivered = [lines[at], lines[at + 2]] if at is not None and at + 2 < len(lines) else lines[-3:]
    return cpu, wall, peak[0], delivered


results = {}
for pages in [0, 10]:
    cpu, wall, peak, lines = run(pages, 40)
    results[pages] = (cpu, wall, peak)
    print(f"{pages:2} pages: broker CPU {cpu:.2f} s over {wall:.1f} s ({100 * cpu / wall:.1f} % of a core), "
          f"peak RSS {peak:.1f} MiB")
    for l in lines:
        print("    loadtest:", l.strip())
c0, w0, r0 = results[0]
c1, w1, r1 = results[10]
print(f"10 pages vs none: CPU {(c1 / w1) / (c0 / w0):.2f}x, peak RSS {r1 - r0:+.1f} MiB; "
      f"feeds read {feed_bytes[0] / 1024:.0f} KiB")
broker.terminate()
broker.wait(timeout=10)
