// fbbus line console. Plain script, no framework, no build step: served by the broker.
// Device-supplied text is only ever set with textContent or SVG text nodes, never parsed
// as HTML. The device list is loaded through the paged API on every (re)connection of the
// live feed, and the feed's changes are applied to it; events that arrive during a load
// are queued and replayed in order after it, which ends at the current state.
'use strict';

(function () {
  const SVG = 'http://www.w3.org/2000/svg';
  const PAGE = 100;             // rows drawn at once in the devices view
  const LIST_PAGE = 1000;       // devices per API request
  const FIRST_PAGE = 100;       // the first request's: the first rows drawn sooner
  const STATUS_ICON = { online: '●', silent: '◐', offline: '■', unreachable: '▲' };

  const S = {
    line: '', version: '', uptimeAt: 0, uptime: 0,
    devices: new Map(),      // id -> record
    history: [],             // stats samples
    lines: {},               // bridge lines
    bridge: false,
    lastSample: null,
    clockSkew: 0,            // server time - local time, ms
    loading: false, queue: [],
    sort: { key: 'id', dir: 1 },
    page: 0,
    view: null, deviceId: null,
    activity: null,          // the viewed device's activity
    feed: null, feedDevice: undefined,
    renderPending: false,
  };

  const $ = (id) => document.getElementById(id);
  const el = (tag, attrs, text) => {
    const e = document.createElement(tag);
    if (attrs) for (const k in attrs) e.setAttribute(k, attrs[k]);
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  };
  const svg = (tag, attrs, text) => {
    const e = document.createElementNS(SVG, tag);
    if (attrs) for (const k in attrs) e.setAttribute(k, attrs[k]);
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  };
  const clear = (e) => { while (e.firstChild) e.removeChild(e.firstChild); };
  const now = () => Date.now() + S.clockSkew;

  function statusOf(r) { return r.status === 'online' && r.silent ? 'silent' : r.status; }
  function statusLabel(s) { return s === 'silent' ? 'online, silent' : s; }
  function statusBadge(s) {
    const b = el('span', { class: 'status status-' + s });
    b.appendChild(el('span', { class: 'icon', 'aria-hidden': 'true' }, STATUS_ICON[s] || '?'));
    b.appendChild(document.createTextNode(' ' + statusLabel(s)));
    return b;
  }
  function ago(iso) {
    const t = Date.parse(iso);
    if (!isFinite(t)) return '';
    const s = Math.max(0, Math.round((now() - t) / 1000));
    if (s < 60) return s + ' s ago';
    if (s < 3600) return Math.floor(s / 60) + ' min ago';
    if (s < 86400) return Math.floor(s / 3600) + ' h ago';
    return Math.floor(s / 86400) + ' d ago';
  }
  function duration(s) {
    s = Math.floor(s);
    const d = Math.floor(s / 86400), h = Math.floor(s % 86400 / 3600), m = Math.floor(s % 3600 / 60);
    return (d ? d + ' d ' : '') + (d || h ? h + ' h ' : '') + m + ' min ' + (s % 60) + ' s';
  }
  function fbNames(r) {
    const fbs = (r.interface && r.interface.fbs) || {};
    return Object.keys(fbs).map((n) => fbs[n].type ? n + ' (' + fbs[n].type + ')' : n).join(', ');
  }
  async function getJson(path) {
    const res = await fetch(path, { cache: 'no-store', headers: { Accept: 'application/json' } });
    if (!res.ok) { const e = new Error(path + ': ' + res.status); e.status = res.status; throw e; }
    return res.json();
  }

  // ------------------------------------------------------------------ loading

  async function loadDevices() {
    S.loading = true;
    S.queue = [];
    const fresh = new Map();
    let after = null, first = true;
    try {
      for (;;) {
        // A small first page draws the first rows at once; the rest comes in large pages.
        const q = '/api/v1/devices?limit=' + (first ? FIRST_PAGE : LIST_PAGE) + (after ? '&after=' + encodeURIComponent(after) : '');
        const page = await getJson(q);
        if (page.line) S.line = page.line;
        for (const r of page.devices) fresh.set(r.id, r);
        // The first load draws its first page at once; a reload keeps the old list whole.
        if (first) { if (S.devices.size === 0) { S.devices = fresh; scheduleRender(true); } first = false; }
        if (!page.next) break;
        after = page.next;
      }
      S.devices = fresh;
    } finally {
      S.loading = false;
      const queued = S.queue; S.queue = [];
      for (const [kind, data] of queued) applyEvent(kind, data);
      scheduleRender();
    }
  }

  async function loadLine() {
    const l = await getJson('/api/v1/line');
    S.line = l.line; S.version = l.version; S.uptime = l.uptime_s; S.uptimeAt = Date.now();
    S.bridge = l.bridge; S.lines = l.lines || {};
    S.history = l.history || [];
    if (S.history.length) takeSample(S.history[S.history.length - 1], false);
    scheduleRender();
  }

  async function loadActivity(id) {
    try {
      const a = await getJson('/api/v1/devices/' + encodeURIComponent(id) + '/activity');
      if (S.deviceId === id) { S.activity = a; scheduleRender(); }
    } catch (e) {
      if (S.deviceId === id) { S.activity = null; scheduleRender(); }
    }
  }

  function resync() {
    loadDevices().catch(feedTrouble);
    loadLine().catch(feedTrouble);
    if (S.deviceId) loadActivity(S.deviceId);
  }

  function feedTrouble() { $('feed-state').textContent = '⚠ broker unreachable, retrying'; }

  // ------------------------------------------------------------------ live feed

  function openFeed() {
    const device = S.view === 'device' ? S.deviceId : null;
    if (S.feed && S.feedDevice === device) return;
    if (S.feed) S.feed.close();
    S.feedDevice = device;
    const url = '/api/v1/events' + (device ? '?device=' + encodeURIComponent(device) : '');
    const feed = new EventSource(url);
    S.feed = feed;
    const on = (name, f) => feed.addEventListener(name, (ev) => {
      if (S.feed !== feed) return;
      let data;
      try { data = JSON.parse(ev.data); } catch (e) { return; }
      f(data);
    });
    on('hello', (h) => {
      S.line = h.line; S.version = h.version; S.uptime = h.uptime_s; S.uptimeAt = Date.now();
      $('feed-state').textContent = '✔ live';
      // Every (re)connection reloads: what changed while the feed was down is not lost.
      resync();
    });
    for (const kind of ['device', 'removed', 'ports', 'refusal']) {
      on(kind, (d) => { if (S.loading && (kind === 'device' || kind === 'removed')) S.queue.push([kind, d]); else applyEvent(kind, d); });
    }
    on('stats', (d) => { takeSample(d.sample, true); S.lines = d.lines || {}; scheduleRender(); });
    on('resync', () => resync());
    feed.onerror = () => { if (S.feed === feed) $('feed-state').textContent = '… reconnecting'; };
  }

  function takeSample(sample, push) {
    if (!sample) return;
    S.lastSample = sample;
    S.clockSkew = sample.t - Date.now();
    if (push) {
      S.history.push(sample);
      if (S.history.length > 300) S.history.shift();
    }
  }

  function applyEvent(kind, d) {
    if (kind === 'device') {
      S.devices.set(d.id, d);
      scheduleRender();
    } else if (kind === 'removed') {
      S.devices.delete(d.id);
      scheduleRender();
    } else if (kind === 'ports') {
      if (S.activity && d.device === S.deviceId) {
        S.activity.ports = Object.assign(S.activity.ports || {}, d.ports);
        scheduleRender();
      }
    } else if (kind === 'refusal') {
      if (S.activity && d.device === S.deviceId) {
        const list = S.activity.refusals || (S.activity.refusals = []);
        list.push(d.refusal);
        if (list.length > 20) list.shift();
        scheduleRender();
      }
    }
  }

  // ------------------------------------------------------------------ routing

  function route() {
    const hash = location.hash || '#/';
    let view = 'line', id = null, params = new URLSearchParams();
    const m = /^#\/device\/(.+)$/.exec(hash);
    if (m) { view = 'device'; try { id = decodeURIComponent(m[1]); } catch (e) { id = m[1]; } }
    else if (hash.startsWith('#/devices')) {
      view = 'devices';
      const q = hash.indexOf('?');
      if (q >= 0) params = new URLSearchParams(hash.slice(q + 1));
    }
    const changedDevice = id !== S.deviceId;
    S.view = view; S.deviceId = id;
    for (const v of ['line', 'devices', 'device']) $('view-' + v).hidden = v !== view;
    $('nav-line').setAttribute('aria-current', view === 'line' ? 'page' : 'false');
    $('nav-devices').setAttribute('aria-current', view === 'devices' ? 'page' : 'false');
    if (view === 'devices' && params.has('status')) { $('filter-status').value = params.get('status'); S.page = 0; }
    if (view === 'device' && changedDevice) { S.activity = null; }
    openFeed();
    scheduleRender(true);
    const h1 = document.querySelector('#view-' + view + ' h1');
    if (h1 && document.activeElement && document.activeElement !== document.body && !document.activeElement.closest('#view-' + view)) {
      $('main').focus({ preventScroll: true });
    }
  }

  // ------------------------------------------------------------------ rendering

  function scheduleRender(now) {
    if (now) { S.renderPending = false; render(); return; }
    if (S.renderPending) return;
    S.renderPending = true;
    setTimeout(() => { if (S.renderPending) { S.renderPending = false; render(); } }, 100);
  }

  function render() {
    $('hdr-line').textContent = S.line ? 'line ' + S.line : '';
    document.title = (S.view === 'device' && S.deviceId ? S.deviceId + ' — ' : '') + 'fbbus ' + (S.line || '') + ' console';
    if (S.view === 'line') renderLine();
    else if (S.view === 'devices') renderDevices();
    else if (S.view === 'device') renderDevice();
  }

  function renderLine() {
    $('line-title').textContent = 'Line ' + (S.line || '');
    $('line-version').textContent = S.version ? 'fbbus ' + S.version : '–';
    $('line-uptime').textContent = S.uptimeAt ? duration(S.uptime + (Date.now() - S.uptimeAt) / 1000) : '–';
    const s = S.lastSample;
    const counts = { online: 0, silent: 0, offline: 0, unreachable: 0 };
    for (const r of S.devices.values()) { counts[r.status] = (counts[r.status] || 0) + 1; if (r.status === 'online' && r.silent) counts.silent++; }
    if (s) {
      $('line-connections').textContent = s.connections;
      $('line-online').textContent = s.line_online;
    }
    for (const k of Object.keys(counts)) $('count-' + k).textContent = counts[k];
    renderCharts();
    renderBridge();
  }

  const CHARTS = [
    ['msgs_in', 'Messages in'], ['msgs_out', 'Messages out'],
    ['accepted', 'Typed accepted'], ['refused', 'Typed refused'],
  ];

  function renderCharts() {
    const box = $('charts');
    if (!box.firstChild) {
      for (const [key, label] of CHARTS) {
        const fig = el('figure', { class: 'chart', id: 'chart-' + key });
        const cap = el('figcaption');
        cap.appendChild(el('span', { class: 'label' }, label));
        cap.appendChild(el('span', { class: 'value', id: 'chart-' + key + '-value' }, '–'));
        fig.appendChild(cap);
        const g = svg('svg', { viewBox: '0 0 300 60', role: 'img', 'aria-labelledby': 'chart-' + key + '-title', preserveAspectRatio: 'none' });
        g.appendChild(svg('title', { id: 'chart-' + key + '-title' }, label));
        g.appendChild(svg('line', { x1: 0, y1: 59.5, x2: 300, y2: 59.5, class: 'axis' }));
        g.appendChild(svg('polyline', { class: 'series', points: '' }));
        fig.appendChild(g);
        fig.appendChild(el('div', { class: 'scale', id: 'chart-' + key + '-scale' }));
        box.appendChild(fig);
      }
    }
    const h = S.history.slice(-300);
    for (const [key, label] of CHARTS) {
      const values = h.map((x) => x[key] || 0);
      const max = Math.max(1, ...values);
      const n = values.length;
      const pts = values.map((v, i) => ((300 - (n - 1 - i)) - 0.5).toFixed(1) + ',' + (58 - v / max * 56).toFixed(1)).join(' ');
      const fig = $('chart-' + key);
      fig.querySelector('polyline').setAttribute('points', pts);
      const last = n ? values[n - 1] : 0;
      const text = fmtRate(last) + '/s';
      $('chart-' + key + '-value').textContent = text;
      $('chart-' + key + '-scale').textContent = 'peak ' + fmtRate(max === 1 && !values.some((v) => v) ? 0 : max) + '/s over ' + Math.round(n) + ' s';
      fig.querySelector('title').textContent = label + ': ' + text + ' now, peak ' + fmtRate(max) + '/s over the last ' + n + ' s';
    }
  }
  function fmtRate(v) { return v >= 100 ? Math.round(v).toString() : v >= 10 ? v.toFixed(1) : v.toFixed(2).replace(/\.?0+$/, '') || '0'; }

  function renderBridge() {
    const names = Object.keys(S.lines).sort();
    $('bridge-none').hidden = S.bridge || names.length > 0;
    $('bridge-table').hidden = !S.bridge && names.length === 0;
    const perLine = {};
    for (const r of S.devices.values()) if (r.line !== S.line) perLine[r.line] = (perLine[r.line] || 0) + 1;
    const rows = $('bridge-rows');
    clear(rows);
    if (!names.length) {
      const tr = el('tr');
      tr.appendChild(el('td', { colspan: 4 }, S.bridge ? 'No other line seen yet.' : ''));
      rows.appendChild(tr);
    }
    for (const name of names) {
      const l = S.lines[name];
      const tr = el('tr', { 'data-line': name });
      tr.appendChild(el('td', null, name));
      const td = el('td');
      td.appendChild(statusBadge(l.reachable ? 'online' : 'unreachable'));
      td.lastChild.lastChild.textContent = l.reachable ? ' reachable' : ' unreachable';
      tr.appendChild(td);
      tr.appendChild(el('td', { title: l.since }, ago(l.since)));
      tr.appendChild(el('td', null, perLine[name] || 0));
      rows.appendChild(tr);
    }
  }

  // devices view

  const SORTERS = {
    id: (r) => r.id, line: (r) => r.line, status: (r) => statusOf(r), since: (r) => r.since,
    session: (r) => r.session, reason: (r) => r.last_will_reason || '', fbs: (r) => fbNames(r),
  };

  function filtered() {
    const q = $('search').value.trim().toLowerCase();
    const st = $('filter-status').value, ln = $('filter-line').value;
    const out = [];
    for (const r of S.devices.values()) {
      if (st && statusOf(r) !== st && !(st === 'online' && r.status === 'online')) continue;
      if (ln && r.line !== ln) continue;
      if (q && !(r.id.toLowerCase().includes(q) || fbNames(r).toLowerCase().includes(q) ||
        (r.last_will_reason || '').toLowerCase().includes(q))) continue;
      out.push(r);
    }
    const key = SORTERS[S.sort.key] || SORTERS.id, dir = S.sort.dir;
    out.sort((a, b) => {
      const x = key(a), y = key(b);
      const c = typeof x === 'number' ? x - y : String(x).localeCompare(String(y));
      return (c || a.id.localeCompare(b.id)) * dir;
    });
    return out;
  }

  function renderDevices() {
    // The line filter offers every line the list holds.
    const lineSel = $('filter-line');
    const lines = new Set(); for (const r of S.devices.values()) lines.add(r.line);
    const have = new Set(Array.from(lineSel.options).map((o) => o.value));
    for (const l of Array.from(lines).sort()) if (!have.has(l)) lineSel.appendChild(el('option', { value: l }, l));
    const rows = filtered();
    const pages = Math.max(1, Math.ceil(rows.length / PAGE));
    if (S.page >= pages) S.page = pages - 1;
    const start = S.page * PAGE;
    const body = $('devices-rows');
    const frag = document.createDocumentFragment();
    for (const r of rows.slice(start, start + PAGE)) {
      const tr = el('tr', { 'data-id': r.id });
      const td = el('td');
      td.appendChild(el('a', { href: '#/device/' + encodeURIComponent(r.id) }, r.id));
      tr.appendChild(td);
      tr.appendChild(el('td', null, r.line));
      const st = el('td', { class: 'st' }); st.appendChild(statusBadge(statusOf(r))); tr.appendChild(st);
      tr.appendChild(el('td', { title: r.since }, ago(r.since)));
      tr.appendChild(el('td', { class: 'num' }, r.session));
      tr.appendChild(el('td', null, r.last_will_reason || ''));
      tr.appendChild(el('td', null, fbNames(r)));
      frag.appendChild(tr);
    }
    // Keep the keyboard's place across the redraw.
    const focused = document.activeElement && body.contains(document.activeElement)
      ? document.activeElement.closest('tr').getAttribute('data-id') : null;
    clear(body);
    body.appendChild(frag);
    if (focused !== null) {
      for (const tr of body.children) {
        if (tr.getAttribute('data-id') === focused) { tr.querySelector('a').focus({ preventScroll: true }); break; }
      }
    }
    $('devices-shown').textContent = rows.length + ' of ' + S.devices.size + ' devices';
    $('page-info').textContent = 'page ' + (S.page + 1) + ' of ' + pages;
    $('page-prev').disabled = S.page === 0;
    $('page-next').disabled = S.page >= pages - 1;
    for (const th of document.querySelectorAll('#devices-head th')) {
      const k = th.getAttribute('data-key');
      th.setAttribute('aria-sort', k === S.sort.key ? (S.sort.dir > 0 ? 'ascending' : 'descending') : 'none');
    }
    if (!window.__fbbusFirstRows && body.firstChild) {
      window.__fbbusFirstRows = performance.now();
    }
  }

  // device view

  function portPeriod(fb, port) {
    const p = S.activity && S.activity.periods && S.activity.periods[fb];
    return p && typeof p[port] === 'number' ? p[port] : null;
  }
  function silentFor(fb, port, value) {
    const period = portPeriod(fb, port);
    if (!period || !value) return null;
    const sil = (S.activity && S.activity.silence) || { factor: 3, min_s: 5 };
    if (!sil.factor) return null;
    const bound = Math.max(sil.factor * period, sil.min_s) * 1000;
    const quiet = now() - Date.parse(value.at);
    return quiet > bound ? { quiet: quiet / 1000, period } : null;
  }
  function shortValue(v, n) { return v.length > n ? v.slice(0, n - 1) + '…' : v; }

  function renderDevice() {
    const id = S.deviceId;
    const r = S.devices.get(id);
    $('device-title').textContent = 'Device ' + id;
    $('device-missing').hidden = !!r || S.loading;
    $('device-facts').hidden = !r;
    if (!r) { clear($('fb-boxes')); clear($('ports-rows')); return; }
    const st = $('device-status'); clear(st); st.appendChild(statusBadge(statusOf(r)));
    if (r.silent && r.silent_since) st.appendChild(document.createTextNode(' since ' + r.silent_since));
    $('device-line').textContent = r.line + (r.line === S.line ? ' (this line)' : '');
    $('device-since').textContent = r.since + ' (' + ago(r.since) + ')';
    $('device-session').textContent = r.session;
    $('device-reason').textContent = r.last_will_reason || (r.status === 'online' ? '– (online)' : '–');
    const a = S.activity || {};
    const ports = a.ports || {};
    renderBoxes(r.interface || { fbs: {} }, ports);
    // Output port table.
    const body = $('ports-rows');
    const frag = document.createDocumentFragment();
    const fbs = (r.interface && r.interface.fbs) || {};
    for (const fb of Object.keys(fbs)) {
      const f = fbs[fb];
      const outs = Object.keys(f.events_out || {}).map((p) => [p, 'event' + ((f.events_out[p].with || []).length ? ' WITH ' + f.events_out[p].with.join(', ') : '')])
        .concat(Object.keys(f.data_out || {}).map((p) => [p, 'data ' + f.data_out[p]]));
      for (const [port, kind] of outs) {
        const key = fb + '.' + port;
        const v = ports[key];
        const tr = el('tr', { 'data-port': key });
        tr.appendChild(el('th', { scope: 'row' }, key));
        tr.appendChild(el('td', null, kind));
        tr.appendChild(el('td', { class: 'value' }, v ? v.value + (v.truncated ? ' …' : '') : '—'));
        tr.appendChild(el('td', { title: v ? v.at : '' }, v ? (v.retained ? 'retained, ' : '') + ago(v.at) : 'never seen'));
        const act = el('td');
        const s = silentFor(fb, port, v);
        const period = portPeriod(fb, port);
        if (s) {
          const b = el('span', { class: 'status status-silent' });
          b.appendChild(el('span', { class: 'icon', 'aria-hidden': 'true' }, STATUS_ICON.silent));
          b.appendChild(document.createTextNode(' silent for ' + Math.round(s.quiet) + ' s (usually every ' + s.period.toFixed(2) + ' s)'));
          act.appendChild(b);
        } else {
          act.textContent = period ? 'publishing, usually every ' + period.toFixed(2) + ' s' : (v ? 'no regular period' : '');
        }
        tr.appendChild(act);
        frag.appendChild(tr);
      }
    }
    clear(body); body.appendChild(frag);
    // Refusals, newest first.
    const refusals = (a.refusals || []).slice().reverse();
    $('refusals-none').hidden = refusals.length > 0;
    const list = $('refusals'); clear(list);
    for (const x of refusals) {
      const li = el('li', { class: 'refusal' });
      li.appendChild(el('span', { class: 'when', title: x.at }, ago(x.at)));
      li.appendChild(el('span', { class: 'kind' }, x.kind + (x.reason ? ': ' + x.reason : '') + (x.code ? ' (0x' + x.code.toString(16) + ')' : '')));
      if (x.topic) li.appendChild(el('code', { class: 'topic' }, x.topic));
      if (x.detail) li.appendChild(el('span', { class: 'detail' }, x.detail));
      list.appendChild(li);
    }
    // Will and offline times.
    const will = a.profile_will;
    const own = a.will;
    const parts = [];
    if (own) {
      parts.push('Will on its connection: ' + own.topic + ' = ' + own.payload + (own.truncated ? ' …' : '') +
        ' (QoS ' + own.qos + (own.retain ? ', retained' : '') + (own.delay_s ? ', after ' + own.delay_s + ' s' : '') + ')');
    }
    if (will && Object.keys(will).length) {
      parts.push('Broker-side will (profile): ' + Object.keys(will).map((k) => k + ' = ' + will[k]).join('; '));
    }
    $('device-will').textContent = parts.length ? parts.join('. ')
      : 'No will: its connection set none' + (r.status === 'online' ? '' : ' (or it is not connected)') + ', and no profile gives one.';
    const off = $('offline-times'); clear(off);
    for (const o of (a.offline || []).slice().reverse()) {
      const li = el('li');
      li.appendChild(statusBadge(o.status));
      li.appendChild(document.createTextNode(' ' + o.since + ' (' + ago(o.since) + ')' + (o.reason ? ' — ' + o.reason : '')));
      off.appendChild(li);
    }
    if (!off.firstChild) off.appendChild(el('li', null, 'Not offline since the broker started.'));
  }

  // IEC 61499 FB boxes: event inputs/outputs in the head, data below the neck, WITH
  // associations as vertical lines with a square at each associated port.
  function renderBoxes(iface, ports) {
    const box = $('fb-boxes');
    clear(box);
    const ROW = 18, W = 200, LEFT = 90, RIGHT = 260;
    for (const name of Object.keys(iface.fbs || {})) {
      const f = iface.fbs[name];
      const ei = Object.keys(f.events_in || {}), eo = Object.keys(f.events_out || {});
      const di = Object.keys(f.data_in || {}), dout = Object.keys(f.data_out || {});
      const head = Math.max(ei.length, eo.length, 1) * ROW + 10;
      const neck = 22;
      const body = Math.max(di.length, dout.length, 1) * ROW + 10;
      const top = 24;
      const H = top + head + neck + body + 12;
      const x0 = LEFT, x1 = LEFT + W;
      const g = svg('svg', { class: 'fb', width: LEFT + W + RIGHT, height: H, viewBox: '0 0 ' + (LEFT + W + RIGHT) + ' ' + H, role: 'img', 'aria-label': 'Function block ' + name + (f.type ? ' of type ' + f.type : '') });
      g.appendChild(svg('title', null, 'FB ' + name + (f.type ? ' : ' + f.type : '')));
      g.appendChild(svg('text', { x: x0 + W / 2, y: 16, class: 'fb-name', 'text-anchor': 'middle' }, name));
      const yHead = top, yNeck = top + head, yBody = yNeck + neck;
      const outline = [
        [x0, yHead], [x1, yHead], [x1, yNeck], [x1 - 14, yNeck], [x1 - 14, yBody], [x1, yBody], [x1, yBody + body],
        [x0, yBody + body], [x0, yBody], [x0 + 14, yBody], [x0 + 14, yNeck], [x0, yNeck],
      ].map((p) => p.join(',')).join(' ');
      g.appendChild(svg('polygon', { points: outline, class: 'fb-outline' }));
      g.appendChild(svg('text', { x: x0 + W / 2, y: yNeck + 15, class: 'fb-type', 'text-anchor': 'middle' }, f.type || ''));
      const yEvent = (i) => yHead + 14 + i * ROW;
      const yData = (i) => yBody + 14 + i * ROW;
      const portY = {};
      // Input types go left of the WITH lines.
      const withIn = ei.filter((e) => ((f.events_in[e].with) || []).some((d) => d in (f.data_in || {}))).length;
      const addPort = (side, kind, label, y, type) => {
        const inSide = side === 'in';
        const x = inSide ? x0 : x1;
        g.appendChild(svg('line', { x1: inSide ? x - 12 : x, y1: y - 4, x2: inSide ? x : x + 12, y2: y - 4, class: kind === 'event' ? 'stub event' : 'stub data' }));
        const t = svg('text', { x: inSide ? x + 6 : x - 6, y: y, class: 'port ' + kind, 'text-anchor': inSide ? 'start' : 'end' }, label);
        g.appendChild(t);
        if (type) g.appendChild(svg('text', { x: inSide ? x - 22 - withIn * 7 : x + 14, y: y, class: 'ptype', 'text-anchor': inSide ? 'end' : 'start' }, type));
      };
      ei.forEach((p, i) => { portY['ei:' + p] = yEvent(i); addPort('in', 'event', p, yEvent(i)); });
      eo.forEach((p, i) => { portY['eo:' + p] = yEvent(i); addPort('out', 'event', p, yEvent(i)); });
      di.forEach((p, i) => { portY['di:' + p] = yData(i); addPort('in', 'data', p, yData(i), f.data_in[p]); });
      dout.forEach((p, i) => { portY['do:' + p] = yData(i); addPort('out', 'data', p, yData(i)); });
      // WITH associations.
      const withLines = (events, evKey, dataKey, inSide) => {
        let k = 0;
        for (const ev of events) {
          const withs = ((inSide ? f.events_in : f.events_out)[ev].with || []).filter((d) => portY[dataKey + d] !== undefined);
          if (!withs.length) continue;
          const x = inSide ? x0 - 16 - k * 7 : x1 + 16 + k * 7;
          k++;
          const ys = [portY[evKey + ev]].concat(withs.map((d) => portY[dataKey + d]));
          g.appendChild(svg('line', { x1: x, y1: Math.min(...ys) - 4, x2: x, y2: Math.max(...ys) - 4, class: 'with' }));
          for (const y of ys) g.appendChild(svg('rect', { x: x - 3, y: y - 7, width: 6, height: 6, class: 'with-mark' }));
          const assoc = svg('title', null, ev + ' WITH ' + withs.join(', '));
          g.lastChild.appendChild(assoc);
        }
        return k;
      };
      const kin = withLines(ei, 'ei:', 'di:', true);
      const kout = withLines(eo, 'eo:', 'do:', false);
      // Output values beside the data outputs (and event outputs), beyond the WITH lines.
      const vx = x1 + 22 + kout * 7;
      const valueText = (key, y, cls) => {
        const v = ports[name + '.' + key];
        if (!v) return;
        const t = svg('text', { x: vx, y: y, class: 'pvalue ' + cls }, shortValue(v.value, 28));
        t.appendChild(svg('title', null, name + '.' + key + ' = ' + v.value + ' at ' + v.at));
        g.appendChild(t);
      };
      dout.forEach((p, i) => { if (f.data_out[p]) { /* type shown in the table */ } valueText(p, yData(i), 'data'); });
      eo.forEach((p, i) => valueText(p, yEvent(i), 'event'));
      void kin;
      const fig = el('figure', { class: 'fb-box', 'data-fb': name });
      fig.appendChild(g);
      const cap = el('figcaption', null, name + (f.type ? ' : ' + f.type : '') + ' — ' +
        [ei.length + ' event in', eo.length + ' event out', di.length + ' data in', dout.length + ' data out'].join(', '));
      fig.appendChild(cap);
      box.appendChild(fig);
    }
    if (!box.firstChild) box.appendChild(el('p', null, 'No FB declared.'));
  }

  // ------------------------------------------------------------------ wiring

  function init() {
    for (const th of document.querySelectorAll('#devices-head th')) {
      th.querySelector('button').addEventListener('click', () => {
        const k = th.getAttribute('data-key');
        S.sort = { key: k, dir: S.sort.key === k ? -S.sort.dir : 1 };
        renderDevices();
      });
    }
    $('filters').addEventListener('submit', (e) => e.preventDefault());
    $('search').addEventListener('input', () => { S.page = 0; renderDevices(); });
    $('filter-status').addEventListener('change', () => { S.page = 0; renderDevices(); });
    $('filter-line').addEventListener('change', () => { S.page = 0; renderDevices(); });
    $('page-prev').addEventListener('click', () => { if (S.page > 0) { S.page--; renderDevices(); } });
    $('page-next').addEventListener('click', () => { S.page++; renderDevices(); });
    window.addEventListener('hashchange', route);
    // Ages and silence markers move with time.
    setInterval(() => scheduleRender(), 1000);
    route();
  }

  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', init);
  else init();
})();
