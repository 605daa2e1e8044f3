"""What a person sees in the line console, checked in headless Chromium over WebDriver.

Run by broker/tests/console.rs:  console_browser.py <admin URL> [<screenshot dir>]

The Rust test owns the broker, the devices and the second line; this script drives the
browser and tells the test when to act, one line on stdout each, and waits for its answer
on stdin:

    ready-for-kill   -> the test kills press-2 without DISCONNECT, answers "killed"
    ready-for-stop   -> the test stops line-b, answers "stopped"
    done

A failed check prints "FAIL <what>" and exits non-zero. Every wait is bounded.
"""

import os
import re
import sys
import tempfile
import shutil

os.environ.setdefault("SE_OFFLINE", "true")  # never ask the internet for a driver

from selenium import webdriver  # noqa: E402
from selenium.common.exceptions import (  # noqa: E402
    NoSuchElementException, StaleElementReferenceException, TimeoutException, WebDriverException)
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait, Select  # noqa: E402

URL = sys.argv[1].rstrip("/")
SHOTS = sys.argv[2] if len(sys.argv) > 2 else ""
WAIT = 20

FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-dev-shm-usage", "--window-size=1280,1000",
]


def say(line):
    print(line, flush=True)


profile = tempfile.mkdtemp(prefix="fbbus-console-chromium-")
options = webdriver.ChromeOptions()
options.binary_location = "/usr/bin/chromium"
for flag in FLAGS + ["--user-data-dir=" + profile]:
    options.add_argument(flag)
driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
driver.set_page_load_timeout(WAIT)
driver.set_script_timeout(WAIT)


def finish(code):
    try:
        driver.quit()
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    sys.exit(code)


def fail(what):
    try:
        body = driver.find_element(By.TAG_NAME, "main").text[:1500]
    except WebDriverException:
        body = "?"
    say("FAIL " + what + " | page: " + body.replace("\n", " / "))
    finish(1)


def wait_for(what, check, timeout=WAIT):
    try:
        # The page redraws what changed: an element found a moment ago may be gone.
        return WebDriverWait(driver, timeout, poll_frequency=0.1, ignored_exceptions=(
            NoSuchElementException, StaleElementReferenceException)).until(lambda d: check())
    except TimeoutException:
        fail(what + " (waited %d s)" % timeout)


def act(what, do):
    """Does `do` (find an element and use it), again if the page redrew the element in
    between (a live page replaces rows and boxes as changes arrive)."""
    return wait_for(what, lambda: do() or True)


def text(css):
    try:
        return " ".join(e.text for e in driver.find_elements(By.CSS_SELECTOR, css))
    except WebDriverException:
        return ""


def row(device):
    return text('#devices-rows tr[data-id="%s"]' % device)


def answer(want):
    line = sys.stdin.readline().strip()
    if line != want:
        fail("expected %r from the test, got %r" % (want, line))


def shot(name, width=1280):
    if not SHOTS:
        return
    os.makedirs(SHOTS, exist_ok=True)
    # The whole page, not the window: the viewport made as tall as the content.
    height = driver.execute_script("return document.documentElement.scrollHeight")
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
        "width": width, "height": max(600, min(int(height), 3000)),
        "deviceScaleFactor": 1, "mobile": False})
    try:
        driver.save_screenshot(os.path.join(SHOTS, name))
    finally:
        driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def go(hash_):
    driver.execute_script("location.hash = arguments[0]", hash_)


def points(css):
    """How many points the polyline `css` draws (0 if there is none)."""
    return driver.execute_script(
        "const p = document.querySelector(arguments[0]);"
        "return p ? p.getAttribute('points').split(' ').filter(Boolean).length : 0", css)


def fits_the_width(what):
    """The page does not scroll sideways (a tablet on the line)."""
    wait_for(what + " without a horizontal scroll at 400 px", lambda: driver.execute_script(
        "const d = document.documentElement; return d.scrollWidth <= d.clientWidth"))


try:
    # Devices view: every device of the bus, local and remote, with its status.
    driver.get(URL + "/#/devices")
    for device in ["press-1", "press-2", "bad-1"]:
        wait_for(device + " online in the devices view",
                 lambda: "online" in row(device) and "line-a" in row(device))
    wait_for("remote-1 of line-b online", lambda: "online" in row("remote-1") and "line-b" in row("remote-1"))
    wait_for("the FBs column", lambda: "CONV (CONVEYOR)" in row("press-1"))
    # Loaded once: a reload would lose this.
    driver.execute_script("window.__sameLoad = 'yes'")

    # Keyboard: the first Tab reaches the skip link, whose focus is visible.
    act("Tab", lambda: driver.find_element(By.TAG_NAME, "body").send_keys(Keys.TAB))
    wait_for("the skip link takes the first Tab",
             lambda: driver.execute_script("return document.activeElement.id") == "skip")

    # press-2's device view: the will its connection holds.
    go("#/device/press-2")
    wait_for("press-2's will on its connection",
             lambda: "plant/press-2/will" in text("#device-will") and "gone" in text("#device-will"))
    act("the Devices tab", lambda: driver.find_element(By.ID, "nav-devices").click())
    wait_for("the devices list again", lambda: row("press-1"))

    say("ready-for-kill")
    answer("killed")
    wait_for("press-2 offline with its reason, live",
             lambda: "offline" in row("press-2") and "connection lost" in row("press-2"))
    if driver.execute_script("return window.__sameLoad") != "yes":
        fail("the page reloaded")

    # Filter by status, search, sort.
    act("the status filter", lambda: Select(driver.find_element(By.ID, "filter-status")).select_by_value("offline"))
    wait_for("the offline filter", lambda: row("press-2") and not row("press-1"))
    act("the status filter", lambda: Select(driver.find_element(By.ID, "filter-status")).select_by_value(""))
    act("the search", lambda: driver.find_element(By.ID, "search").send_keys("remote"))
    wait_for("the search", lambda: row("remote-1") and not row("press-1"))
    act("clearing the search", lambda: driver.find_element(By.ID, "search").clear())
    act("clearing the search", lambda: driver.find_element(By.ID, "search").send_keys(Keys.BACKSPACE))
    wait_for("the search cleared", lambda: row("press-1"))
    # Search by port name (issue 37): only the oven has T_ZONE1.
    act("the search", lambda: driver.find_element(By.ID, "search").send_keys("T_ZONE1"))
    wait_for("the search by port, saying which", lambda: "port OVEN.T_ZONE1" in row("oven-1")
             and not row("press-1") and not row("remote-1"))
    shot("search-port.png")
    act("clearing the search", lambda: driver.find_element(By.ID, "search").clear())
    act("clearing the search", lambda: driver.find_element(By.ID, "search").send_keys(Keys.BACKSPACE))
    wait_for("the search cleared", lambda: row("press-1"))
    act("the id column's sort button", lambda: driver.find_element(By.CSS_SELECTOR, 'th[data-key="id"] button').click())
    wait_for("sorted by id, descending", lambda: driver.find_element(
        By.CSS_SELECTOR, "#devices-rows tr").get_attribute("data-id") == "remote-1")
    act("the id column's sort button", lambda: driver.find_element(By.CSS_SELECTOR, 'th[data-key="id"] button').click())

    # The refused device: its refusal with the reason.
    act("the link to bad-1", lambda: driver.find_element(By.LINK_TEXT, "bad-1").click())
    wait_for("bad-1's refusal with its reason",
             lambda: "payload_format_invalid" in text("#refusals")
             and "fb/bad-1/CONV/POSITION" in text("#refusals"))

    # The publishing device: its FB box, ports, WITH associations and last values.
    go("#/device/press-1")
    wait_for("the CONV FB box", lambda: driver.find_elements(By.CSS_SELECTOR, 'figure[data-fb="CONV"] svg'))
    box = 'figure[data-fb="CONV"] svg '
    ports = ["START", "MOVED", "TICK", "SPEED", "POSITION", "SENSOR_IN", "ID"]
    wait_for("every port drawn in the FB box", lambda: all(
        p in driver.execute_script(
            "return Array.from(document.querySelectorAll(arguments[0])).map(t => t.textContent)",
            box + "text.port") for p in ports))
    wait_for("the WITH associations drawn (START WITH SPEED, MOVED WITH POSITION, SENSOR_IN)",
             lambda: len(driver.find_elements(By.CSS_SELECTOR, box + "line.with")) >= 2)

    def position():
        value = text('#ports-rows tr[data-port="CONV.POSITION"] td.value')
        return value if value.isdigit() else None

    first = wait_for("CONV.POSITION's last value", position)
    wait_for("CONV.POSITION's value changing live", lambda: position() not in (None, first))
    wait_for("CONV.MOVED's last event", lambda: "SENSOR_IN" in text('#ports-rows tr[data-port="CONV.MOVED"] td.value'))
    wait_for("the value drawn beside the FB box", lambda: driver.find_elements(By.CSS_SELECTOR, box + "text.pvalue"))
    shot("device.png")

    # Trends (issue 37): CONV.POSITION's sparkline in the FB box grows as values arrive.
    spark = box + 'polyline.spark[data-port="CONV.POSITION"]'
    first = wait_for("CONV.POSITION's sparkline", lambda: points(spark) or None)
    wait_for("the sparkline growing", lambda: points(spark) > first)
    # An event's WITH data: SENSOR_IN only ever arrives inside MOVED.
    wait_for("CONV.SENSOR_IN's value from MOVED's WITH data",
             lambda: text('#ports-rows tr[data-port="CONV.SENSOR_IN"] td.value') == "true")
    wait_for("CONV.SENSOR_IN's sparkline", lambda: points(box + 'polyline.spark[data-port="CONV.SENSOR_IN"]'))
    # An event's time as local date and time, its raw value on hover.
    moved = '#ports-rows tr[data-port="CONV.MOVED"] td.value'
    wait_for("MOVED's occurrence in words", lambda: re.match(r"^#\d+ at .*: POSITION \d+, SENSOR_IN true$", text(moved)))
    raw = driver.find_element(By.CSS_SELECTOR, moved).get_attribute("title")
    if '"ts":' not in raw or '"seq":' not in raw:
        fail("MOVED's raw value on hover: %r" % raw)
    # The occurrence's seq and ts (µs, the device's own) shown in this browser's local
    # date and time.
    def moved_in_local_time():
        cell = driver.find_element(By.CSS_SELECTOR, moved)
        raw = cell.get_attribute("title")
        seq, ts = re.search(r'"seq":\s*(\d+)', raw), re.search(r'"ts":\s*(\d+)', raw)
        if not seq or not ts:
            return False
        local = driver.execute_script(
            "const d = new Date(arguments[0] / 1000); return d.toLocaleDateString() + ' ' + d.toLocaleTimeString()",
            int(ts.group(1)))
        return cell.text.startswith("#%s at %s: " % (seq.group(1), local))
    wait_for("MOVED's seq and ts in local date and time", moved_in_local_time)
    # Two ports on one chart, growing live.
    for port in ["CONV.POSITION", "CONV.SENSOR_IN"]:
        act("plot " + port, lambda port=port: driver.find_element(
            By.CSS_SELECTOR, 'input.plot[data-port="%s"]' % port).click())
    line = '#trend-chart polyline[data-port="CONV.POSITION"]'
    first = wait_for("CONV.POSITION on the chart", lambda: points(line) or None)
    wait_for("the chart growing", lambda: points(line) > first)
    wait_for("both ports in the legend with their types", lambda: "CONV.POSITION (INT)" in text("#trend-chart .legend")
             and "CONV.SENSOR_IN (BOOL)" in text("#trend-chart .legend"))
    wait_for("local times on the time axis", lambda: len(driver.find_elements(By.CSS_SELECTOR, "#trend-chart text.time-tick")) >= 3)
    # A click on a sparkline in the FB box puts its port on the chart (an event: its
    # occurrences' numbers); Enter on it, focused, takes it off.
    hit = box + 'g.spark-hit[data-plot="CONV.MOVED"]'
    act("a click on CONV.MOVED's sparkline", lambda: driver.find_element(By.CSS_SELECTOR, hit).click())
    wait_for("CONV.MOVED on the chart from its sparkline",
             lambda: points('#trend-chart polyline[data-port="CONV.MOVED"]') >= 2
             and "CONV.MOVED (event" in text("#trend-chart .legend")
             and driver.find_element(By.CSS_SELECTOR, hit).get_attribute("aria-pressed") == "true"
             and driver.find_element(By.CSS_SELECTOR, 'input.plot[data-port="CONV.MOVED"]').is_selected())
    act("Enter on CONV.MOVED's sparkline", lambda: driver.find_element(By.CSS_SELECTOR, hit).send_keys(Keys.ENTER))
    wait_for("CONV.MOVED off the chart", lambda: "CONV.MOVED" not in text("#trend-chart .legend")
             and driver.find_element(By.CSS_SELECTOR, hit).get_attribute("aria-pressed") == "false")
    act("a click on CONV.MOVED's sparkline", lambda: driver.find_element(By.CSS_SELECTOR, hit).click())
    wait_for("CONV.MOVED on the chart again", lambda: "CONV.MOVED (event" in text("#trend-chart .legend"))
    # A port's history as CSV, from its link: a file named after the device and port,
    # every value kept (press-1 publishes CONV.POSITION 5 times a second, on its own topic
    # and as MOVED's WITH data: one series either way), in time order.
    href = driver.find_element(By.CSS_SELECTOR, 'a.csv[data-port="CONV.POSITION"]').get_attribute("href")
    got = {}

    def csv_export():
        csv, disposition = driver.execute_async_script(
            "fetch(arguments[0]).then(r => r.text().then(t => [t, r.headers.get('content-disposition')]))"
            ".then(arguments[1], e => arguments[1](['error ' + e, '']))", href)
        got.update(csv=csv, disposition=disposition)
        rows = csv.splitlines()
        times = [r.split(",")[0] for r in rows[1:]]
        return (rows[0] == "time,CONV.POSITION" and len(rows) > 10 and times == sorted(times)
                and all(re.match(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z,\d+$", r) for r in rows[1:]))
    try:
        WebDriverWait(driver, 10, poll_frequency=0.5).until(lambda d: csv_export())
    except TimeoutException:
        fail("the CSV export (header, then more than 10 rows of time,value in time order): %r" % got.get("csv", "")[:400])
    if 'filename="press-1_CONV.POSITION.csv"' not in (got.get("disposition") or ""):
        fail("the CSV export's file name: %r" % got.get("disposition"))
    if SHOTS:
        # A chart worth looking at: 20 s of values.
        wait_for("20 s of CONV.POSITION on the chart", lambda: points(line) >= 100, timeout=45)
    shot("trends.png")

    # The tablet on the line: 400 px wide, no sideways scroll of the page.
    driver.set_window_size(400, 1000)
    fits_the_width("the device view")
    # Drawn for that width, not shrunk: the FB box's port names and the chart's ticks
    # stay readable.
    wait_for("readable port names and chart ticks at 400 px", lambda: driver.execute_script(
        "const h = (css) => Math.min(...Array.from(document.querySelectorAll(css)).map(e => e.getBoundingClientRect().height));"
        "return h('figure[data-fb=\"CONV\"] text.port') >= 10 && h('#trend-chart text.tick') >= 10"))
    shot("device-400px.png", width=400)
    go("#/devices")
    wait_for("the devices list at 400 px", lambda: row("press-1"))
    fits_the_width("the devices view")
    go("#/")
    wait_for("the line view at 400 px", lambda: text("#count-online") not in ("", "0"))
    fits_the_width("the line view")
    go("#/retained")
    wait_for("the retained view at 400 px", lambda: text("#retained-shown"))
    fits_the_width("the retained view")

    # Connected clients, with a known client id; retained topics under a filter.
    go("#/clients")
    wait_for("press-1 among the connected clients",
             lambda: "MQTT 3.1.1" in text('#clients-rows tr[data-client="press-1"]'))
    fits_the_width("the clients view")
    driver.set_window_size(1280, 1000)
    wait_for("the clients' columns", lambda: "127.0.0.1:" in text('#clients-rows tr[data-client="press-1"]'))
    shot("clients.png")
    go("#/retained")
    act("the retained filter", lambda: driver.find_element(By.ID, "retained-filter").clear())
    act("the retained filter", lambda: driver.find_element(By.ID, "retained-filter").send_keys("plant/+/shift" + Keys.ENTER))
    wait_for("the retained shift topic with its size",
             lambda: "plant/line-a/shift" in text("#retained-rows") and "19" in text('#retained-rows tr[data-topic="plant/line-a/shift"]'))
    shot("retained.png")

    # The killed device: its offline time and reason.
    go("#/device/press-2")
    wait_for("press-2's offline time with its reason", lambda: "connection lost" in text("#offline-times"))

    # Line view: counts, charts, the bridge's other line.
    act("the Line tab", lambda: driver.find_element(By.ID, "nav-line").click())
    wait_for("line-b reachable in the bridge links",
             lambda: "reachable" in text('#bridge-rows tr[data-line="line-b"]')
             and "unreachable" not in text('#bridge-rows tr[data-line="line-b"]'))
    wait_for("the device counts", lambda: text("#count-offline") == "1" and text("#count-online") == "4")
    wait_for("messages in the charts", lambda: text("#chart-msgs_in-value") not in ("", "–", "0/s"))
    if SHOTS:
        # Charts worth looking at: half a minute of samples.
        wait_for("30 s of rates", lambda: driver.execute_script(
            "return document.querySelector('#chart-msgs_in polyline').getAttribute('points').split(' ').length") >= 30,
            timeout=45)
    shot("line.png")

    say("ready-for-stop")
    answer("stopped")
    act("the Devices tab", lambda: driver.find_element(By.ID, "nav-devices").click())
    wait_for("remote-1 unreachable once line-b stopped", lambda: "unreachable" in row("remote-1"), timeout=30)
    if driver.execute_script("return window.__sameLoad") != "yes":
        fail("the page reloaded")
    shot("devices.png")
    act("the Line tab", lambda: driver.find_element(By.ID, "nav-line").click())
    wait_for("line-b unreachable in the bridge links",
             lambda: "unreachable" in text('#bridge-rows tr[data-line="line-b"]'))
    say("done")
    finish(0)
except SystemExit:
    raise
except Exception as e:  # noqa: BLE001 - any failure is reported to the test
    fail("%s: %s" % (type(e).__name__, e))
