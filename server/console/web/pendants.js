// Pendants: connection state, binding, M1-M4 macros (the server validates them), and the
// pendants announced on the LAN with one-click add.

import { api } from './api.js';
import { state, h, gate, act, toast, errorText, machineName, can } from './ui.js';

const COMMANDS = ['feed_hold', 'cycle_start', 'resume', 'stop', 'reset', 'home', 'zero', 'go_to_zero'];
const AXES = ['X', 'Y', 'Z', 'A'];

/** One macro slot's editor: type and its fields; `value()` is the action or null. */
function macroEditor(pid, slot, action) {
  const type = h('select', { 'aria-label': `${slot} type`, dataset: { macroType: slot } },
    ['none', 'command', 'jog', 'toggle', 'mdi'].map((t) => h('option', { value: t, selected: (action ? action.type : 'none') === t }, t)));
  const fields = h('span', { class: 'row wrap' });
  const err = h('div', { class: 'error', dataset: { macroError: slot } });
  let read = () => null;
  const draw = () => {
    const t = type.value;
    const a = action && action.type === t ? action : {};
    if (t === 'command') {
      const c = h('select', { 'aria-label': `${slot} command` }, COMMANDS.map((x) => h('option', { selected: a.command === x }, x)));
      const ax = h('select', { 'aria-label': `${slot} axis` }, h('option', { value: '' }, 'all'), AXES.map((x) => h('option', { selected: a.axis === x }, x)));
      fields.replaceChildren(c, ax);
      read = () => Object.assign({ type: 'command', command: c.value }, ax.value && ['zero', 'home'].includes(c.value) ? { axis: ax.value } : {});
    } else if (t === 'jog') {
      const ax = h('select', { 'aria-label': `${slot} axis` }, AXES.map((x) => h('option', { selected: a.axis === x }, x)));
      const d = h('input', { type: 'number', step: 'any', value: a.distance ?? 1, 'aria-label': `${slot} distance` });
      fields.replaceChildren(ax, d, 'mm');
      read = () => ({ type: 'jog', axis: ax.value, distance: parseFloat(d.value) });
    } else if (t === 'toggle') {
      const o = h('select', { 'aria-label': `${slot} output` }, ['spindle', 'coolant', 'z_lift'].map((x) => h('option', { selected: a.output === x }, x)));
      fields.replaceChildren(o);
      read = () => ({ type: 'toggle', output: o.value });
    } else if (t === 'mdi') {
      const l = h('input', { type: 'text', value: a.line || '', placeholder: 'G91 G0 Z5', 'aria-label': `${slot} MDI line`, dataset: { macroLine: slot } });
      fields.replaceChildren(l);
      read = () => ({ type: 'mdi', line: l.value });
    } else {
      fields.replaceChildren();
      read = () => null;
    }
  };
  type.addEventListener('change', draw);
  draw();
  const save = h('button', { dataset: { need: 'operator', macroSave: slot }, onclick: async (ev) => {
    err.textContent = '';
    try {
      await act(ev.currentTarget, () => api('PATCH', `/pendants/${pid}`, { macros: { [slot]: read() } }), `${slot} saved`);
      err.replaceChildren(h('span', { class: 'ok', dataset: { macroSaved: slot } }, 'saved'));
    } catch (e) { err.textContent = errorText(e); }
  } }, 'Save');
  return h('div', { class: 'macro row wrap', dataset: { macro: slot } }, h('strong', {}, slot), type, fields, save, err);
}

/** What the pendant's "Set cero" leaves Z reading: its touch plate's thickness, or 0. */
function plate(p) {
  const mm = (p.config || {}).touch_plate_mm;
  return mm > 0 ? `Touch plate ${mm} mm: Set cero leaves Z reading ${mm}`
    : 'No touch plate set (config.touch_plate_mm): Set cero leaves Z reading 0';
}

function pendantCard(p) {
  const sel = h('select', { 'aria-label': 'machine', dataset: { bindSelect: p.id } },
    h('option', { value: '' }, '— unbound —'),
    [...state.machines.values()].map((m) => h('option', { value: m.id, selected: p.machine === m.id }, m.name)));
  const bind = h('button', { dataset: { need: 'operator', bind: p.id }, onclick: (ev) => {
    const machine = sel.value === '' ? null : +sel.value;
    act(ev.currentTarget, () => api('PATCH', `/pendants/${p.id}`, { machine }), machine === null ? 'Unbound' : `Bound to ${machineName(machine)}`).catch(() => {});
  } }, 'Bind');
  const del = can('admin') ? h('button', { class: 'danger', dataset: { need: 'admin' }, onclick: (ev) =>
    act(ev.currentTarget, () => api('DELETE', `/pendants/${p.id}`), 'Deleted').catch(() => {}) }, 'Delete') : null;
  return h('section', { class: 'card', dataset: { pendant: p.id } },
    h('div', { class: 'row between' }, h('h2', {}, p.name),
      h('span', { class: 'badge ' + (p.connected ? 'ok' : 'lost'), dataset: { conn: p.id } }, p.connected ? 'connected' : 'not connected')),
    h('p', { class: 'muted' }, `${p.address} · dialect ${p.dialect}` + (p.reason ? ` · ${p.reason}` : '')),
    h('p', { dataset: { touchPlate: p.id } }, plate(p)),
    h('div', { class: 'row wrap' }, h('span', {}, 'Bound to ', h('strong', { dataset: { boundTo: p.id } }, machineName(p.machine))), sel, bind, del),
    h('h3', {}, 'Macros'),
    ['M1', 'M2', 'M3', 'M4'].map((slot) => macroEditor(p.id, slot, (p.macros || {})[slot])));
}

export async function pendantsPage(page, _params, events) {
  const list = h('div', { class: 'grid' });
  const discovered = h('tbody');
  const drawList = () => {
    list.replaceChildren(...(state.pendants.length ? state.pendants.map(pendantCard) : [h('p', { class: 'muted' }, 'No pendants yet.')]));
    gate(list);
  };
  const boundOnly = () => {
    // Keep editors (and what is typed in them) when only connection or binding changed.
    for (const p of state.pendants) {
      const b = list.querySelector(`[data-bound-to="${p.id}"]`);
      const c = list.querySelector(`[data-conn="${p.id}"]`);
      if (!b || !c) return drawList();
      b.textContent = machineName(p.machine);
      c.textContent = p.connected ? 'connected' : 'not connected';
      c.className = 'badge ' + (p.connected ? 'ok' : 'lost');
    }
    if (list.querySelectorAll('[data-pendant]').length !== state.pendants.length) drawList();
  };
  const loadDiscovered = async () => {
    try {
      const d = await api('GET', '/pendants/discovered');
      discovered.replaceChildren(...(d.pendants.length ? d.pendants.map((x) => h('tr', {},
        h('td', {}, x.name), h('td', {}, x.address), h('td', {}, (x.addresses || []).join(', ')),
        h('td', {}, x.pendant ? `added (#${x.pendant})` : h('button', { dataset: { need: 'admin' }, onclick: (ev) =>
          act(ev.currentTarget, () => api('POST', '/pendants', { name: x.name, address: x.address }), `${x.name} added`).then(loadDiscovered).catch(() => {}) }, 'Add'))))
        : [h('tr', {}, h('td', { colspan: 4, class: 'muted' }, 'none announced on the LAN (browsing starts on the first look; refresh in a second or two)'))]));
      gate(discovered);
    } catch (e) {
      discovered.replaceChildren(h('tr', {}, h('td', { colspan: 4, class: 'error' }, errorText(e))));
    }
  };
  const name = h('input', { type: 'text', placeholder: 'bench-1', 'aria-label': 'name', required: true });
  const address = h('input', { type: 'text', placeholder: 'MPG000001.local:8001', 'aria-label': 'address', required: true });
  const dialect = h('select', { 'aria-label': 'dialect' }, h('option', {}, 'firmware'), h('option', {}, 'document'));
  const add = h('form', { class: 'row wrap' }, name, address, dialect, h('button', { type: 'submit', dataset: { need: 'admin' } }, 'Add pendant'));
  add.addEventListener('submit', (ev) => {
    ev.preventDefault();
    act(null, () => api('POST', '/pendants', { name: name.value, address: address.value, dialect: dialect.value }), 'Pendant added').catch(() => {});
  });
  page.append(h('h1', {}, 'Pendants'), list,
    h('section', { class: 'card' }, h('div', { class: 'row between' }, h('h2', {}, 'Discovered on the LAN'),
      h('button', { onclick: loadDiscovered }, 'Refresh')),
      h('table', {}, h('thead', {}, h('tr', {}, ['name', 'address', 'addresses', ''].map((t) => h('th', {}, t)))), discovered)),
    h('section', { class: 'card' }, h('h2', {}, 'Add by address'), add));
  drawList();
  loadDiscovered();
  gate(page);
  const offs = [events.on('pendants', boundOnly), events.on('reloaded', drawList)];
  return () => offs.forEach((f) => f());
}
