// A machine's records on its page (issue 28, part 2): the maintenance counters and intervals
// (a "maintenance due" badge for the header, "Done" for admins) and a small stacked bar per day
// of the last 7 days' utilisation (GET /reports/utilisation). Plain elements, no chart library.

import { api } from './api.js';
import { h, act, errorText } from './ui.js';

const STATES = ['cutting', 'idle', 'held', 'alarm', 'unresponsive', 'offline'];
const DAY_S = 86400;

const hours = (s) => (s / 3600).toFixed(s < 360 ? 3 : 1) + ' h';

/** `{el, badge, load}`: the card, the header's due badge, and a reload. */
export function recordsCard(id) {
  const badge = h('span', { class: 'badge maint-due', id: 'maintenance-due', hidden: true });
  const counters = h('p', { class: 'muted', id: 'counters' });
  const items = h('tbody', { id: 'maintenance-items' });
  const chart = h('div', { class: 'util-chart', id: 'utilisation-chart' });
  const legend = h('div', { class: 'row wrap util-legend' },
    STATES.map((s) => h('span', {}, h('i', { class: 'util-' + s }), s)));
  const error = h('p', { class: 'error' });

  const drawCounters = (c) => {
    const d = c.distance_mm || {};
    counters.textContent = `spindle ${hours(c.spindle_hours * 3600)} · motion ${hours(c.motion_hours * 3600)} · ` +
      `${c.jobs} jobs · travel X ${(d.x / 1000).toFixed(2)} m, Y ${(d.y / 1000).toFixed(2)} m, Z ${(d.z / 1000).toFixed(2)} m`;
    const due = c.maintenance.filter((m) => m.due);
    badge.hidden = due.length === 0;
    badge.textContent = 'maintenance due: ' + due.map((m) => m.name).join(', ');
    items.replaceChildren(...(c.maintenance.length ? c.maintenance.map((m) => h('tr', { dataset: { maintenance: m.name } },
      h('td', {}, m.name, m.due ? h('span', { class: 'badge maint-due' }, 'due') : ''),
      h('td', { class: 'num' }, `${m.since_done.toFixed(m.counter === 'jobs' ? 0 : 3)} / ${m.every} ${m.counter.replace('_', ' ')}`),
      h('td', {}, m.done_by ? `${m.done_by}` : '—'),
      h('td', {}, h('button', { dataset: { need: 'admin' }, onclick: (ev) =>
        act(ev.currentTarget, () => api('POST', `/machines/${id}/maintenance/${encodeURIComponent(m.name)}/done`), `${m.name} done`)
          .then(load).catch(() => {}) }, 'Done')))) :
      [h('tr', {}, h('td', { colspan: 4, class: 'muted' }, 'no maintenance intervals'))]));
  };

  const drawChart = (report) => {
    const mine = (report.machines || []).find((m) => m.machine === id);
    const days = mine ? mine.days : [];
    chart.replaceChildren(...(days.length ? days.map((d) => {
      const bar = h('div', { class: 'util-bar', title: STATES.map((s) => `${s} ${hours(d[s])}`).join(', ') });
      for (const s of STATES) {
        if (d[s] <= 0) continue;
        const seg = h('span', { class: 'util-' + s });
        // CSSOM, not a style attribute: the console's CSP allows no inline styles.
        seg.style.width = (100 * d[s] / DAY_S) + '%';
        bar.append(seg);
      }
      return h('div', { class: 'util-day' }, h('span', { class: 'muted small' }, d.day.slice(5)), bar);
    }) : [h('p', { class: 'muted' }, 'no recorded time yet')]));
  };

  async function load() {
    error.textContent = '';
    try {
      const [c, r] = await Promise.all([api('GET', `/machines/${id}/counters`), api('GET', '/reports/utilisation')]);
      drawCounters(c);
      drawChart(r);
    } catch (e) { error.textContent = errorText(e); }
  }

  const el = h('section', { class: 'card', id: 'records-card', dataset: { whyGroup: '' } }, h('h2', {}, 'Records'),
    h('p', { class: 'why', hidden: true }), counters,
    h('table', {}, h('thead', {}, h('tr', {}, h('th', {}, 'maintenance'), h('th', {}, 'since done'), h('th', {}, 'last done by'), h('th', {}, ''))), items),
    h('h3', {}, 'Utilisation, last 7 days (share of each day)'), chart, legend, error);
  return { el, badge, load };
}
