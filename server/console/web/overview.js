// The workshop at a glance: a card per machine, updated in place from the event stream.

import { api } from './api.js';
import { state, h, gate, coord, duration, act, ioLamps, fixed } from './ui.js';

const AXES = ['x', 'y', 'z', 'a'];

/** STOP and feed hold: on every machine view, sent at once, never waiting for anything else. */
export function urgentButtons(id) {
  const send = (command) => (ev) => act(null, () => api('POST', `/machines/${id}/commands`, { command }),
    command === 'stop' ? 'STOP sent' : 'Feed hold sent');
  return [
    h('button', { class: 'stop', dataset: { need: 'operator', cmd: 'stop' }, onclick: send('stop') }, 'STOP'),
    h('button', { class: 'hold', dataset: { need: 'operator', cmd: 'feed_hold' }, onclick: send('feed_hold') }, 'Feed hold'),
  ];
}

export function stateBadge(state, reason) {
  return h('span', { class: 'badge state-' + (state || 'unknown') }, state || 'unknown', reason ? ' — ' + reason : '');
}

/** A progress block for a machine's running job; `refs.update()` refreshes it. */
export function runBlock(id) {
  const bar = h('progress', { max: 100, value: 0 });
  const label = h('span', { class: 'run-label' });
  const times = h('span', { class: 'muted' });
  const el = h('div', { class: 'run', hidden: true }, label, bar, times);
  return {
    el,
    update() {
      const r = state.runs.get(id);
      el.hidden = !r;
      if (!r) return;
      const total = r.total_lines || 0;
      const pct = r.percent !== undefined ? r.percent : total ? (100 * (r.line || 0)) / total : 0;
      bar.value = pct;
      label.textContent = `${r.name || 'job ' + r.job} — ${pct.toFixed(1)} % · line ${fixed(r.line || 0)}/${fixed(total)}` +
        (r.state === 'paused' ? ' · paused' : '');
      const elapsed = r.started_at ? (Date.now() - r.started_at) / 1000 : NaN;
      // The server's time left by line (with the machine's acceleration and the overrides in
      // force); a share of the whole estimate only for a job without one.
      const remaining = typeof r.remaining_s === 'number' ? r.remaining_s
        : r.estimated_seconds ? r.estimated_seconds * (1 - pct / 100) : NaN;
      times.textContent = `elapsed ${duration(elapsed)} · remaining ≈ ${duration(remaining)}`;
    },
  };
}

function card(m) {
  const pos = {};
  const table = h('table', { class: 'pos' },
    h('tr', {}, h('th', {}, ''), AXES.map((a) => h('th', {}, a.toUpperCase()))),
    ['work', 'machine'].map((kind) => h('tr', {}, h('th', {}, kind === 'work' ? 'WPos' : 'MPos'),
      AXES.map((a) => (pos[kind + a] = h('td', { class: 'num', dataset: { axis: a, kind } }, '—'))))));
  const badge = h('span');
  const offset = h('span', { class: 'muted' });
  const pendants = h('div', { class: 'pendants-line' });
  const lamps = h('div');
  const run = runBlock(m.id);
  const el = h('section', { class: 'card machine-card', dataset: { machine: m.id } },
    h('div', { class: 'row between' },
      h('h2', {}, h('a', { href: `#/machines/${m.id}` }, m.name)),
      h('span', { class: 'muted' }, m.backend)),
    h('div', { class: 'row' }, badge, offset), table, run.el, lamps, pendants,
    h('div', { class: 'row' }, urgentButtons(m.id), h('a', { class: 'button', href: `#/machines/${m.id}` }, 'Open')));
  return {
    el,
    update() {
      const s = state.status.get(m.id) || {};
      const row = state.machines.get(m.id) || m;
      badge.replaceChildren(stateBadge(s.state || row.state, row.reason || s.reason || s.alarm));
      offset.textContent = s.active_offset ? 'offset ' + s.active_offset : '';
      for (const kind of ['work', 'machine']) {
        const p = s[kind + '_position'] || {};
        for (const a of AXES) pos[kind + a].textContent = coord(p[a]);
      }
      run.update();
      const l = ioLamps(m.id);
      lamps.replaceChildren(...(l ? [l] : []));
      const bound = state.pendants.filter((p) => p.machine === m.id);
      pendants.replaceChildren(...bound.map((p) =>
        h('span', { class: 'badge ' + (p.connected ? 'ok' : 'lost') }, `⌁ ${p.name} ${p.connected ? 'connected' : 'lost'}`)));
    },
  };
}

export async function overview(page, _params, events) {
  const grid = h('div', { class: 'grid' });
  page.append(h('h1', {}, 'Workshop'), grid);
  let cards = new Map();
  const build = () => {
    cards = new Map();
    grid.replaceChildren();
    if (!state.machines.size) grid.append(h('p', { class: 'muted' }, 'No machines yet: add one with POST /api/v1/machines or fresa machine add.'));
    for (const m of state.machines.values()) {
      const c = card(m);
      cards.set(m.id, c);
      grid.append(c.el);
      c.update();
    }
    gate(grid);
  };
  build();
  // Many status events per second for many machines: repaint each dirty card once a frame.
  const dirty = new Set();
  let frame = 0;
  const mark = (id) => {
    if (id === undefined) for (const k of cards.keys()) dirty.add(k); else dirty.add(id);
    if (!frame) frame = requestAnimationFrame(() => {
      frame = 0;
      for (const k of dirty) { const c = cards.get(k); if (c) c.update(); }
      dirty.clear();
    });
  };
  const offs = [
    events.on('status', (e) => mark(e.machine)),
    events.on('machine.state', (e) => mark(e.machine)),
    events.on('machine.io', (e) => mark(e.machine)),
    events.on('runs', () => mark()),
    events.on('pendants', () => mark()),
    events.on('reloaded', () => build()),
  ];
  const tick = setInterval(() => mark(), 1000); // elapsed/remaining clocks
  const onUnits = () => mark();
  document.addEventListener('fresa:units', onUnits);
  return () => { offs.forEach((f) => f()); clearInterval(tick); cancelAnimationFrame(frame); document.removeEventListener('fresa:units', onUnits); };
}
