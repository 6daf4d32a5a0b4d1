// Shared page state, DOM helpers and the rules that enable or disable controls.

import { api, ApiError } from './api.js';

/** Everything the pages show, kept current by the event stream (see app.js). */
export const state = {
  who: { name: '', role: 'viewer', auth_required: false },
  connected: false,
  machines: new Map(),   // id -> machine row
  status: new Map(),     // id -> latest status
  io: new Map(),         // id -> {inputs, outputs} (absent keys: unsupported)
  runs: new Map(),       // machine id -> {job, run, line, total_lines, percent, started_at, estimated_seconds}
  pendants: [],
};

const RANK = { viewer: 0, operator: 1, admin: 2 };

export function can(role) {
  return (RANK[state.who.role] || 0) >= RANK[role];
}

/** `h('button', {class: 'x', onclick}, 'text', child)`: an element. */
export function h(tag, props, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(props || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'class') el.className = v;
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else if (k === 'text') el.textContent = v;
    else el.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/**
 * Controls say what they need with `data-need`: `operator`/`admin` (a role) or `motion`
 * (operator, and the live stream must be up: never move or change a machine the page cannot
 * watch). STOP, feed hold, jog cancel and pause need only the role. `data-when` adds what the
 * machine must be doing (see `machineBlock`), the machine being the closest
 * `[data-gate-machine]`. A disabled control says why in its title, and a `[data-why-group]`
 * (a card) shows the reasons of its disabled controls in its `.why` line, beside them.
 */
export function gate(root = document) {
  const groups = new Set();
  const within = root.closest ? root.closest('[data-why-group]') : null;
  if (within) groups.add(within);
  for (const el of root.querySelectorAll('[data-need]')) {
    const why = blocked(el);
    const off = !!why;
    if (el.disabled !== off) el.disabled = off;
    const title = why && why !== BUSY ? why : (el.dataset.tip || '');
    if (el.title !== title) el.title = title;
    if (why && why !== BUSY) el.dataset.why = why; else delete el.dataset.why;
    const g = el.closest('[data-why-group]');
    if (g) groups.add(g);
  }
  for (const g of root.querySelectorAll ? root.querySelectorAll('[data-why-group]') : []) groups.add(g);
  for (const g of groups) {
    const line = g.querySelector('.why');
    if (!line) continue;
    const reasons = [...new Set([...g.querySelectorAll('[data-why]')].filter((e) => !e.closest('[hidden]')).map((e) => e.dataset.why))];
    const text = reasons.length ? 'Disabled: ' + reasons.join(' · ') : '';
    if (line.textContent !== text) line.textContent = text;
    line.hidden = !text;
  }
}

const BUSY = 'busy';

/** Why a control cannot act now ('' when it can). */
function blocked(el) {
  const need = el.dataset.need;
  const role = need === 'motion' ? 'operator' : need;
  if (!can(role)) return `needs the ${role} role`;
  if (need === 'motion' && !state.connected) return 'the live connection is lost (positions may be stale)';
  if (el.dataset.busy === '1') return BUSY;
  if (el.dataset.off === '1') return el.dataset.tip || 'not possible now';
  if (el.dataset.when) {
    const host = el.closest('[data-gate-machine]');
    if (host) return machineBlock(+host.dataset.gateMachine, el.dataset.when, el.dataset.toolChange === 'ok');
  }
  return '';
}

const MOVING = ['jogging', 'homing', 'running', 'paused', 'probing'];

/**
 * What a machine's state forbids, as the server refuses it (so the page disables it first):
 * `no-run`: motion a running job forbids (jog, MDI, home, probing; a tool-change hold allows
 * jogs and probes when `toolChange`); `still`: offset and part-zero changes, which wait until
 * the machine stands still; `not-cutting`: spindle and coolant while a job cuts.
 */
export function machineBlock(id, when, toolChange) {
  const s = state.status.get(id) || {};
  const st = s.state || (state.machines.get(id) || {}).state;
  if (st === 'offline' || st === 'unresponsive') return `the machine is ${st}`;
  const run = state.runs.get(id) || s.job;
  const inToolChange = !!s.hold && s.hold.kind === 'tool_change' && (st === 'paused' || st === 'jogging');
  const job = run ? `job ${run.job} ` : 'a job ';
  if (when === 'no-run') {
    if (run && !(toolChange && inToolChange)) return job + (st === 'paused' ? 'is paused on this machine' : 'is running on this machine');
  } else if (when === 'still') {
    if (MOVING.includes(st) && !(st === 'paused' && inToolChange)) return `the machine is ${st}: wait until it stands still`;
  } else if (when === 'not-cutting') {
    if (run && st === 'running') return job + 'is cutting: pause it first';
  }
  return '';
}

export function toast(message, kind = 'error') {
  const box = document.getElementById('toasts');
  // A few at a time: they tell what just happened, and must not pile up over the page.
  while (box.childElementCount >= 3) box.firstChild.remove();
  const el = h('div', { class: 'toast ' + kind, role: kind === 'error' ? 'alert' : 'status' }, message);
  box.append(el);
  setTimeout(() => el.remove(), kind === 'error' ? 8000 : 3000);
}

export function errorText(e) {
  return e instanceof ApiError ? `${e.message} (${e.code})` : String(e && e.message || e);
}

/** Runs an API call for a button: disables it while in flight, shows errors. */
export async function act(button, fn, okMessage) {
  if (button) { button.dataset.busy = '1'; gate(button.parentNode || document); }
  try {
    const r = await fn();
    if (okMessage) toast(okMessage, 'ok');
    return r;
  } catch (e) {
    toast(errorText(e));
    throw e;
  } finally {
    if (button) { delete button.dataset.busy; gate(button.parentNode || document); }
  }
}

export function mm(v) {
  return typeof v === 'number' && isFinite(v) ? v.toFixed(3) : '—';
}

// --- Display units and number formats (issue 27) ------------------------------------------------
// Positions at the display's resolution: 0.001 mm or 0.0001 in (the switch in the header, kept
// in this browser). The API is always mm; only what is shown changes.

const UNITS_KEY = 'fresa.units';

export const display = { units: localStorage.getItem(UNITS_KEY) === 'in' ? 'in' : 'mm' };

export function setUnits(u) {
  display.units = u === 'in' ? 'in' : 'mm';
  localStorage.setItem(UNITS_KEY, display.units);
  document.dispatchEvent(new CustomEvent('fresa:units'));
}

/** A position in mm, shown in the display units at their resolution. */
export function coord(v) {
  if (typeof v !== 'number' || !isFinite(v)) return '—';
  return display.units === 'in' ? (v / 25.4).toFixed(4) : v.toFixed(3);
}

/** `n` with `digits` decimals and thousands grouped (1,234.5). */
export function fixed(n, digits = 0) {
  if (typeof n !== 'number' || !isFinite(n)) return '—';
  return n.toLocaleString('en-US', { minimumFractionDigits: digits, maximumFractionDigits: digits });
}

/** A length in mm in the display units: 609.6 mm, 12,345.6 mm, 199,999 m; 24.000 in. */
export function length(v) {
  if (typeof v !== 'number' || !isFinite(v)) return '—';
  if (display.units === 'in') return Math.abs(v) >= 12000 ? fixed(v / 304.8, 0) + ' ft' : fixed(v / 25.4, 2) + ' in';
  return Math.abs(v) >= 100000 ? fixed(v / 1000, 0) + ' m' : fixed(v, 1) + ' mm';
}

/** A feed in mm/min in the display units: 610 mm/min, 24.0 in/min. */
export function feed(v) {
  if (typeof v !== 'number' || !isFinite(v)) return '—';
  return display.units === 'in' ? fixed(v / 25.4, 1) + ' in/min' : fixed(v, 0) + ' mm/min';
}

/** A percentage as the server rounds it: 28 %, 28.5 %. */
export function percent(v) {
  if (typeof v !== 'number' || !isFinite(v)) return '—';
  return (Number.isInteger(v) ? String(v) : v.toFixed(1)) + ' %';
}

export function duration(s) {
  if (!isFinite(s) || s < 0) return '—';
  s = Math.round(s);
  const hh = Math.floor(s / 3600), m = Math.floor(s / 60) % 60, ss = s % 60;
  return (hh ? hh + ':' + String(m).padStart(2, '0') : m) + ':' + String(ss).padStart(2, '0');
}

export function time(ms) {
  return new Date(ms).toLocaleString();
}

/** A G-code line/column from a server message ("line 3, column 7" or "column 7"). */
export function position(message) {
  const lc = /line (\d+), column (\d+)/.exec(message || '');
  if (lc) return { line: +lc[1], column: +lc[2] };
  const c = /column (\d+)/.exec(message || '');
  return c ? { line: 1, column: +c[1] } : null;
}

/** A modal dialog; resolves with the value of the button pressed. */
export function dialog(title, body, buttons) {
  const d = document.getElementById('dialog');
  d.replaceChildren(h('h2', {}, title), body,
    h('div', { class: 'row end' }, buttons.map(([label, value, cls]) =>
      h('button', { class: cls || '', value, onclick: () => d.close(value) }, label))));
  d.returnValue = '';
  d.showModal();
  return new Promise((resolve) => d.addEventListener('close', () => resolve(d.returnValue), { once: true }));
}

export function machineName(id) {
  const m = state.machines.get(id);
  return m ? m.name : (id === null || id === undefined ? '—' : '#' + id);
}

/** Machine I/O lamps: a key present is supported, null is unknown (grey), absent is hidden. */
export function ioLamps(machine) {
  const io = state.io.get(machine) || {};
  const box = h('div', { class: 'lamps' });
  for (const [group, map] of [['in', io.inputs], ['out', io.outputs]]) {
    if (!map || typeof map !== 'object') continue;
    for (const [name, v] of Object.entries(map)) {
      const cls = v === null ? 'unknown' : v === false || v === 0 ? 'off' : 'on';
      const label = typeof v === 'number' ? `${name} ${v}` : name;
      box.append(h('span', { class: `lamp ${cls} ${group}`, title: `${group}put ${name}: ${v === null ? 'unknown' : v}` }, label));
    }
  }
  return box.childElementCount ? box : null;
}

/** Loads the machine list and every machine's status. */
export async function loadMachines() {
  const rows = await api('GET', '/machines');
  state.machines = new Map(rows.map((m) => [m.id, m]));
  await Promise.all(rows.map(async (m) => {
    try {
      const s = await api('GET', `/machines/${m.id}/status`);
      state.status.set(m.id, s);
      applyIo(m.id, s);
      if (s.job) await trackRun(m.id, s.job);
      else state.runs.delete(m.id);
    } catch (_) { /* an offline machine has no status; its row says why */ }
  }));
}

export function applyIo(machine, data) {
  if (!data) return;
  if (!('inputs' in data) && !('outputs' in data)) return;
  const cur = state.io.get(machine) || {};
  if ('inputs' in data) cur.inputs = data.inputs;
  if ('outputs' in data) cur.outputs = data.outputs;
  state.io.set(machine, cur);
}

const jobCache = new Map();

export async function job(id) {
  if (!jobCache.has(id)) jobCache.set(id, api('GET', `/jobs/${id}`).catch((e) => { jobCache.delete(id); throw e; }));
  return jobCache.get(id);
}

/** Notes a machine's running job (from status or progress) with what elapsed/remaining need. */
export async function trackRun(machine, p) {
  const cur = state.runs.get(machine) || {};
  const next = Object.assign({}, cur, p);
  if (p.job !== undefined && p.job !== cur.job) {
    try {
      const j = await job(p.job);
      next.name = j.name;
      next.total_lines = next.total_lines || j.line_count;
      next.estimated_seconds = j.analysis ? j.analysis.estimated_seconds : null;
      next.started_at = j.run && j.run.started_at;
    } catch (_) { /* shown without name */ }
  }
  state.runs.set(machine, next);
}

export function forgetJob(id) {
  jobCache.delete(id);
}
