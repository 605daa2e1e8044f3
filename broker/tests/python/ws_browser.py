"""A browser HMI over MQTT over WebSockets: headless Chromium (WebDriver) loads a page
that runs MQTT.js (tests/js/ws_hmi.html) and prints what the page saw.

Run by broker/tests/websocket.rs:  ws_browser.py <page URL> [--insecure]

`--insecure` (wss only): Chromium accepts the test's own certificate authority's server
certificate without the CA in a trust store (--ignore-certificate-errors); installing the
CA into an NSS database for one test run is more machinery than it checks. The TLS itself
is real: the broker's listener does the handshake.

Prints one JSON line: the page's window.hmiOutcome. Every wait is bounded.
"""

import json
import os
import shutil
import sys
import tempfile

os.environ.setdefault("SE_OFFLINE", "true")  # never ask the internet for a driver

from selenium import webdriver  # noqa: E402
from selenium.common.exceptions import TimeoutException  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

URL = sys.argv[1]
INSECURE = "--insecure" in sys.argv[2:]
WAIT = 25

flags = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-dev-shm-usage",
]
if INSECURE:
    flags.append("--ignore-certificate-errors")
profile = tempfile.mkdtemp(prefix="fbbus-ws-chromium-")
options = webdriver.ChromeOptions()
options.binary_location = "/usr/bin/chromium"
for flag in flags + ["--user-data-dir=" + profile]:
    options.add_argument(flag)
driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
driver.set_page_load_timeout(WAIT)
try:
    driver.get(URL)
    try:
        outcome = WebDriverWait(driver, WAIT).until(
            lambda d: d.execute_script("return window.hmiOutcome || null"))
    except TimeoutException:
        outcome = {"error": "the page reported nothing within %d s" % WAIT}
    logs = []
    try:
        logs = [entry.get("message") for entry in driver.get_log("browser")]
    except Exception:  # noqa: BLE001 (the log is a diagnostic only)
        pass
    outcome["console"] = logs
    print(json.dumps(outcome), flush=True)
finally:
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)
