// The console's entry: sign-in when the server needs a token, the event stream that keeps
// `state` current, and the hash router (#/, #/machines/1, #/jobs, ...).

import { api, ApiError, Events, EVENT_TYPES, setToken, token } from './api.js';
import { state, h, gate, toast, loadMachines, applyIo, trackRun, forgetJob, errorText } from './ui.js';
import { overview } from './overview.js';
import { machinePage } from './machine.js';
import { jobsPage } from './jobs.js';
import { pendantsPage } from './pendants.js';
import { eventsPage } from './events.js';
import { pluginsPage } from './plugins.js';
import { heightMapPage } from './heightmap.js';
import { initPrefs } from './prefs.js';

export const events = new Events();

let cleanup = null;
let rendering = 0;

function route() {
  const parts = (location.hash.replace(/^#\/?/, '') || '').split('/').filter(Boolean);
  if (parts[0] === 'machines' && parts[1] && parts[2] === 'height-maps') return ['heightmaps', { id: +parts[1] }];
  if (parts[0] === 'machines' && parts[1]) return ['machine', { id: +parts[1] }];
  if (['jobs', 'pendants', 'events', 'plugins'].includes(parts[0])) {
    return [parts[0], { job: parts[1] ? +parts[1] : null }];
  }
  return ['overview', {}];
}

const PAGES = { overview, machine: machinePage, jobs: jobsPage, pendants: pendantsPage, events: eventsPage, plugins: pluginsPage, heightmaps: heightMapPage };

async function render() {
  const my = ++rendering;
  if (cleanup) { try { cleanup(); } catch (_) { /* page gone */ } cleanup = null; }
  const [name, params] = route();
  for (const a of document.querySelectorAll('[data-nav]')) {
    a.classList.toggle('active', a.dataset.nav === name || (['machine', 'heightmaps'].includes(name) && a.dataset.nav === 'overview'));
  }
  const view = document.getElementById('view');
  const page = h('div', { class: 'page', dataset: { page: name } });
  try {
    const c = await PAGES[name](page, params, events);
    if (my !== rendering) { if (c) c(); return; }
    cleanup = c || null;
    view.replaceChildren(page);
    gate(view);
  } catch (e) {
    if (my !== rendering) return;
    if (e instanceof ApiError && (e.status === 401)) return signIn(e.message);
    view.replaceChildren(h('p', { class: 'error' }, errorText(e)));
  }
}

function showConnection(connected) {
  state.connected = connected;
  const banner = document.getElementById('conn');
  banner.hidden = connected;
  banner.textContent = connected ? '' :
    'Live connection to the server lost — positions may be stale, and every control that moves or changes a machine is disabled until it is back (STOP and feed hold still work).';
  document.body.classList.toggle('offline', !connected);
  gate(document);
}

function signIn(message) {
  events.stop();
  const input = h('input', { type: 'password', name: 'token', autocomplete: 'current-password', placeholder: 'fresa_…', required: true, id: 'token' });
  const err = h('p', { class: 'error', id: 'signin-error' }, message && token() ? message : '');
  const form = h('form', { class: 'card signin', id: 'signin' },
    h('h1', {}, 'Sign in'),
    h('p', {}, 'This server is reachable from the network, so every request needs an API token. ' +
      'Create one on the server host with ', h('code', {}, 'fresa token create --role operator --name NAME'), '.'),
    h('label', { for: 'token' }, 'Token'), input, err,
    h('button', { type: 'submit', class: 'primary' }, 'Sign in'));
  form.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    setToken(input.value.trim());
    try {
      await start();
    } catch (e) {
      setToken('');
      err.textContent = errorText(e);
    }
  });
  document.getElementById('who').textContent = '';
  document.getElementById('view').replaceChildren(form);
  input.focus();
}

async function start() {
  const who = await api('GET', '/whoami');
  state.who = who;
  const whoEl = document.getElementById('who');
  whoEl.replaceChildren(h('span', { class: 'role ' + who.role, id: 'role' }, `${who.name} · ${who.role}`));
  if (who.auth_required) whoEl.append(h('button', { class: 'link', onclick: () => { setToken(''); location.reload(); } }, 'Sign out'));
  document.body.dataset.role = who.role;
  await loadMachines();
  state.pendants = await api('GET', '/pendants');
  events.start(EVENT_TYPES);
  await render();
}

function wire() {
  events.onConnection(async (c) => {
    showConnection(c);
    if (c) {
      // Back after a gap: what was missed is reloaded, not guessed.
      try { await loadMachines(); state.pendants = await api('GET', '/pendants'); } catch (_) { /* retried next time */ }
      events.dispatch('reloaded', '{}');
    }
  });
  events.on('status', (e) => {
    // A status event is the whole status: fields it leaves out (alarm, reason, run) are gone,
    // not kept from the last one. Only the job summary from GET .../status is carried over.
    const cur = state.status.get(e.machine) || {};
    const next = Object.assign({}, e.data);
    if (cur.job && !('job' in next) && next.run !== undefined) next.job = cur.job;
    state.status.set(e.machine, next);
    applyIo(e.machine, e.data);
    const r = state.runs.get(e.machine);
    if (r && e.data.line !== undefined) r.line = Math.max(r.line || 0, e.data.line);
    // The server's time left (its estimate by line, under the overrides in force).
    if (r && e.data.job && e.data.job.job === r.job && 'remaining_s' in e.data.job) r.remaining_s = e.data.job.remaining_s;
  });
  events.on('machine.io', (e) => applyIo(e.machine, e.data));
  events.on('machine.state', (e) => {
    const m = state.machines.get(e.machine);
    if (m) m.state = e.data.to;
    const s = state.status.get(e.machine);
    if (s) {
      s.state = e.data.to;
      if (e.data.to !== 'alarm') delete s.alarm;
    }
  });
  events.on('job.progress', async (e) => { await trackRun(e.machine, e.data); events.dispatch('runs', '{}'); });
  events.on('job.state', async (e) => {
    forgetJob(e.data.job);
    if (e.data.state === 'running' || e.data.state === 'paused') {
      await trackRun(e.machine, { job: e.data.job, run: e.data.run, line: e.data.line, state: e.data.state });
    } else {
      const r = state.runs.get(e.machine);
      if (r && r.job === e.data.job) state.runs.delete(e.machine);
    }
    events.dispatch('runs', '{}');
  });
  events.on('machine.created', async () => {
    try { await loadMachines(); } catch (_) { return; }
    events.dispatch('reloaded', '{}');
  });
  for (const t of ['pendant.created', 'pendant.connected', 'pendant.lost', 'pendant.bound', 'pendant.macro', 'pendant.deleted']) {
    events.on(t, async () => { try { state.pendants = await api('GET', '/pendants'); } catch (_) { /* next */ } events.dispatch('pendants', '{}'); });
  }
  window.addEventListener('hashchange', render);
}

initPrefs();
wire();
showConnection(false);
start().catch((e) => {
  if (e instanceof ApiError && e.status === 401) signIn(e.message);
  else document.getElementById('view').replaceChildren(h('p', { class: 'error' }, errorText(e)));
});
