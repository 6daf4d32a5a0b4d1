// The audit log: history replayed from the persisted log, then live, filtered by machine and
// type (the server filters), each event as a sentence with who did it ("local cancelled job 4
// at line 1,839, 28 %"); the raw data is the sentence's tooltip.

import { eventStream, EVENT_TYPES } from './api.js';
import { state, h, time, machineName, coord, fixed, display, job as jobInfo } from './ui.js';

const MAX_ROWS = 500;

const AXES = ['x', 'y', 'z', 'a'];

/** "X 1.000 Y 2.000 Z 0.000" in the display units (axes present only). */
function point(p) {
  if (!p || typeof p !== 'object') return '';
  return AXES.filter((a) => typeof p[a] === 'number').map((a) => `${a.toUpperCase()} ${coord(p[a])}`).join(' ') + ` ${display.units}`;
}

function signed(v) {
  return (v > 0 ? '+' : '') + coord(v);
}

/** The rest of an event's data as "key value" pairs, for types without their own sentence. */
function rest(d) {
  return Object.entries(d || {}).filter(([, v]) => v !== null && typeof v !== 'object')
    .map(([k, v]) => `${k.replace(/_/g, ' ')} ${v}`).join(', ').slice(0, 200);
}

const COMMANDS = {
  stop: 'sent STOP', feed_hold: 'sent a feed hold', reset: 'reset the machine', cycle_start: 'pressed cycle start',
  resume: 'resumed the machine', home: 'homed', go_to_zero: 'sent the machine to zero',
};

/** The event `e` in words; `total` is the job's line count when known (for a percentage). */
export function sentence(e, total) {
  const d = e.data || {};
  const who = e.actor || '';
  const by = (s) => (who ? `${who} ${s}` : s.charAt(0).toUpperCase() + s.slice(1));
  const at = (line) => {
    if (!line) return '';
    const pct = total ? `, ${Math.round((100 * line) / total)} %` : '';
    return ` at line ${fixed(line)}${pct}`;
  };
  switch (e.type) {
    case 'job.created':
      return by(`uploaded job ${d.job} "${d.name}" (${fixed(d.lines)} lines)`);
    case 'job.state': {
      const j = `job ${d.job}`;
      switch (d.state) {
        case 'running': return by(d.line ? `resumed ${j}${at(d.line)}` : `started ${j}`);
        case 'paused': {
          const hold = d.hold;
          const programmed = hold && ['program_pause', 'optional_stop', 'tool_change'].includes(hold.kind);
          const why = hold && hold.message ? `: ${hold.message}` : '';
          if (programmed || !who) return `${j} paused${at(d.line)}${why}`;
          return by(`paused ${j}${at(d.line)}`);
        }
        case 'cancelled': return by(`cancelled ${j}${at(d.line)}`);
        case 'completed': return `${j} completed` + (d.line ? ` (${fixed(d.line)} lines)` : '');
        case 'failed': return `${j} failed${at(d.line)}` + (d.message ? `: ${d.message}` : '');
        case 'interrupted': return `${j} was interrupted${at(d.line)}` + (d.message ? `: ${d.message}` : '');
        default: return `${j} ${d.state}${at(d.line)}`;
      }
    }
    case 'job.progress':
      return `job ${d.job}${at(d.line)}`;
    case 'machine.jog':
      if (d.continuous || d.direction) return by(`jogged ${d.axis}${d.direction || ''} while held`);
      return by(`jogged ${d.axis} ${typeof d.distance === 'number' ? signed(d.distance) + ' ' + display.units : ''}`.trim());
    case 'machine.jog_cancel':
      return by('cancelled the jog');
    case 'machine.mdi':
      return by(`sent MDI "${d.line}"`);
    case 'machine.command': {
      const c = d.command;
      if (c === 'zero') return by(`zeroed ${d.axis || 'every axis'}`);
      if (c === 'select_offset') return by(`selected ${d.offset}`);
      if (c === 'toggle_output' || c === 'set_output') return by(`switched ${d.name} ${d.on ? 'on' : 'off'}`);
      if (c === 'set_overrides') {
        const parts = ['feed', 'spindle', 'rapid'].filter((k) => typeof d[k] === 'number').map((k) => `${k} ${d[k]} %`);
        return by(`set the override${parts.length > 1 ? 's' : ''}: ${parts.join(', ')}`);
      }
      if (c === 'home' && d.axis) return by(`homed ${d.axis}`);
      return by(COMMANDS[c] || `sent ${c}`);
    }
    case 'machine.offsets':
      if (d.offset && d.values) return by(`set ${d.offset} to ${point(d.values)}`);
      if (d.active && Array.isArray(d.offsets)) {
        const active = d.offsets.find(([name]) => name === d.active);
        return by(`changed the offsets: ${d.active} is ${point(active ? active[1] : null)}`);
      }
      return by('changed the offsets');
    case 'machine.part_zero':
      return by(`recorded a part zero at ${point(d)}`) + (d.note ? ` ("${d.note}")` : '');
    case 'machine.touch_off': {
      const a = String(d.axis || '').toLowerCase();
      const change = d.before && d.after && a ? `: ${d.offset} ${d.axis} ${coord(d.before[a])} → ${coord(d.after[a])}` : '';
      return by(`touched off ${d.axis || ''}${change}`);
    }
    case 'machine.probe':
      return by(`probed ${d.axis || ''}`.trim()) + (d.tripped === false ? ' (no contact)' : '');
    case 'machine.alarm':
      return `Alarm: ${d.message || rest(d)}`;
    case 'machine.state':
      return `${d.from} → ${d.to}`;
    case 'machine.created':
      return by(`added machine ${d.name || ''}`.trim());
    default: {
      const what = e.type.replace(/^[a-z_]+\./, '').replace(/_/g, ' ');
      const r = rest(d);
      return by(`${e.type.split('.')[0].replace(/_/g, ' ')} ${what}`) + (r ? ` (${r})` : '');
    }
  }
}

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
      const what = h('td', { class: 'what', title: JSON.stringify(e.data) }, sentence(e));
      const row = h('tr', { dataset: { type: e.type } }, h('td', { class: 'small' }, time(e.time)),
        h('td', {}, e.machine ? machineName(e.machine) : ''), what, h('td', { class: 'muted small' }, e.type),
        h('td', { class: 'num muted small' }, e.id ?? ''));
      tbody.prepend(row);
      while (tbody.childElementCount > MAX_ROWS) tbody.lastChild.remove();
      // A job's events with a line say how far it was: its line count comes from the job.
      const d = e.data || {};
      if (d.job && d.line) {
        jobInfo(d.job).then((j) => { what.textContent = sentence(e, j.line_count); }).catch(() => {});
      }
    }, (ok) => { live.textContent = ok ? 'live' : 'reconnecting…'; live.className = 'badge ' + (ok ? 'ok' : 'lost'); });
  };
  const form = h('form', { class: 'row wrap' }, machine, types, h('button', { type: 'submit' }, 'Apply'), live);
  form.addEventListener('submit', (ev) => { ev.preventDefault(); open(); });
  page.append(h('h1', {}, 'Events'), h('section', { class: 'card' }, form,
    h('table', { class: 'events' }, h('thead', {}, h('tr', {}, ['when', 'machine', 'what happened', 'type', '#'].map((t) => h('th', {}, t)))), tbody)));
  open();
  return () => { if (es) es.close(); };
}
