# The line console's cost (issue 18), on a broker of its own on loopback:
#   1. page weight: every asset's bytes, raw (as served) and gzip -9;
#   2. time to first render of the devices view with 1,000 registered devices (declared
#      one by one over MQTT), in headless Chromium: navigation start to the first row
#      drawn (window.__fbbusFirstRows, performance.now()), median of 5 fresh loads;
#   3. the broker's CPU (utime+stime of /proc/<pid>/stat) and peak RSS during a bounded
#      `fbbus-loadtest pairs` run with no page open, then with 10 pages' live feeds open
#      (each: the device list loaded, then /api/v1/events read; half of them watching a
#      device as the device view does, with the history of its plotted ports), and the
#      ratio;
#   4. (issue 37) the trends' memory: 1,000 devices x 10 INT outputs, each port one value
#      a second for HISTORY_SECONDS (default 240: past the 200 s that fill each port's
#      share of the default history_max_points), on a broker with the default history
#      and on one without (history_max_points = 0): resident memory and CPU, and the
#      history's own gauges.
#
# Usage: python3 console_cost.py FBBUS_BINARY FBBUS_LOADTEST_BINARY [HISTORY_SECONDS]
import gzip, json, os, socket, statistics, struct, subprocess, sys, tempfile, threading, time
import urllib.request

binary, loadtest = sys.argv[1], sys.argv[2]
HISTORY_SECONDS = int(sys.argv[3]) if len(sys.argv) > 3 else 240
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
            # The device view's plots: each plottable output's history, once.
            for name in ["CONV.MOVED", "CONV.POSITION", "CONV.SENSOR_IN"]:
                get(f"/api/v1/devices/dev-0001/ports/{name}/history")
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


# ------------------------------------------------------------ 4. the trends' memory
TEN = json.dumps({"fbs": {"F": {"type": "T", "data_out": {f"P{p}": "INT" for p in range(10)}}}}).encode()


def history_run(max_points, seconds):
    """1,000 devices x 10 ports at one value a second on a fresh broker keeping at most
    max_points: (RSS MiB before the values, RSS MiB at the end, CPU s, history gauges)."""
    global broker, port, admin
    port += 10
    admin = f"127.0.0.1:{port + 1}"
    conf = f"{d}/history-{max_points}.toml"
    open(conf, "w").write(f"""[broker]
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
[console]
history_max_points = {max_points}
""")
    broker = subprocess.Popen([binary, "serve", "--config", conf], stdout=log, stderr=log)
    for _ in range(200):
        try:
            if get("/readyz").startswith(b"ready"):
                break
        except OSError:
            pass
        time.sleep(0.05)
    socks = []
    for i in range(1000):
        s = socket.create_connection(("127.0.0.1", port))
        s.sendall(packet(0x10, mqtt_str("MQTT") + bytes([4, 2]) + struct.pack(">H", 0) + mqtt_str(f"ten-{i:04}")))
        read_packet(s)
        s.sendall(packet(0x32, mqtt_str(f"fbbus/declare/ten-{i:04}") + struct.pack(">H", 1) + TEN))
        while read_packet(s)[0] >> 4 != 4:
            pass
        socks.append(s)
    time.sleep(2)
    before = rss_mib()
    cpu0 = cpu_s()
    start = time.time()
    for tick in range(seconds):
        for i, s in enumerate(socks):
            s.sendall(b"".join(packet(0x30, mqtt_str(f"fb/ten-{i:04}/F/P{p}") + str(tick % 1000).encode())
                               for p in range(10)))
        time.sleep(max(0.0, start + tick + 1 - time.time()))
    time.sleep(2)
    after, cpu = rss_mib(), cpu_s() - cpu0
    metrics = get("/metrics").decode()
    gauges = {}
    for line in metrics.splitlines():
        for name in ['fbbus_console_entries{what="history_points"}', 'fbbus_console_entries{what="history_series"}',
                     "fbbus_console_history_bytes", "fbbus_typed_messages_accepted_total"]:
            if line.startswith(name + " "):
                gauges[name] = float(line.split()[-1])
    for s in socks:
        s.close()
    broker.terminate()
    broker.wait(timeout=10)
    return before, after, cpu, gauges


if HISTORY_SECONDS > 0:
    figures = {}
    for max_points in [2_000_000, 0]:
        before, after, cpu, gauges = history_run(max_points, HISTORY_SECONDS)
        figures[max_points] = (before, after, cpu)
        print(f"history_max_points = {max_points}: 1,000 devices x 10 ports at 1 value/s for {HISTORY_SECONDS} s: "
              f"RSS {before:.1f} -> {after:.1f} MiB, broker CPU {cpu:.1f} s; {gauges}")
    (b1, a1, c1), (b0, a0, c0) = figures[2_000_000], figures[0]
    print(f"the history's cost: RSS {(a1 - b1) - (a0 - b0):+.1f} MiB, CPU {c1 / c0:.2f}x "
          f"({c1:.1f} s against {c0:.1f} s)")
