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
    trends: new Map(),       // the viewed device's 'FB.PORT' -> { kind, type, points: [[ms, value]] }
    plotted: [],             // ports on the trend chart, in the order they were added
    trendRange: 600,         // seconds shown by the sparklines and the chart
    clients: null, clientsAfter: [], clientsAt: 0,
    retained: null, retainedAfter: [],
  };
  // Port types whose values are numbers (BOOL as 1/0): the history keeps and plots them.
  const NUMERIC = new Set(['BOOL', 'SINT', 'INT', 'DINT', 'LINT', 'USINT', 'UINT', 'UDINT', 'ULINT',
    'BYTE', 'WORD', 'DWORD', 'LWORD', 'REAL', 'LREAL']);

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
  // Local date and time of an RFC 3339 text or ms since 1970; the raw value goes in a title.
  function localTime(t) {
    const ms = typeof t === 'number' ? t : Date.parse(t);
    if (!isFinite(ms)) return String(t);
    const d = new Date(ms);
    return d.toLocaleDateString() + ' ' + d.toLocaleTimeString();
  }
  // The same, the date left out when it is today.
  function shortTime(t) {
    const ms = typeof t === 'number' ? t : Date.parse(t);
    if (!isFinite(ms)) return String(t);
    const d = new Date(ms);
    return d.toDateString() === new Date().toDateString() ? d.toLocaleTimeString() : localTime(ms);
  }
  function clockTime(ms, seconds) {
    return new Date(ms).toLocaleTimeString([], seconds ? { hour: '2-digit', minute: '2-digit', second: '2-digit' } : { hour: '2-digit', minute: '2-digit' });
  }
  // An event's canonical JSON as words: "#17 at <local time>: POSITION 3, SENSOR_IN true".
  function eventWords(raw, short) {
    let e;
    try { e = JSON.parse(raw); } catch (x) { return null; }
    if (!e || typeof e !== 'object' || Array.isArray(e) || typeof e.ts !== 'number') return null;
    if (short) return '#' + e.seq + ' at ' + clockTime(e.ts / 1000, true);
    const data = e.data && typeof e.data === 'object' ? Object.keys(e.data).map((k) => k + ' ' + JSON.stringify(e.data[k])).join(', ') : '';
    return '#' + e.seq + ' at ' + localTime(e.ts / 1000) + (data ? ': ' + data : '');
  }
  function duration(s) {
    s = Math.floor(s);
    const d = Math.floor(s / 86400), h = Math.floor(s % 86400 / 3600), m = Math.floor(s % 3600 / 60);
    return (d ? d + ' d ' : '') + (d || h ? h + ' h ' : '') + m + ' min ' + (s % 60) + ' s';
  }
  // Every port of a record as FB.PORT, and the same in lower case for the search (kept
  // per record object).
  const portWords = new WeakMap();
  function portList(r) {
    let w = portWords.get(r);
    if (w === undefined) {
      const fbs = (r.interface && r.interface.fbs) || {};
      const names = [];
      for (const fb of Object.keys(fbs)) {
        for (const side of ['events_out', 'events_in', 'data_out', 'data_in']) {
          for (const p of Object.keys(fbs[fb][side] || {})) names.push(fb + '.' + p);
        }
      }
      w = { names, lower: names.map((n) => n.toLowerCase()) };
      w.text = w.lower.join(' ');
      portWords.set(r, w);
    }
    return w;
  }
  function portNames(r) { return portList(r).text; }
  // The ports whose name holds the search text (at most 3 named).
  function portMatches(r, q) {
    const w = portList(r);
    const hits = w.names.filter((n, i) => w.lower[i].includes(q));
    return hits.length > 3 ? hits.slice(0, 3).join(', ') + ' and ' + (hits.length - 3) + ' more' : hits.join(', ');
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
      if (S.deviceId === id) { S.activity = a; scheduleRender(); loadTrends(id); }
    } catch (e) {
      if (S.deviceId === id) { S.activity = null; scheduleRender(); }
    }
  }

  // The viewed device's plottable outputs: its event outputs, and its numeric data outputs.
  function plottablePorts(r) {
    const out = [];
    const fbs = (r && r.interface && r.interface.fbs) || {};
    for (const fb of Object.keys(fbs)) {
      for (const p of Object.keys(fbs[fb].events_out || {})) out.push(fb + '.' + p);
      for (const p of Object.keys(fbs[fb].data_out || {})) if (NUMERIC.has(fbs[fb].data_out[p])) out.push(fb + '.' + p);
    }
    return out;
  }
  function historyPath(id, port, extra) {
    return '/api/v1/devices/' + encodeURIComponent(id) + '/ports/' + encodeURIComponent(port) + '/history' + (extra || '');
  }
  async function loadTrends(id) {
    const from = Math.floor(now() - S.trendRange * 1000);
    const ports = plottablePorts(S.devices.get(id));
    const fresh = new Map();
    await Promise.all(ports.map(async (port) => {
      try {
        const h = await getJson(historyPath(id, port, '?from=' + from));
        fresh.set(port, { kind: h.kind, type: h.type, points: h.points || [] });
      } catch (e) { /* a port without history: no line drawn */ }
    }));
    if (S.deviceId !== id) return;
    // Points the feed brought while the histories loaded are kept.
    for (const [port, t] of S.trends) {
      const f = fresh.get(port);
      if (f) {
        const last = f.points.length ? f.points[f.points.length - 1][0] : -1;
        for (const p of t.points) if (p[0] > last) f.points.push(p);
      }
    }
    S.trends = fresh;
    scheduleRender();
  }
  function addPoints(points) {
    const oldest = now() - S.trendRange * 1000;
    for (const port of Object.keys(points || {})) {
      let t = S.trends.get(port);
      if (!t) { t = { kind: null, type: null, points: [] }; S.trends.set(port, t); }
      for (const p of points[port]) t.points.push(p);
      let cut = 0;
      while (cut < t.points.length && t.points[cut][0] < oldest) cut++;
      if (cut) t.points.splice(0, cut);
    }
  }

  async function loadClients(after) {
    const page = await getJson('/api/v1/clients?limit=100' + (after ? '&after=' + encodeURIComponent(after) : ''));
    S.clients = page; S.clientsAt = Date.now();
    scheduleRender();
  }
  async function loadRetained(after) {
    const filter = $('retained-filter').value.trim() || '#';
    const page = await getJson('/api/v1/retained?limit=100&filter=' + encodeURIComponent(filter) +
      (after ? '&after=' + encodeURIComponent(after) : ''));
    S.retained = page;
    scheduleRender();
  }

  function resync() {
    loadDevices().catch(feedTrouble);
    loadLine().catch(feedTrouble);
    if (S.deviceId) loadActivity(S.deviceId);
    if (S.view === 'clients') loadClients(S.clientsAfter[S.clientsAfter.length - 1]).catch(feedTrouble);
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
        addPoints(d.points);
        // The broker sent only part of the new points (a fast device): read the history
        // again, at most every 5 s.
        if (d.points_cut && Date.now() - (S.trendsCutAt || 0) > 5000) { S.trendsCutAt = Date.now(); loadTrends(S.deviceId); }
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
    else if (hash.startsWith('#/clients')) view = 'clients';
    else if (hash.startsWith('#/retained')) view = 'retained';
    else if (hash.startsWith('#/devices')) {
      view = 'devices';
      const q = hash.indexOf('?');
      if (q >= 0) params = new URLSearchParams(hash.slice(q + 1));
    }
    const changedDevice = id !== S.deviceId;
    S.view = view; S.deviceId = id;
    for (const v of ['line', 'devices', 'device', 'clients', 'retained']) $('view-' + v).hidden = v !== view;
    for (const v of ['line', 'devices', 'clients', 'retained']) $('nav-' + v).setAttribute('aria-current', view === v ? 'page' : 'false');
    if (view === 'clients') { S.clientsAfter = []; loadClients(null).catch(feedTrouble); }
    if (view === 'retained' && !S.retained) loadRetained(null).catch(feedTrouble);
    if (view === 'devices' && params.has('status')) { $('filter-status').value = params.get('status'); S.page = 0; }
    if (view === 'device' && changedDevice) { S.activity = null; S.trends = new Map(); S.plotted = []; clear($('ports-rows')); clear($('fb-boxes')); BOX.key = null; }
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
    else if (S.view === 'clients') renderClients();
    else if (S.view === 'retained') renderRetained();
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
      tr.appendChild(el('td', { title: l.since }, shortTime(l.since) + ' (' + ago(l.since) + ')'));
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
        portNames(r).includes(q) || (r.last_will_reason || '').toLowerCase().includes(q))) continue;
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
    const q = $('search').value.trim().toLowerCase();
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
      tr.appendChild(el('td', { title: localTime(r.since) + ' (' + r.since + ')' }, shortTime(r.since) + ' (' + ago(r.since) + ')'));
      tr.appendChild(el('td', { class: 'num' }, r.session));
      tr.appendChild(el('td', null, r.last_will_reason || ''));
      const fbCell = el('td', null, fbNames(r));
      // A search that found the device by a port says which.
      if (q && !r.id.toLowerCase().includes(q) && !fbNames(r).toLowerCase().includes(q) && portNames(r).includes(q)) {
        fbCell.appendChild(el('span', { class: 'match' }, 'port ' + portMatches(r, q)));
      }
      tr.appendChild(fbCell);
      frag.appendChild(tr);
    }
    // Keep the keyboard's place across the redraw.
    const focused = document.activeElement && body.contains(document.activeElement)
      ? document.activeElement.closest('tr').getAttribute('data-id') : null;
    clear(body);
    body.appendChild(frag);
    labelCells($('devices-table'));
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
    if (!r) { clear($('fb-boxes')); BOX.key = null; clear($('ports-rows')); return; }
    const st = $('device-status'); clear(st); st.appendChild(statusBadge(statusOf(r)));
    if (r.silent && r.silent_since) st.appendChild(el('span', { title: r.silent_since }, ' since ' + localTime(r.silent_since)));
    $('device-line').textContent = r.line + (r.line === S.line ? ' (this line)' : '');
    $('device-since').textContent = localTime(r.since) + ' (' + ago(r.since) + ')';
    $('device-since').title = r.since;
    $('device-session').textContent = r.session;
    $('device-reason').textContent = r.last_will_reason || (r.status === 'online' ? '– (online)' : '–');
    const a = S.activity || {};
    const ports = a.ports || {};
    renderBoxes(r.interface || { fbs: {} }, ports);
    // Output port table. Rows are kept across redraws (a row per port, updated in place),
    // so a click on a row's plot box is never lost to a redraw between press and release.
    const body = $('ports-rows');
    const fbs = (r.interface && r.interface.fbs) || {};
    const kept = new Map(Array.from(body.rows).map((tr) => [tr.getAttribute('data-port'), tr]));
    const order = [];
    for (const fb of Object.keys(fbs)) {
      const f = fbs[fb];
      const carriedBy = {};
      for (const ev of Object.keys(f.events_out || {})) for (const d of f.events_out[ev].with || []) (carriedBy[d] = carriedBy[d] || []).push(ev);
      const outs = Object.keys(f.events_out || {}).map((p) => [p, 'event' + ((f.events_out[p].with || []).length ? ' WITH ' + f.events_out[p].with.join(', ') : ''), true])
        .concat(Object.keys(f.data_out || {}).map((p) => [p, 'data ' + f.data_out[p] + (carriedBy[p] ? ' (with ' + carriedBy[p].join(', ') + ')' : ''), NUMERIC.has(f.data_out[p])]));
      for (const [port, kind, plottable] of outs) {
        const key = fb + '.' + port;
        let tr = kept.get(key);
        if (!tr || tr.getAttribute('data-kind') !== kind) tr = portRow(id, key, kind, plottable);
        order.push(tr);
        const v = ports[key];
        const cells = tr.cells;
        const words = v && kind.startsWith('event') ? eventWords(v.value) : null;
        cells[2].textContent = v ? (words || v.value) + (v.truncated ? ' …' : '') : '—';
        cells[2].title = v ? v.value : '';
        cells[3].textContent = v ? (v.retained ? 'retained, ' : '') + localTime(v.at) + ' (' + ago(v.at) + ')' : 'never seen';
        cells[3].title = v ? v.at : '';
        const act = cells[4];
        clear(act);
        const quiet = silentFor(fb, port, v);
        const period = portPeriod(fb, port);
        if (quiet) {
          const b = el('span', { class: 'status status-silent' });
          b.appendChild(el('span', { class: 'icon', 'aria-hidden': 'true' }, STATUS_ICON.silent));
          b.appendChild(document.createTextNode(' silent for ' + Math.round(quiet.quiet) + ' s (usually every ' + quiet.period.toFixed(2) + ' s)'));
          act.appendChild(b);
        } else {
          act.textContent = period ? 'publishing, usually every ' + period.toFixed(2) + ' s' : (v ? 'no regular period' : '');
        }
        const box = tr.querySelector('input.plot');
        if (box) box.checked = S.plotted.includes(key);
      }
    }
    // Rows in interface order; nodes moved only when the order changed.
    const same = order.length === body.rows.length && order.every((tr, k) => body.rows[k] === tr);
    if (!same) {
      clear(body);
      for (const tr of order) body.appendChild(tr);
    }
    labelCells($('ports-table'));
    renderTrend();
    // Refusals, newest first.
    const refusals = (a.refusals || []).slice().reverse();
    $('refusals-none').hidden = refusals.length > 0;
    const list = $('refusals'); clear(list);
    for (const x of refusals) {
      const li = el('li', { class: 'refusal' });
      li.appendChild(el('span', { class: 'when', title: x.at }, localTime(x.at) + ' (' + ago(x.at) + ')'));
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
      li.title = o.since;
      li.appendChild(document.createTextNode(' ' + localTime(o.since) + ' (' + ago(o.since) + ')' + (o.reason ? ' — ' + o.reason : '')));
      off.appendChild(li);
    }
    if (!off.firstChild) off.appendChild(el('li', null, 'Not offline since the broker started.'));
  }

  // One output port's row: name, kind, and (for a plottable port) its plot box and CSV
  // link; the value, time and activity cells are filled by renderDevice.
  function portRow(id, key, kind, plottable) {
    const tr = el('tr', { 'data-port': key, 'data-kind': kind });
    tr.appendChild(el('th', { scope: 'row' }, key));
    tr.appendChild(el('td', null, kind));
    tr.appendChild(el('td', { class: 'value' }));
    tr.appendChild(el('td'));
    tr.appendChild(el('td'));
    const trend = el('td', { class: 'trend-cell' });
    if (plottable) {
      const label = el('label');
      label.appendChild(el('input', { type: 'checkbox', class: 'plot', 'data-port': key }));
      label.appendChild(document.createTextNode(' plot'));
      trend.appendChild(label);
      trend.appendChild(document.createTextNode(' · '));
      trend.appendChild(el('a', { class: 'csv', 'data-port': key, download: id + '_' + key + '.csv', href: historyPath(id, key, '?format=csv') }, 'CSV'));
    } else {
      trend.textContent = '—';
    }
    tr.appendChild(trend);
    return tr;
  }

  // A port's IEC type from the viewed device's interface ('' for an event output).
  function portType(key) {
    const r = S.devices.get(S.deviceId);
    const dot = key.indexOf('.');
    const f = r && r.interface && r.interface.fbs && r.interface.fbs[key.slice(0, dot)];
    return (f && f.data_out && f.data_out[key.slice(dot + 1)]) || '';
  }
  // The event outputs whose WITH list carries the data output `key`.
  function carriers(key) {
    const r = S.devices.get(S.deviceId);
    const dot = key.indexOf('.');
    const f = r && r.interface && r.interface.fbs && r.interface.fbs[key.slice(0, dot)];
    const evs = (f && f.events_out) || {};
    return Object.keys(evs).filter((e) => (evs[e].with || []).includes(key.slice(dot + 1)));
  }
  // Held values are drawn as steps (a value stands until the next one: BOOL, integers,
  // an event's count); REAL and LREAL as lines between their samples.
  function stepped(key) { const t = portType(key); return t !== 'REAL' && t !== 'LREAL'; }

  // The polyline of `points` in the range [start, end], mapped by x(t) and y(v). More
  // points than `cols` pixels are thinned to each pixel column's first, lowest, highest
  // and last value, so an hour at 10 values a second stays a few hundred points, peaks kept.
  function polyline(points, start, end, x, y, cols, step) {
    const inRange = [];
    for (const p of points) if (p[0] >= start && p[0] <= end) inRange.push(p);
    let pts = inRange;
    if (inRange.length > cols * 4) {
      pts = [];
      let col = null, bucket = [];
      const flush = () => {
        if (!bucket.length) return;
        let lo = bucket[0], hi = bucket[0];
        for (const p of bucket) { if (p[1] < lo[1]) lo = p; if (p[1] > hi[1]) hi = p; }
        const keep = new Set([bucket[0], lo, hi, bucket[bucket.length - 1]]);
        for (const p of bucket) if (keep.has(p)) pts.push(p);
        bucket = [];
      };
      for (const p of inRange) {
        const c = Math.floor((p[0] - start) / Math.max(1, end - start) * cols);
        if (c !== col) { flush(); col = c; }
        bucket.push(p);
      }
      flush();
    }
    const out = [];
    let prev = null;
    for (const p of pts) {
      const px = x(p[0]).toFixed(1), py = y(p[1]).toFixed(1);
      if (step && prev !== null) out.push(px + ',' + prev);
      out.push(px + ',' + py);
      prev = py;
    }
    return out.join(' ');
  }

  // A sparkline's points in the box (x, y, w, h): the trend range, or less if the port has
  // not been seen for that long, newest at the right.
  function sparkPoints(key, points, x, y, w, h) {
    if (!points.length) return '';
    const end = now(), start = Math.max(end - S.trendRange * 1000, points[0][0]);
    let lo = Infinity, hi = -Infinity;
    for (const p of points) if (p[0] >= start) { lo = Math.min(lo, p[1]); hi = Math.max(hi, p[1]); }
    if (!isFinite(lo)) return '';
    if (hi === lo) { hi += 1; lo -= 1; }
    return polyline(points, start, end, (t) => x + (t - start) / Math.max(1, end - start) * w,
      (v) => y + h - (v - lo) / (hi - lo) * h, w, stepped(key));
  }

  // Value axis ticks at round numbers (1, 2 or 5 times a power of ten), about n of them.
  function niceTicks(lo, hi, n) {
    const raw = (hi - lo) / n;
    const mag = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) || 10 * mag;
    const first = Math.floor(lo / step) * step, last = Math.ceil(hi / step) * step;
    const ticks = [];
    for (let v = first; v <= last + step / 2; v += step) ticks.push(v);
    const decimals = Math.max(0, -Math.floor(Math.log10(step)));
    return { lo: first, hi: last, ticks, label: (v) => (Math.abs(v) < step / 2 ? 0 : v).toFixed(Math.min(decimals, 6)) };
  }
  // Time axis ticks at round local times, at most n of them.
  const TIME_STEPS = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600].map((s) => s * 1000);
  function timeTicks(start, end, n) {
    const step = TIME_STEPS.find((s) => (end - start) / s <= n) || 3600000;
    const zone = new Date(start).getTimezoneOffset() * 60000;   // round in local time
    const ticks = [];
    for (let t = Math.ceil((start - zone) / step) * step + zone; t <= end; t += step) ticks.push(t);
    return { ticks, seconds: step < 60000 };
  }

  // The trend chart: the plotted ports over the range, one value axis, local times. Drawn
  // at the width it is shown at (no stretching: its text stays readable at 400 px).
  function renderTrend() {
    const fig = $('trend-chart');
    const shown = S.plotted.filter((p) => S.trends.has(p));
    $('trend-none').hidden = shown.length > 0;
    fig.hidden = shown.length === 0;
    clear(fig);
    if (!shown.length) return;
    const cs = getComputedStyle(fig);
    const W = Math.max(240, Math.floor(fig.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight) - 2));
    const H = W < 500 ? 200 : 260, R = 14, T = 10, B = 24;
    // The range, or from the oldest value shown if the ports are younger than that.
    const end = now();
    let start = end - S.trendRange * 1000;
    const oldest = Math.min(...shown.map((p) => { const q = S.trends.get(p).points; return q.length ? q[0][0] : end; }));
    start = Math.max(start, Math.min(oldest, end - 10000));
    let lo = Infinity, hi = -Infinity;
    for (const p of shown) for (const q of S.trends.get(p).points) if (q[0] >= start) { lo = Math.min(lo, q[1]); hi = Math.max(hi, q[1]); }
    if (!isFinite(lo)) { lo = 0; hi = 1; }
    if (hi === lo) { hi += 1; lo -= 1; }
    const vt = niceTicks(lo, hi, H < 240 ? 4 : 5);
    const labels = vt.ticks.map(vt.label);
    const L = 10 + 7 * Math.max(...labels.map((s) => s.length));
    const x = (t) => L + (t - start) / (end - start) * (W - L - R);
    const y = (v) => T + (vt.hi - v) / (vt.hi - vt.lo) * (H - T - B);
    const g = svg('svg', { viewBox: '0 0 ' + W + ' ' + H, width: W, height: H, role: 'img', 'aria-labelledby': 'trend-title' });
    const minutes = Math.round((end - start) / 60000);
    g.appendChild(svg('title', { id: 'trend-title' }, 'Trend of ' + shown.join(', ') + ' over the last ' + (minutes ? minutes + ' min' : Math.round((end - start) / 1000) + ' s')));
    vt.ticks.forEach((v, i) => {
      g.appendChild(svg('line', { x1: L, x2: W - R, y1: y(v), y2: y(v), class: 'grid-line' }));
      g.appendChild(svg('text', { x: L - 6, y: y(v) + 4, class: 'tick value-tick', 'text-anchor': 'end' }, labels[i]));
    });
    // Time ticks a label's width and a gap apart; a label that would cross the chart's
    // edge is left out (its tick stays).
    const labelW = 6.2 * clockTime(end, true).length;
    const tt = timeTicks(start, end, Math.max(2, Math.floor((W - L - R) / (labelW + 40))));
    for (const t of tt.ticks) {
      const px = x(t);
      g.appendChild(svg('line', { x1: px, x2: px, y1: H - B, y2: H - B + 4, class: 'axis' }));
      if (px - labelW / 2 < 2 || px + labelW / 2 > W - 2) continue;
      const label = svg('text', { x: px, y: H - 6, class: 'tick time-tick', 'text-anchor': 'middle' }, clockTime(t, tt.seconds));
      label.appendChild(svg('title', null, localTime(t)));
      g.appendChild(label);
    }
    g.appendChild(svg('line', { x1: L, x2: L, y1: T, y2: H - B, class: 'axis' }));
    g.appendChild(svg('line', { x1: L, x2: W - R, y1: H - B, y2: H - B, class: 'axis' }));
    const legend = el('ul', { class: 'legend' });
    shown.forEach((port, i) => {
      const t = S.trends.get(port);
      const type = t.type || portType(port) || 'event, occurrence #';
      const line = svg('polyline', { class: 'series s' + (i % 4), 'data-port': port, points: polyline(t.points, start, end, x, y, W - L - R, stepped(port)) });
      line.appendChild(svg('title', null, port + ' (' + type + ')'));
      g.appendChild(line);
      const li = el('li', { class: 's' + (i % 4), 'data-port': port });
      li.appendChild(el('span', { class: 'swatch', 'aria-hidden': 'true' }));
      const last = t.points[t.points.length - 1];
      li.appendChild(document.createTextNode(port + ' (' + type + ')' + (carriers(port).length ? ', WITH data of ' + carriers(port).join(', ') : '') +
        (last ? ': ' + last[1] + ' at ' + clockTime(last[0], true) : '')));
      if (last) li.title = localTime(last[0]) + ' (' + last[0] + ' ms since 1970)';
      legend.appendChild(li);
    });
    fig.appendChild(g);
    fig.appendChild(legend);
  }
  // Narrow screens show table rows as cards: each cell says which column it is.
  function labelCells(table) {
    const heads = Array.from(table.querySelectorAll('thead th')).map((th) => th.textContent.trim());
    for (const tr of table.tBodies[0].rows) {
      Array.from(tr.cells).forEach((c, i) => { if (heads[i]) c.setAttribute('data-label', heads[i]); });
    }
  }

  function renderClients() {
    const page = S.clients;
    const body = $('clients-rows');
    clear(body);
    if (!page) return;
    for (const c of page.clients) {
      const tr = el('tr', { 'data-client': c.client_id });
      tr.appendChild(el('th', { scope: 'row' }, c.client_id));
      tr.appendChild(el('td', null, c.username === null ? '–' : c.username));
      tr.appendChild(el('td', null, c.address));
      tr.appendChild(el('td', null, c.listener));
      tr.appendChild(el('td', null, 'MQTT ' + c.protocol));
      tr.appendChild(el('td', { class: 'num' }, c.keep_alive_s ? c.keep_alive_s + ' s' : 'off'));
      tr.appendChild(el('td', { title: c.connected_since }, localTime(c.connected_since) + ' (' + ago(c.connected_since) + ')'));
      tr.appendChild(el('td', { class: 'num' }, c.subscriptions));
      tr.appendChild(el('td', { class: 'num' }, c.messages_in));
      tr.appendChild(el('td', { class: 'num' }, c.messages_out));
      body.appendChild(tr);
    }
    labelCells($('clients-table'));
    const from = S.clientsAfter.length * 100;
    $('clients-shown').textContent = page.clients.length ? (from + 1) + '–' + (from + page.clients.length) + ' of ' + page.total + ' connected' : 'No client connected.';
    $('clients-first').disabled = S.clientsAfter.length === 0;
    $('clients-next').disabled = !page.next;
  }

  function renderRetained() {
    const page = S.retained;
    const body = $('retained-rows');
    clear(body);
    if (!page) return;
    for (const r of page.retained) {
      const tr = el('tr', { 'data-topic': r.topic });
      tr.appendChild(el('th', { scope: 'row' }, r.topic));
      tr.appendChild(el('td', { class: 'num' }, r.bytes));
      tr.appendChild(el('td', null, r.owner));
      tr.appendChild(el('td', { title: r.retained_at }, localTime(r.retained_at) + ' (' + ago(r.retained_at) + ')'));
      body.appendChild(tr);
    }
    labelCells($('retained-table'));
    $('retained-shown').textContent = page.retained.length + ' shown of ' + page.total + ' retained topics held by clients';
    $('retained-first').disabled = S.retainedAfter.length === 0;
    $('retained-next').disabled = !page.next;
  }

  // IEC 61499 FB boxes: event inputs/outputs in the head, data below the neck, WITH
  // associations as vertical lines with a square at each associated port. A box is drawn
  // once per interface (and per narrow or wide screen), sized to its port names; the
  // sparklines and values beside its outputs are then updated in place, so a click on one
  // or the keyboard's focus is never lost to a redraw.
  const BOX = { key: null, parts: new Map() };   // 'FB.PORT' -> its sparkline and value
  function renderBoxes(iface, ports) {
    const box = $('fb-boxes');
    const narrow = box.clientWidth > 0 && box.clientWidth < 600;
    const key = JSON.stringify(iface) + (narrow ? ' narrow' : '');
    if (key !== BOX.key) { buildBoxes(box, iface, narrow); BOX.key = key; }
    for (const [full, part] of BOX.parts) {
      if (part.spark) {
        const trend = S.trends.get(full);
        const on = S.plotted.includes(full);
        part.spark.setAttribute('points', trend ? sparkPoints(full, trend.points, part.sx, part.y - 12, part.sw, 12) : '');
        part.hit.setAttribute('aria-pressed', on ? 'true' : 'false');
        part.hitTitle.textContent = full + ': ' + (trend ? trend.points.length + ' values in the last ' +
          Math.round(S.trendRange / 60) + ' min' : 'no history') + ' (click: ' + (on ? 'off' : 'on') + ' the trend chart)';
      }
      const v = ports[full];
      const words = v && part.event ? eventWords(v.value, true) : null;
      part.value.textContent = v ? shortValue(words || v.value, part.chars) : '';
      part.valueTitle.textContent = v ? full + ' = ' + v.value + ' at ' + localTime(v.at) + ' (' + v.at + ')' : '';
    }
  }

  function buildBoxes(box, iface, narrow) {
    clear(box);
    BOX.parts = new Map();
    // px per character: port names (12 px), types and values (11 px).
    const ROW = 18, CH = 7.4, TCH = 6.6, SPARK = narrow ? 40 : 60, CHARS = narrow ? 17 : 28;
    const longest = (list) => Math.max(0, ...list.map((p) => p.length));
    for (const name of Object.keys(iface.fbs || {})) {
      const f = iface.fbs[name];
      const ei = Object.keys(f.events_in || {}), eo = Object.keys(f.events_out || {});
      const di = Object.keys(f.data_in || {}), dout = Object.keys(f.data_out || {});
      const head = Math.max(ei.length, eo.length, 1) * ROW + 10;
      const neck = 22;
      const body = Math.max(di.length, dout.length, 1) * ROW + 10;
      const top = 24;
      const H = top + head + neck + body + 12;
      // Events with WITH lines on each side (drawn between the box and the types/values).
      const withIn = ei.filter((e) => ((f.events_in[e].with) || []).some((d) => d in (f.data_in || {}))).length;
      const withOut = eo.filter((e) => ((f.events_out[e].with) || []).some((d) => d in (f.data_out || {}))).length;
      const W = Math.round(Math.max(120, (Math.max(longest(ei), longest(di)) + Math.max(longest(eo), longest(dout))) * CH + 44,
        name.length * 8 + 20, (f.type || '').length * 7 + 44));
      const LEFT = Math.round(26 + withIn * 7 + longest(di.map((p) => f.data_in[p] || '')) * TCH);
      const vx = LEFT + W + 22 + withOut * 7;                // sparklines, then values
      const RIGHT = 22 + withOut * 7 + SPARK + 6 + Math.round(CHARS * TCH) + 4;
      const x0 = LEFT, x1 = LEFT + W;
      const g = svg('svg', { class: 'fb', width: LEFT + W + RIGHT, height: H, viewBox: '0 0 ' + (LEFT + W + RIGHT) + ' ' + H, role: 'group', 'aria-label': 'Function block ' + name + (f.type ? ' of type ' + f.type : '') });
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
      const addPort = (side, kind, label, y, type) => {
        const inSide = side === 'in';
        const x = inSide ? x0 : x1;
        g.appendChild(svg('line', { x1: inSide ? x - 12 : x, y1: y - 4, x2: inSide ? x : x + 12, y2: y - 4, class: kind === 'event' ? 'stub event' : 'stub data' }));
        g.appendChild(svg('text', { x: inSide ? x + 6 : x - 6, y: y, class: 'port ' + kind, 'text-anchor': inSide ? 'start' : 'end' }, label));
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
          g.lastChild.appendChild(svg('title', null, ev + ' WITH ' + withs.join(', ')));
        }
      };
      withLines(ei, 'ei:', 'di:', true);
      withLines(eo, 'eo:', 'do:', false);
      // Beside each output: its sparkline (a plottable one: a button that puts it on the
      // trend chart) and its last value.
      const output = (port, y, event, plottable) => {
        const full = name + '.' + port;
        const part = { y, event, chars: CHARS, sx: vx, sw: SPARK };
        let parent = g;
        if (plottable) {
          part.hit = svg('g', { class: 'spark-hit', 'data-plot': full, tabindex: '0', role: 'button', 'aria-pressed': 'false', 'aria-label': 'Plot ' + full + ' on the trend chart' });
          part.hitTitle = svg('title');
          part.hit.appendChild(part.hitTitle);
          part.hit.appendChild(svg('rect', { x: vx - 3, y: y - 14, width: SPARK + 9 + CHARS * TCH, height: 17, rx: 3 }));
          part.spark = svg('polyline', { class: 'spark', 'data-port': full, points: '' });
          part.hit.appendChild(part.spark);
          g.appendChild(part.hit);
          parent = part.hit;
        }
        const t = svg('text', { x: vx + SPARK + 6, y: y, class: 'pvalue ' + (event ? 'event' : 'data'), 'data-port': full });
        part.value = svg('tspan');
        part.valueTitle = svg('title');
        t.appendChild(part.value);
        t.appendChild(part.valueTitle);
        parent.appendChild(t);
        BOX.parts.set(full, part);
      };
      dout.forEach((p, i) => output(p, yData(i), false, NUMERIC.has(f.data_out[p])));
      eo.forEach((p, i) => output(p, yEvent(i), true, true));
      const fig = el('figure', { class: 'fb-box', 'data-fb': name });
      fig.appendChild(g);
      fig.appendChild(el('figcaption', null, name + (f.type ? ' : ' + f.type : '') + ' — ' +
        [ei.length + ' event in', eo.length + ' event out', di.length + ' data in', dout.length + ' data out'].join(', ')));
      box.appendChild(fig);
    }
    if (!box.firstChild) box.appendChild(el('p', null, 'No FB declared.'));
  }

  // A port on or off the trend chart (from its plot box or its sparkline).
  function setPlotted(port, on, reveal) {
    S.plotted = S.plotted.filter((p) => p !== port);
    if (on) S.plotted.push(port);
    scheduleRender(true);
    if (on && reveal) $('trend').scrollIntoView({ block: 'nearest' });
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
    $('ports-rows').addEventListener('change', (e) => {
      const port = e.target.getAttribute && e.target.getAttribute('data-port');
      if (!port || !e.target.classList.contains('plot')) return;
      setPlotted(port, e.target.checked, false);
    });
    // A sparkline in an FB box: a click (or Enter, Space) puts its port on the chart.
    const plotFromBox = (e) => {
      const hit = e.target.closest && e.target.closest('[data-plot]');
      if (!hit) return false;
      const port = hit.getAttribute('data-plot');
      setPlotted(port, !S.plotted.includes(port), true);
      return true;
    };
    $('fb-boxes').addEventListener('click', plotFromBox);
    $('fb-boxes').addEventListener('keydown', (e) => {
      if ((e.key === 'Enter' || e.key === ' ') && plotFromBox(e)) e.preventDefault();
    });
    // The boxes and the chart are drawn for the width they are shown at.
    window.addEventListener('resize', () => scheduleRender());
    for (const radio of document.querySelectorAll('input[name="trend-range"]')) {
      radio.addEventListener('change', () => {
        S.trendRange = Number(radio.value);
        if (S.deviceId) loadTrends(S.deviceId);
      });
    }
    $('clients-first').addEventListener('click', () => { S.clientsAfter = []; loadClients(null).catch(feedTrouble); });
    $('clients-next').addEventListener('click', () => {
      if (!S.clients || !S.clients.next) return;
      S.clientsAfter.push(S.clients.next);
      loadClients(S.clients.next).catch(feedTrouble);
    });
    $('retained-form').addEventListener('submit', (e) => { e.preventDefault(); S.retainedAfter = []; loadRetained(null).catch(feedTrouble); });
    $('retained-first').addEventListener('click', () => { S.retainedAfter = []; loadRetained(null).catch(feedTrouble); });
    $('retained-next').addEventListener('click', () => {
      if (!S.retained || !S.retained.next) return;
      S.retainedAfter.push(S.retained.next);
      loadRetained(S.retained.next).catch(feedTrouble);
    });
    // The clients' counters move: the page shown is read again every 5 s.
    setInterval(() => {
      if (S.view === 'clients' && Date.now() - S.clientsAt >= 5000) loadClients(S.clientsAfter[S.clientsAfter.length - 1]).catch(feedTrouble);
    }, 1000);
    window.addEventListener('hashchange', route);
    // Ages and silence markers move with time.
    setInterval(() => scheduleRender(), 1000);
    route();
  }

  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', init);
  else init();
})();
