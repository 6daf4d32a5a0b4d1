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
 * (operator, and the live stream must be up: never move a machine the page cannot watch).
 * STOP and feed hold need only the role.
 */
export function gate(root = document) {
  for (const el of root.querySelectorAll('[data-need]')) {
    const need = el.dataset.need;
    let ok = need === 'motion' ? can('operator') && state.connected : can(need);
    // `data-off`: not possible in the current state (e.g. pausing a finished job).
    if (ok && (el.dataset.busy === '1' || el.dataset.off === '1')) ok = false;
    el.disabled = !ok;
    el.title = ok || el.dataset.off === '1' ? (el.dataset.tip || '') :
      !can(need === 'motion' ? 'operator' : need) ? `needs the ${need === 'motion' ? 'operator' : need} role` :
        'the live connection is lost: motion is disabled until it is back';
  }
}

export function toast(message, kind = 'error') {
  const box = document.getElementById('toasts');
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
  return typeof v === 'number' ? v.toFixed(3) : '—';
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
