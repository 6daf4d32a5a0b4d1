// The audit log: history replayed from the persisted log, then live, filtered by machine and
// type (the server filters).

import { eventStream, EVENT_TYPES } from './api.js';
import { state, h, time, machineName } from './ui.js';

const MAX_ROWS = 500;

export async function eventsPage(page) {
  const machine = h('select', { id: 'events-machine', 'aria-label': 'machine' }, h('option', { value: '' }, 'all machines'),
    [...state.machines.values()].map((m) => h('option', { value: m.id }, m.name)));
  const types = h('input', { id: 'events-types', type: 'text', value: 'job,machine,pendant', 'aria-label': 'event types',
    title: 'comma-separated; "job" matches job.*' });
  const live = h('span', { class: 'badge' });
  const tbody = h('tbody');
  let es = null;
  const open = () => {
    if (es) es.close();
    tbody.replaceChildren();
    const q = { after: '0' };
    if (machine.value) q.machine = machine.value;
    if (types.value.trim()) q.types = types.value.trim();
    es = eventStream(q, EVENT_TYPES, (e) => {
      if (e.type === 'status') return;
      const row = h('tr', { dataset: { type: e.type } }, h('td', { class: 'num' }, e.id ?? ''), h('td', {}, time(e.time)),
        h('td', {}, e.type), h('td', {}, e.machine ? machineName(e.machine) : ''), h('td', {}, e.actor || ''),
        h('td', { class: 'data' }, JSON.stringify(e.data)));
      tbody.prepend(row);
      while (tbody.childElementCount > MAX_ROWS) tbody.lastChild.remove();
    }, (ok) => { live.textContent = ok ? 'live' : 'reconnecting…'; live.className = 'badge ' + (ok ? 'ok' : 'lost'); });
  };
  const form = h('form', { class: 'row wrap' }, machine, types, h('button', { type: 'submit' }, 'Apply'), live);
  form.addEventListener('submit', (ev) => { ev.preventDefault(); open(); });
  page.append(h('h1', {}, 'Events'), h('section', { class: 'card' }, form,
    h('table', { class: 'events' }, h('thead', {}, h('tr', {}, ['#', 'when', 'type', 'machine', 'who', 'data'].map((t) => h('th', {}, t)))), tbody)));
  open();
  return () => { if (es) es.close(); };
}
