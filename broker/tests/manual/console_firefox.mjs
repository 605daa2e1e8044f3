// The line console in Firefox: a manual check (CI drives headless Chromium,
// broker/tests/console.rs; Debian has no geckodriver for selenium, so Firefox is driven
// here over WebDriver BiDi by puppeteer-core). Run on 2026-11-27 with Firefox ESR 153.7:
// every step passed; docs/console/device-firefox.png is its device view.
//
//   apt-get install firefox-esr; npm install puppeteer-core@24 (in this folder or NODE_PATH)
//   fbbus serve --config C   # admin on 127.0.0.1:28884 (else pass it as the first argument)
//   mosquitto_pub -p PORT -i press-1 -t fbbus/declare/press-1 -q 1 -m '{"fbs":{"CONV":{"type":"CONVEYOR",
//     "events_out":{"MOVED":{"with":["POSITION"]}},"events_in":{"START":{"with":["SPEED"]}},
//     "data_out":{"POSITION":"INT"},"data_in":{"SPEED":"REAL"}}}}'
//   mosquitto_pub -p PORT -i press-1 -t fb/press-1/CONV/POSITION -m 42 -r -q 1
//   node console_firefox.mjs [http://127.0.0.1:28884]
//
// It checks what a person would see: press-1's row in the devices view, its FB box and
// its last value in the device view, the live feed connected in the line view.
import puppeteer from 'puppeteer-core';
const browser = await puppeteer.launch({
  browser: 'firefox',
  executablePath: '/usr/bin/firefox-esr',
  headless: true,
  args: ['--width=1280', '--height=900'],
});
const page = await browser.newPage();
await page.setViewport({ width: 1280, height: 900 });
const base = process.argv[2] || 'http://127.0.0.1:28884';
await page.goto(base + '/#/devices');
await page.waitForSelector('#devices-rows tr[data-id="press-1"]', { timeout: 15000 });
const row = await page.$eval('#devices-rows tr[data-id="press-1"]', (e) => e.textContent);
console.log('devices row:', row.replace(/\s+/g, ' ').trim());
await page.screenshot({ path: 'firefox-devices.png' });
await page.goto(base + '/#/device/press-1');
await page.waitForSelector('figure[data-fb="CONV"] svg', { timeout: 15000 });
await page.waitForFunction(() => document.querySelector('#ports-rows') && document.querySelector('#ports-rows').textContent.includes('42'), { timeout: 15000 });
const ports = await page.$eval('#ports-rows', (e) => e.textContent);
console.log('ports:', ports.replace(/\s+/g, ' ').trim().slice(0, 200));
await page.screenshot({ path: 'firefox-device.png' });
await page.goto(base + '/#/');
await page.waitForFunction(() => document.body.textContent.includes('press-1') || document.querySelectorAll('svg').length > 0, { timeout: 15000 });
await new Promise((r) => setTimeout(r, 2500));
const live = await page.$eval('header', (e) => e.textContent);
console.log('header:', live.replace(/\s+/g, ' ').trim());
await page.screenshot({ path: 'firefox-line.png' });
console.log('firefox', await browser.version());
await browser.close();
