// The run screen (issue 27): on the machine page, everything about the job the machine runs:
// its name, state and the reason for any hold, line of total, elapsed and the server's time
// left, pause / resume and a confirmed cancel, the program listing scrolled to the line running
// (a window of lines fetched around it, never the whole program), and the toolpath with the
// executed part and the tool.

import { api } from './api.js';
import { state, h, gate, act, dialog, duration, fixed, percent, errorText } from './ui.js';
import { ToolpathView } from './toolpath.js';
import { holdText, continueLabel } from './holds.js';
import { control } from './jobs.js';

/** Lines fetched around the current one, and how close to a window's edge a new one is asked. */
const WINDOW = 120;
const BEFORE = 30;
const MARGIN = 15;

/** The program listing: a window of lines around `line`, refetched as the line moves on. */
function listing() {
  const el = h('pre', { class: 'listing', id: 'run-listing', 'aria-label': 'program listing' });
  let job = null, from = 0, count = 0, total = 0, rows = [], current = 0, loading = false, failed = false;
  const fetchAround = async (line) => {
    if (loading) return;
    loading = true;
    const want = Math.max(1, line - BEFORE);
    const forJob = job;
    try {
      const text = await api('GET', `/jobs/${forJob}/gcode?from_line=${want}&lines=${WINDOW}`);
      if (forJob !== job) return;
      const lines = String(text).split('\n');
      if (lines.length && lines[lines.length - 1] === '') lines.pop();
      from = want; count = lines.length; failed = false;
      rows = lines.map((t, i) => h('div', { dataset: { line: want + i } }, h('span', { class: 'ln' }, String(want + i)), t));
      el.replaceChildren(...rows);
      current = 0;
    } catch (e) {
      failed = true;
      el.replaceChildren(h('div', { class: 'error' }, errorText(e)));
    } finally {
      loading = false;
    }
    show(line);
  };
  let wanted = 0;
  const show = (line) => {
    wanted = line;
    const end = from + count - 1;
    const outside = !count || line < from + (from > 1 ? 5 : 0) || (line > end - MARGIN && end < total);
    if (outside && !failed) { fetchAround(line); return; }
    if (line === current) return;
    if (current >= from && current <= end) rows[current - from].classList.remove('current');
    current = line;
    const row = rows[line - from];
    if (!row) return;
    row.classList.add('current');
    el.dataset.current = line;
    el.scrollTop = Math.max(0, row.offsetTop - el.clientHeight / 3);
  };
  return {
    el,
    /** Shows `line` of `jobId`'s program (`lines` in all). */
    update(jobId, line, lines) {
      if (jobId !== job) {
        job = jobId; from = 0; count = 0; rows = []; current = 0; failed = false;
        el.replaceChildren();
        delete el.dataset.current;
      }
      total = lines || 0;
      if (line !== wanted || !count) show(Math.max(1, line));
    },
  };
}

/** The run card of machine `id`: `{ el, update(), destroy() }`; `update` is cheap (per frame). */
export function runScreen(id) {
  const name = h('a', { id: 'run-job' });
  const badge = h('span', { class: 'badge', id: 'run-state' });
  const hold = h('p', { class: 'hold-reason', id: 'run-hold', hidden: true });
  const figure = (key, label) => {
    const v = h('span', { class: 'v', id: 'run-' + key }, '—');
    return [h('div', {}, h('span', { class: 'k' }, label), v), v];
  };
  const [lineBox, lineV] = figure('line', 'Line');
  const [pctBox, pctV] = figure('percent', 'Done');
  const [elBox, elapsedV] = figure('elapsed', 'Elapsed');
  const [remBox, remainingV] = figure('remaining', 'Remaining');
  const bar = h('progress', { max: 100, value: 0, id: 'run-progress' });
  let cur = null;
  // No toast when it works: the state beside the buttons says so.
  const send = (action) => (ev) => act(ev.currentTarget, () => control(cur.job, action)).catch(() => {});
  const pause = h('button', { class: 'go', dataset: { need: 'operator', run: 'pause' }, onclick: send('pause') }, 'Pause');
  const resume = h('button', { class: 'go primary', dataset: { need: 'motion', run: 'resume' }, onclick: send('resume') }, 'Resume');
  // Cancel ends the run: smaller, away from Pause, and confirmed.
  const cancel = h('button', { class: 'danger small cancel', dataset: { need: 'motion', run: 'cancel' }, onclick: async (ev) => {
    const r = cur;
    const body = h('div', { id: 'cancel-dialog' },
      h('p', {}, `Job ${r.job} "${r.name || ''}" stops at line ${fixed(r.line || 0)} of ${fixed(r.total_lines || 0)}; the machine stops.`),
      h('p', { class: 'muted small' }, 'A cancelled run does not resume: the job can be started again, or from a line.'));
    const answer = await dialog(`Cancel job ${r.job}?`, body, [['Keep the job', 'no'], ['Cancel the job', 'yes', 'danger']]);
    if (answer === 'yes') send('cancel')(ev);
  } }, 'Cancel job…');
  const list = listing();
  const previewBox = h('div', { class: 'preview-box' });
  const details = h('div', {},
    hold, h('div', { class: 'run-figures' }, lineBox, pctBox, elBox, remBox), bar,
    h('div', { class: 'run-controls' }, pause, resume, h('span', { class: 'spacer' }), cancel),
    list.el, previewBox);
  const idle = h('p', { class: 'muted', id: 'run-none' }, 'No job running on this machine. ', h('a', { href: '#/jobs' }, 'Start one from Jobs.'));
  const el = h('section', { class: 'card run-card', id: 'run-card', dataset: { whyGroup: '' } },
    h('div', { class: 'run-head' }, h('h2', {}, 'Job ', name), badge),
    h('p', { class: 'why', hidden: true }), details, idle);
  let preview = null, previewJob = null;

  const update = () => {
    const s = state.status.get(id) || {};
    const r = state.runs.get(id);
    const job = s.job && (!r || s.job.job === r.job) ? s.job : null;
    cur = r ? Object.assign({}, r) : job ? Object.assign({}, job) : null;
    details.hidden = !cur;
    idle.hidden = !!cur;
    if (!cur) {
      name.textContent = '';
      badge.hidden = true;
      if (preview) { preview.destroy(); preview = null; previewJob = null; previewBox.replaceChildren(); }
      return;
    }
    const line = Math.max(cur.line || 0, job ? job.line : 0);
    const total = cur.total_lines || (job && job.total_lines) || 0;
    cur.line = line; cur.total_lines = total;
    // The machine's state is the run's (the server keeps them together); paused says why.
    const paused = s.state === 'paused' || cur.state === 'paused';
    const st = paused ? 'paused' : (s.state === 'running' || cur.state === 'running' ? 'running' : (cur.state || s.state || 'running'));
    name.textContent = cur.name ? `${cur.job} · ${cur.name}` : String(cur.job);
    name.href = `#/jobs/${cur.job}`;
    badge.hidden = false;
    badge.textContent = st;
    badge.className = 'badge state-' + st;
    hold.hidden = !paused;
    hold.textContent = s.hold ? `Held: ${holdText(s.hold)} — ${continueLabel(s.hold)} goes on` + (s.hold.blocked ? ` (${s.hold.blocked})` : '') : 'Paused';
    lineV.textContent = `${fixed(line)} / ${fixed(total)}`;
    lineV.dataset.line = line;
    const pct = job && job.line === line ? job.percent : total ? Math.min(100, Math.round(1000 * line / total) / 10) : 0;
    pctV.textContent = percent(pct);
    bar.value = pct;
    const elapsed = cur.started_at ? (Date.now() - cur.started_at) / 1000 : NaN;
    elapsedV.textContent = duration(elapsed);
    const remaining = typeof cur.remaining_s === 'number' ? cur.remaining_s : job && typeof job.remaining_s === 'number' ? job.remaining_s : NaN;
    remainingV.textContent = duration(remaining) + (paused && isFinite(remaining) ? ' (paused)' : '');
    remainingV.dataset.seconds = isFinite(remaining) ? remaining : '';
    // Pause while it runs, resume (or cycle start, as the hold says) while paused: one at a time.
    pause.hidden = paused;
    resume.hidden = !paused;
    resume.textContent = paused && s.hold ? continueLabel(s.hold) : 'Resume';
    gate(el);
    // The line executing now (the machine's), else the one after the last acknowledged.
    list.update(cur.job, Math.max(s.line || 0, line + (line < total ? 1 : 0)), total);
    if (previewJob !== cur.job) {
      previewJob = cur.job;
      if (preview) preview.destroy();
      preview = new ToolpathView(previewBox);
      preview.load(cur.job).catch((e) => previewBox.replaceChildren(h('p', { class: 'error' }, errorText(e))));
    }
    preview.setProgress(line, s.work_position);
  };
  return { el, update, destroy: () => { if (preview) preview.destroy(); } };
}
