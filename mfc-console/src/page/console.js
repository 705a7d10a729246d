// The console's page: polls the console's JSON API and draws everything itself (plots on
// <canvas>, no library, nothing loaded from elsewhere). Every value from the API is put in
// the page as text (textContent), never as markup.
//
// For tests and scripts, each plot's <canvas> carries `data-points` (points drawn) and
// `data-last-time` (plant time of the last one); each device in the list carries
// `data-device` and `data-alive`; each form's result line carries `data-state`
// (`idle`, `pending`, `accepted`, `refused`).
'use strict';

const WINDOW_S = 20;          // seconds of plant time shown
const LIST_MS = 500;          // device list refresh
const SERIES_MS = 250;        // plot refresh
const DETAIL_MS = 1000;       // status and configuration refresh
const AUDIT_MS = 3000;        // the audit trail's refresh (and after every change sent)
const COLORS = ['#2f6fdb', '#e07b00', '#1a9e5a', '#8e44ad', '#c0392b', '#16a2b8'];

const state = {
  selected: decodeURIComponent(location.hash.slice(1)) || null,
  run: null,
  next: 0,
  points: [],
  detail: null,
  me: null,         // who the console acts for: {name, role, proof}, or null (log in)
  shape: '',        // the configuration's shape the forms were built for
  refFilled: false,
};

const $ = (id) => document.getElementById(id);

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}

function fmt(v) {
  if (v === null || v === undefined || Number.isNaN(v)) return '–';
  if (typeof v !== 'number') return String(v);
  const a = Math.abs(v);
  if (a !== 0 && (a >= 1e5 || a < 1e-3)) return v.toExponential(3);
  return String(Number(v.toPrecision(5)));
}

// An axis tick: the round value niceTicks chose, in its shortest form ("4e-4", not
// "4.000e-4"; "0.25", not "0.25000000000000006").
function tickFmt(v) {
  if (v === 0) return '0';
  const r = Number(v.toPrecision(4));
  const a = Math.abs(r);
  return a >= 1e5 || a < 1e-3 ? r.toExponential() : String(r);
}

async function api(path, options) {
  const r = await fetch(path, Object.assign({ cache: 'no-store' }, options || {}));
  let body = {};
  try { body = await r.json(); } catch (_) { /* not JSON */ }
  // A session that ended (idle, too old, logged out elsewhere): back to the login form.
  if (r.status === 401 && state.me) showLogin();
  return { ok: r.ok, status: r.status, body };
}

// ---- who is here -----------------------------------------------------------------------

function showLogin() {
  state.me = null;
  $('main').hidden = true;
  $('login').hidden = false;
  $('who').textContent = '';
  $('logout').hidden = true;
}

function showMe(me) {
  state.me = me;
  $('login').hidden = true;
  $('main').hidden = false;
  const how = me.proof === 'open' ? 'no login: loopback only' : `by ${me.proof}`;
  $('who').textContent = `${me.name} · ${me.role} · ${how}`;
  $('who').dataset.role = me.role;
  $('logout').hidden = me.proof !== 'password';
  const viewer = me.role === 'viewer';
  for (const id of ['gain-apply', 'ref-apply', 'com-start', 'com-confirm', 'com-abort']) $(id).disabled = viewer;
  for (const p of document.querySelectorAll('.viewer-note')) p.hidden = !viewer;
}

async function checkMe() {
  let r;
  try { r = await api('api/me'); } catch (_) { return false; }
  if (r.ok) { showMe(r.body); return true; }
  showLogin();
  return false;
}

async function submitLogin(ev) {
  ev.preventDefault();
  const p = $('login-result');
  p.dataset.state = 'pending';
  p.textContent = 'checking…';
  let r;
  try {
    r = await api('api/login', {
      method: 'POST', headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ name: $('login-name').value.trim(), password: $('login-password').value }),
    });
  } catch (e) { r = { ok: false, status: 0, body: { reason: String(e) } }; }
  $('login-password').value = '';
  if (r.ok) {
    p.dataset.state = 'accepted';
    p.textContent = '';
    showMe(r.body);
  } else {
    p.dataset.state = 'refused';
    p.textContent = r.body.reason || `failed (HTTP ${r.status})`;
  }
}

async function logout() {
  try { await api('api/logout', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: '{}' }); } catch (_) { /* gone anyway */ }
  showLogin();
}

// ---- the device list -----------------------------------------------------------------

function select(id) {
  if (state.selected === id) return;
  state.selected = id;
  state.run = null;
  state.next = 0;
  state.points = [];
  state.detail = null;
  state.shape = '';
  state.refFilled = false;
  history.replaceState(null, '', '#' + encodeURIComponent(id));
  $('gain-result').textContent = '';
  $('gain-result').dataset.state = 'idle';
  $('ref-result').textContent = '';
  $('ref-result').dataset.state = 'idle';
  for (const li of $('devices').children) li.classList.toggle('selected', li.dataset.device === id);
  $('audit').replaceChildren();
  refreshDetail();
  refreshAudit();
}

async function refreshList() {
  if (!state.me) return;
  let r;
  try { r = await api('api/devices'); } catch (e) {
    $('link').dataset.state = 'down';
    $('link').textContent = 'console unreachable';
    return;
  }
  $('link').dataset.state = 'ok';
  $('link').textContent = 'live';
  const list = r.body.devices || [];
  const c = r.body.counters || {};
  $('counters').textContent =
    `samples ${c.samples} · commands ${c.commands} · refused ${
      (c.oversized || 0) + (c.undecodable || 0) + (c.bad_id || 0) + (c.bad_values || 0)} · devices ${list.length}`;
  const ul = $('devices');
  const seen = new Set();
  for (const d of list) {
    seen.add(d.id);
    let li = ul.querySelector(`li[data-device="${CSS.escape(d.id)}"]`);
    if (!li) {
      li = el('li', { 'data-device': d.id });
      li.append(el('span', { class: 'dot' }), el('span', { class: 'name' }), el('span', { class: 'sub' }));
      li.addEventListener('click', () => select(d.id));
      ul.append(li);
    }
    li.dataset.alive = String(d.alive);
    li.classList.toggle('selected', d.id === state.selected);
    li.querySelector('.name').textContent = d.id;
    const mode = d.mode ? d.mode : 'no samples';
    li.querySelector('.sub').textContent =
      `${d.alive ? 'up' : 'gone'} · ${mode} · ${d.served_by ? 'served by ' + d.served_by : 'not served'}`;
  }
  for (const li of [...ul.children]) if (!seen.has(li.dataset.device)) li.remove();
  // Keep the list in the API's order (sorted by id).
  for (const d of list) ul.append(ul.querySelector(`li[data-device="${CSS.escape(d.id)}"]`));
  $('no-devices').hidden = list.length > 0;
  if (!state.selected && list.length > 0) select((list.find((d) => d.alive) || list[0]).id);
}

// ---- plots ---------------------------------------------------------------------------

async function refreshSeries() {
  const id = state.selected;
  if (!id || !state.me) return;
  for (let round = 0; round < 5; round++) {
    let r;
    try { r = await api(`api/devices/${encodeURIComponent(id)}/series?since=${state.next}`); } catch (_) { return; }
    if (!r.ok || id !== state.selected) return;
    const s = r.body;
    if (state.run !== s.run) { state.run = s.run; state.points = []; }
    state.points.push(...s.points);
    state.next = s.next;
    if (s.points.length < 4000) break;
  }
  const last = state.points.length ? state.points[state.points.length - 1].t : 0;
  let cut = 0;
  while (cut < state.points.length && state.points[cut].t < last - WINDOW_S) cut++;
  if (cut > 0) state.points.splice(0, cut);
  drawAll();
}

function plotsFor(channels) {
  const box = $('plots');
  if (box.dataset.channels === String(channels)) return;
  box.dataset.channels = String(channels);
  box.replaceChildren();
  for (let i = 0; i < channels; i++) {
    for (const [kind, title] of [['y', `Channel ${i}: output y and reference y*`],
                                 ['v', `Channel ${i}: command v and F estimate`]]) {
      const div = el('div', { class: 'plot' });
      div.append(el('h4', {}, title),
                 el('canvas', { id: `plot-${kind}-${i}`, 'data-points': '0', 'data-last-time': '' }));
      box.append(div);
    }
  }
}

function drawAll() {
  const pts = state.points;
  let channels = 0;
  for (const p of pts) channels = Math.max(channels, p.y.length);
  if (state.detail) channels = Math.max(channels, state.detail.channels || 0);
  plotsFor(channels);
  for (let i = 0; i < channels; i++) {
    const t = pts.map((p) => p.t);
    const pick = (key) => pts.map((p) => (p[key].length > i ? p[key][i] : null));
    draw($(`plot-y-${i}`), t, [
      { name: 'y', color: COLORS[0], ys: pick('y') },
      { name: 'y*', color: COLORS[1], ys: pick('r'), dash: [6, 4] },
    ]);
    draw($(`plot-v-${i}`), t, [
      { name: 'v', color: COLORS[2], ys: pick('v') },
      { name: 'F (right axis)', color: COLORS[3], ys: pick('f'), right: true },
    ]);
  }
}

function niceTicks(lo, hi, n) {
  const span = hi - lo;
  if (!(span > 0)) return [lo];
  const raw = span / n;
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * mag).find((s) => s >= raw) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

function range(series) {
  let lo = Infinity, hi = -Infinity;
  for (const s of series) for (const v of s.ys) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (lo === Infinity) return null;
  if (hi - lo < 1e-9) { const m = Math.max(Math.abs(lo) * 0.1, 1e-3); lo -= m; hi += m; }
  const pad = (hi - lo) * 0.06;
  return [lo - pad, hi + pad];
}

// One plot: time on x, left-axis and right-axis series. Records what it drew on the canvas.
function draw(canvas, t, series) {
  if (!canvas) return;
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth || 400, h = canvas.clientHeight || 190;
  if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
    canvas.width = Math.round(w * dpr);
    canvas.height = Math.round(h * dpr);
  }
  const ctx = canvas.getContext('2d');
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, w, h);
  ctx.font = '11px system-ui, sans-serif';
  const left = series.filter((s) => !s.right), right = series.filter((s) => s.right);
  const yl = range(left), yr = range(right);
  const pad = { l: 54, r: yr ? 58 : 10, t: 16, b: 20 };
  const pw = w - pad.l - pad.r, ph = h - pad.t - pad.b;
  let drawn = 0;
  if (t.length > 0 && yl) {
    let x0 = t[0], x1 = t[t.length - 1];
    if (x1 - x0 < 1) x1 = x0 + 1;
    const X = (v) => pad.l + (v - x0) / (x1 - x0) * pw;
    const Y = (r) => (v) => pad.t + (1 - (v - r[0]) / (r[1] - r[0])) * ph;
    ctx.strokeStyle = '#e3e7ec';
    ctx.fillStyle = '#6b7480';
    ctx.lineWidth = 1;
    ctx.textAlign = 'right';
    for (const v of niceTicks(yl[0], yl[1], 4)) {
      const y = Y(yl)(v);
      ctx.beginPath(); ctx.moveTo(pad.l, y); ctx.lineTo(pad.l + pw, y); ctx.stroke();
      ctx.fillText(tickFmt(v), pad.l - 4, y + 4);
    }
    if (yr) {
      ctx.textAlign = 'left';
      for (const v of niceTicks(yr[0], yr[1], 4)) ctx.fillText(tickFmt(v), pad.l + pw + 4, Y(yr)(v) + 4);
    }
    ctx.textAlign = 'center';
    for (const v of niceTicks(x0, x1, 6)) {
      const x = X(v);
      ctx.beginPath(); ctx.moveTo(x, pad.t); ctx.lineTo(x, pad.t + ph); ctx.stroke();
      ctx.fillText(tickFmt(v) + ' s', x, h - 5);
    }
    for (const s of series) {
      const r = s.right ? yr : yl;
      if (!r) continue;
      const yf = Y(r);
      ctx.strokeStyle = s.color;
      ctx.lineWidth = 1.5;
      ctx.setLineDash(s.dash || []);
      ctx.beginPath();
      let pen = false, n = 0;
      for (let k = 0; k < t.length; k++) {
        const v = s.ys[k];
        if (v === null || !Number.isFinite(v)) { pen = false; continue; }
        const x = X(t[k]), y = yf(v);
        if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
        pen = true; n++;
      }
      ctx.stroke();
      ctx.setLineDash([]);
      if (s === series[0]) drawn = n;
    }
  }
  ctx.strokeStyle = '#b8c0ca';
  ctx.strokeRect(pad.l, pad.t, pw, ph);
  // Legend.
  let lx = pad.l + 6;
  ctx.textAlign = 'left';
  for (const s of series) {
    ctx.fillStyle = s.color;
    ctx.fillRect(lx, 4, 10, 3);
    ctx.fillStyle = '#1d232b';
    ctx.fillText(s.name, lx + 14, 11);
    lx += ctx.measureText(s.name).width + 30;
  }
  canvas.dataset.points = String(drawn);
  canvas.dataset.lastTime = t.length ? String(t[t.length - 1]) : '';
}

// ---- status, configuration, forms ----------------------------------------------------

function rows(table, pairs) {
  table.replaceChildren(...pairs.map(([k, v]) => {
    const tr = el('tr');
    tr.append(el('td', {}, k), el('td', {}, v));
    return tr;
  }));
}

function limitsText(l) {
  if (!l) return '–';
  const lo = l.min === null || l.min === undefined ? '−∞' : fmt(l.min);
  const hi = l.max === null || l.max === undefined ? '+∞' : fmt(l.max);
  const rate = l.rate_limit === null || l.rate_limit === undefined ? '' : `, ≤ ${fmt(l.rate_limit)}/s`;
  return `[${lo}, ${hi}]${rate}`;
}

async function refreshDetail() {
  const id = state.selected;
  if (!id || !state.me) return;
  let r;
  try { r = await api(`api/devices/${encodeURIComponent(id)}`); } catch (_) { return; }
  if (id !== state.selected) return;
  if (!r.ok) { $('detail').hidden = true; return; }
  const d = r.body;
  state.detail = d;
  $('detail').hidden = false;
  $('dev-id').textContent = d.id;
  const alive = $('dev-alive');
  alive.dataset.state = d.alive ? 'up' : 'gone';
  alive.textContent = d.alive ? 'plant up' : 'plant gone';
  const mode = d.mode || d.status_mode;
  $('dev-mode').dataset.state = mode || '';
  $('dev-mode').textContent = mode ? `mode: ${mode}` : 'no samples';
  $('dev-served').textContent = d.served_by ? `served by ${d.served_by}` : 'no controller serves it';

  const s = d.status;
  if (s) {
    const rtt = s.loop_rtt || {};
    rows($('status'), [
      ['samples', s.samples], ['commands', s.commands], ['lost', s.lost],
      ['recovered', s.recovered], ['duplicates', s.duplicates], ['stale', s.stale],
      ['rejected', s.rejected], ['superseded', s.superseded],
      ['off remote control', s.samples_off_remote], ['clamped', s.clamped],
      ['references refused', s.references_refused], ['envelope changes', s.envelope_changes],
      ['runs', s.restarts],
      ['lease holder', s.lease_holder ? `${s.lease_holder} (epoch ${s.lease_epoch})`
        : (s.lease_epoch ? `vacant after epoch ${s.lease_epoch}` : 'none (a plant without leases)')],
      ['lease: refused by the plant / fenced here / claims / yields',
        `${s.lease_refused || 0} / ${s.lease_fenced || 0} / ${s.lease_claims || 0} / ${s.lease_yields || 0}`],
      ['round trip p50 / p99 / max', `${fmt(rtt.p50_us)} / ${fmt(rtt.p99_us)} / ${fmt(rtt.max_us)} µs`],
      ['mode (last flags)', d.status_mode || '–'],
      ['plant time', `${fmt(s.plant_time)} s (seq ${s.last_seq})`],
      ['F estimates', (s.f_est || []).map(fmt).join(', ')],
      ['last error', s.last_error || '–'],
      ['status age', `${fmt(d.status_age)} s`],
    ].map(([k, v]) => [k, String(v)]));
    showCommission(s.commission);
  } else {
    rows($('status'), [['status', d.served_by ? 'waiting for the service' : 'no controller serves it']]);
  }

  const cfg = d.config;
  $('config-error').textContent = d.config_error || '';
  if (cfg) {
    const t = $('config');
    const head = el('tr');
    head.append(el('th', {}, 'channel'), el('th', {}, 'law'), el('th', {}, 'parameters'),
                el('th', {}, 'output limits'), el('th', {}, 'envelope'));
    const trs = cfg.map((c, i) => {
      const tr = el('tr');
      const out = Object.fromEntries(c.output);
      tr.append(el('td', {}, String(i)), el('td', {}, c.law),
                el('td', {}, c.params.filter(([, v]) => v !== 0).map(([k, v]) => `${k} ${fmt(v)}`).join(', ')),
                el('td', {}, limitsText(out)),
                el('td', { 'data-envelope': String(i) }, limitsText(c.envelope)));
      return tr;
    });
    t.replaceChildren(head, ...trs);
    buildForms(cfg);
  }
}

function buildForms(cfg) {
  const shape = JSON.stringify(cfg.map((c) => [c.law, c.params.map(([k]) => k)]));
  const sel = $('gain-channel');
  if (shape !== state.shape) {
    state.shape = shape;
    const keep = sel.value;
    sel.replaceChildren(...cfg.map((_, i) => el('option', { value: String(i) }, String(i))));
    if (keep && Number(keep) < cfg.length) sel.value = keep;
    buildGainFields();
    const box = $('ref-fields');
    box.replaceChildren(...cfg.map((_, i) => {
      const l = el('label', {}, `channel ${i} `);
      l.append(el('input', { type: 'number', step: 'any', name: `ref-${i}`, id: `ref-${i}` }));
      return l;
    }));
    state.refFilled = false;
  }
  updateGainCurrent();
  fillCommissionChannels(cfg.length);
  const now = state.detail.reference_now || [];
  if (!state.refFilled && now.length === cfg.length) {
    now.forEach((v, i) => { $(`ref-${i}`).value = String(Number(v.toPrecision(6))); });
    state.refFilled = true;
  }
}

function buildGainFields() {
  const cfg = state.detail && state.detail.config;
  if (!cfg) return;
  const c = cfg[Number($('gain-channel').value) || 0];
  $('gain-law').textContent = `law: ${c.law}`;
  const head = el('tr');
  head.append(el('th', {}, 'field'), el('th', {}, 'now'), el('th', {}, 'new value'), el('th', {}, 'allowed'));
  const fields = [...c.params, ...c.output];
  const trs = fields.map(([name]) => {
    const tr = el('tr');
    const input = el('input', { type: 'number', step: 'any', name, 'data-field': name });
    let allowed = '';
    if (name === 'min' || name === 'max') {
      allowed = `envelope ${limitsText(c.envelope)}`;
    } else if (name === 'rate_limit' && c.envelope.rate_limit !== null && c.envelope.rate_limit !== undefined) {
      allowed = `≤ ${fmt(c.envelope.rate_limit)}`;
    }
    const td = el('td');
    td.append(input);
    // The field's meaning, unit and sane bounds (the service's table) on hover.
    const help = (c.help && c.help[name]) || '';
    tr.append(el('td', { title: help }, name), el('td', { 'data-now': name }, ''), td, el('td', { class: 'env' }, allowed));
    return tr;
  });
  $('gain-fields').replaceChildren(head, ...trs);
  updateGainCurrent();
}

function updateGainCurrent() {
  const cfg = state.detail && state.detail.config;
  if (!cfg) return;
  const c = cfg[Number($('gain-channel').value) || 0];
  if (!c) return;
  for (const [name, v] of [...c.params, ...c.output]) {
    const td = $('gain-fields').querySelector(`td[data-now="${name}"]`);
    if (td) td.textContent = fmt(v);
  }
}

// ---- the audit trail -----------------------------------------------------------------

function auditWho(e) {
  const notes = [e.role, e.verified ? '' : 'unverified'].filter(Boolean);
  return notes.length ? `${e.operator} (${notes.join(', ')})` : e.operator;
}

async function refreshAudit() {
  const id = state.selected;
  if (!id || !state.me) return;
  let r;
  try { r = await api(`api/devices/${encodeURIComponent(id)}/audit`); } catch (_) { return; }
  if (id !== state.selected) return;
  $('audit-error').textContent = r.ok ? '' : (r.body.reason || r.body.error || `HTTP ${r.status}`);
  if (!r.ok) return;
  const head = el('tr');
  head.append(el('th', {}, 'when (UTC)'), el('th', {}, 'who'), el('th', {}, 'what'),
              el('th', {}, 'changes'), el('th', {}, 'result'));
  const entries = (r.body.entries || []).slice().reverse();
  const trs = entries.map((e) => {
    const tr = el('tr', { 'data-state': e.accepted ? 'accepted' : 'refused', 'data-operator': e.operator });
    const when = new Date(e.unix_ns / 1e6).toISOString().replace('T', ' ').replace('Z', '');
    const changes = (e.changes || []).map((c) => `${c.what}: ${c.old} → ${c.new}`).join('; ');
    tr.append(el('td', {}, when), el('td', {}, auditWho(e)), el('td', {}, e.action),
              el('td', {}, changes || (e.asked ? `asked: ${e.asked}` : '–')),
              el('td', {}, e.accepted ? 'accepted' : `refused: ${e.reason}`));
    return tr;
  });
  $('audit').replaceChildren(head, ...(trs.length ? trs : [el('tr', {}, '')]));
}

function showResult(p, r, what) {
  if (r.ok && r.body.accepted) {
    p.dataset.state = 'accepted';
    p.textContent = `accepted: ${what}`;
  } else {
    p.dataset.state = 'refused';
    const by = r.body.refused_by ? `refused by the ${r.body.refused_by}` : `failed (HTTP ${r.status})`;
    p.textContent = `${by}: ${r.body.reason || r.body.error || 'no reason given'}`;
  }
}

async function submitGains(ev) {
  ev.preventDefault();
  const id = state.selected;
  const channel = Number($('gain-channel').value) || 0;
  const fields = {};
  for (const input of $('gain-fields').querySelectorAll('input[data-field]')) {
    if (input.value.trim() !== '') fields[input.dataset.field] = Number(input.value);
  }
  const p = $('gain-result');
  if (Object.keys(fields).length === 0) {
    p.dataset.state = 'refused';
    p.textContent = 'nothing to change: fill in at least one field';
    return;
  }
  p.dataset.state = 'pending';
  p.textContent = 'sending…';
  let r;
  try {
    r = await api(`api/devices/${encodeURIComponent(id)}/gains`, {
      method: 'POST', headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ channel, fields }),
    });
  } catch (e) { r = { ok: false, status: 0, body: { reason: String(e) } }; }
  const what = `channel ${channel}: ` + Object.entries(fields).map(([k, v]) => `${k} = ${v}`).join(', ');
  showResult(p, r, what);
  if (r.ok) {
    for (const input of $('gain-fields').querySelectorAll('input[data-field]')) input.value = '';
    refreshDetail();
  }
  refreshAudit();
}

async function submitReference(ev) {
  ev.preventDefault();
  const id = state.selected;
  const inputs = [...$('ref-fields').querySelectorAll('input')];
  const p = $('ref-result');
  if (inputs.length === 0 || inputs.some((i) => i.value.trim() === '')) {
    p.dataset.state = 'refused';
    p.textContent = 'give a value for every channel';
    return;
  }
  const values = inputs.map((i) => Number(i.value));
  p.dataset.state = 'pending';
  p.textContent = 'sending…';
  let r;
  try {
    r = await api(`api/devices/${encodeURIComponent(id)}/reference`, {
      method: 'POST', headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ values }),
    });
  } catch (e) { r = { ok: false, status: 0, body: { reason: String(e) } }; }
  showResult(p, r, `reference ${values.map(fmt).join(', ')}`);
  refreshAudit();
}

// ---- commissioning -------------------------------------------------------------------

const PHASES = { 1: 'running', 2: 'proposed', 3: 'applied', 4: 'aborted' };

/// The device's last commissioning run, from its status (or a request's answer).
function showCommission(c) {
  const p = $('com-state');
  if (!c) {
    p.dataset.phase = 'none';
    p.textContent = 'no run';
    return;
  }
  const phase = PHASES[c.phase] || 'unknown';
  p.dataset.phase = phase;
  // A confirmation or an abort names the run shown, never one started since.
  state.commissionRun = c.run || 0;
  const fits = (c.fits || []).map((f) => `order ${f.order}: alpha ${fmt(f.alpha)} (explains ${Math.round(100 * f.explained)} %)`);
  const law = c.proposed && c.proposed.law && c.proposed.law.Intelligent;
  const proposed = law ? [`proposed: alpha ${fmt(law.alpha)}, kp ${fmt(law.kp)}, kd ${fmt(law.kd)}`] : [];
  const parts = [`run ${c.run} on channel ${c.channel}: ${phase}`, `started by ${c.started_by}`,
    `${fmt(c.elapsed)} of ${fmt(c.duration)} s`, `largest deviation ${fmt(c.deviation)}`,
    `alpha before ${fmt(c.alpha_before)}`, ...fits, ...proposed];
  if (c.ended_by) parts.push(`ended by ${c.ended_by}`);
  if (c.reason) parts.push(c.reason);
  p.textContent = parts.join(' · ');
}

function fillCommissionChannels(n) {
  const sel = $('com-channel');
  if (sel.options.length === n) return;
  sel.replaceChildren(...Array.from({ length: n }, (_, i) => el('option', { value: String(i) }, String(i))));
}

async function commission(action) {
  const id = state.selected;
  const p = $('com-result');
  const body = { action, channel: Number($('com-channel').value) || 0, run: state.commissionRun || 0 };
  if (action === 'start') {
    body.amplitude = Number($('com-amplitude').value);
    body.max_deviation = Number($('com-deviation').value);
    body.period = Number($('com-period').value);
    body.cycles = Number($('com-cycles').value);
  }
  p.dataset.state = 'pending';
  p.textContent = 'sending…';
  let r;
  try {
    r = await api(`api/devices/${encodeURIComponent(id)}/commission`, {
      method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
    });
  } catch (e) { r = { ok: false, status: 0, body: { reason: String(e) } }; }
  showResult(p, r, `${action} on channel ${body.channel}`);
  if (r.ok && r.body.commission) showCommission(r.body.commission);
  refreshAudit();
}

// ---- start ---------------------------------------------------------------------------

function every(ms, f) {
  let busy = false;
  const tick = async () => {
    if (busy) return;
    busy = true;
    try { await f(); } finally { busy = false; }
  };
  tick();
  setInterval(tick, ms);
}

window.addEventListener('DOMContentLoaded', async () => {
  $('login-form').addEventListener('submit', submitLogin);
  $('logout').addEventListener('click', logout);
  await checkMe();
  $('gain-form').addEventListener('submit', submitGains);
  $('ref-form').addEventListener('submit', submitReference);
  $('gain-channel').addEventListener('change', buildGainFields);
  $('com-form').addEventListener('submit', (ev) => { ev.preventDefault(); commission('start'); });
  $('com-confirm').addEventListener('click', () => commission('confirm'));
  $('com-abort').addEventListener('click', () => commission('abort'));
  every(LIST_MS, refreshList);
  every(SERIES_MS, refreshSeries);
  every(DETAIL_MS, refreshDetail);
  every(AUDIT_MS, refreshAudit);
});
