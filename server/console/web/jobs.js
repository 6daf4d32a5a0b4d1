// Jobs: upload (file picker or drag and drop, with progress), the analysis or the refusal with
// its line and column shown in the program, the job list with run control, and a job's preview.

import { api, upload } from './api.js';
import { state, h, gate, act, toast, errorText, position, duration, time, machineName, dialog, forgetJob, coord, length, feed, fixed, percent, display } from './ui.js';
import { ToolpathView } from './toolpath.js';
import { holdText, continueLabel } from './holds.js';
import { heightMapChoice } from './heightmap.js';

// Positions at the display resolution (mm or inch, the header's switch), lengths grouped.
const BOUNDS = (b) => b ? `X ${coord(b.min[0])}…${coord(b.max[0])} · Y ${coord(b.min[1])}…${coord(b.max[1])} · Z ${coord(b.min[2])}…${coord(b.max[2])} ${display.units}` : '—';

export function analysisView(a) {
  if (!a) return h('p', { class: 'muted' }, 'no analysis stored');
  const rows = [
    ['Lines', `${fixed(a.lines)} (${fixed(a.motion_lines)} with motion)`],
    ['Cutting bounds', BOUNDS(a.cutting_bounds)],
    ['Rapid bounds', BOUNDS(a.rapid_bounds)],
    ['Cutting length', length(a.cutting_length_mm)],
    ['Rapid length', length(a.rapid_length_mm)],
    ['Estimated time', duration(a.estimated_seconds)],
    ['Moves', `${fixed(a.rapid_moves)} rapid · ${fixed(a.linear_moves)} linear · ${fixed(a.arc_moves)} arc`],
    ['Max feed / spindle', `${feed(a.max_feed_mm_min)} · ${fixed(a.max_spindle_rpm)} rpm`],
    ['Tools', a.tools.length ? a.tools.map((t) => 'T' + t).join(' ') : '—'],
  ];
  if (a.units_inch_seen) {
    rows.unshift(['Units', display.units === 'in' ? 'inch program (G20), shown in inches' : 'inch program (G20), shown in mm: the header\'s "mm" button switches to inches']);
  }
  const warnings = (a.warnings || []).slice(0, 50).map((w) => h('li', {}, `line ${w.line}, column ${w.column}: ${w.message}`));
  return h('div', { class: 'analysis', id: 'analysis' },
    h('table', {}, rows.map(([k, v]) => h('tr', {}, h('th', {}, k), h('td', {}, v)))),
    warnings.length ? h('details', { open: true }, h('summary', {}, `${a.warnings.length + (a.warnings_dropped || 0)} warnings`), h('ul', {}, warnings)) : null);
}

/** The program around `line`, that line marked and its `column` highlighted. */
export function gcodeExcerpt(text, line, column) {
  const lines = text.split(/\r?\n/);
  const from = Math.max(1, line - 5), to = Math.min(lines.length, line + 5);
  const out = h('pre', { class: 'gcode', id: 'gcode-view' });
  for (let n = from; n <= to; n++) {
    const src = lines[n - 1] || '';
    const num = h('span', { class: 'ln' }, String(n).padStart(5) + '  ');
    if (n === line) {
      const i = Math.max(0, Math.min(src.length, column - 1));
      out.append(h('div', { class: 'err-line', dataset: { line: n } }, num, src.slice(0, i),
        h('mark', { class: 'col', dataset: { column } }, src.slice(i, i + 1) || ' '), src.slice(i + 1)));
    } else {
      out.append(h('div', {}, num, src));
    }
  }
  return out;
}

function runButtons(j, after, startBody) {
  // `startBody()`: the start's options chosen beside the buttons (a height map), if any.
  const ctl = (action, body) => (ev) => act(ev.currentTarget, () => control(j.id, action, typeof body === 'function' ? body() : body), `${action} sent`).then(after).catch(() => {});
  // Cancel ends the run for good: asked first (issue 27).
  const confirmCancel = async (ev) => {
    const el = ev.currentTarget;
    const answer = await dialog(`Cancel job ${j.id}?`, h('div', { id: 'cancel-dialog' },
      h('p', {}, `Job ${j.id}${j.name ? ` "${j.name}"` : ''} stops${j.line ? ` at line ${fixed(j.line)}` : ''}; the machine stops.`),
      h('p', { class: 'muted small' }, 'A cancelled run does not resume: the job can be started again, or from a line.')),
    [['Keep the job', 'no'], ['Cancel the job', 'yes', 'danger']]);
    if (answer === 'yes') ctl('cancel')({ currentTarget: el });
  };
  const s = j.state;
  const active = ['running', 'paused'].includes(s);
  // What the run's state allows (the server checks again); `gate` adds the role and stream.
  const off = (allowed) => (allowed ? '0' : '1');
  return h('div', { class: 'row wrap' },
    h('button', { dataset: { need: 'motion', action: 'start', off: off(!active) }, onclick: ctl('start', startBody) }, s === 'ready' ? 'Start' : 'Run again'),
    h('button', { dataset: { need: 'operator', action: 'pause', off: off(s === 'running') }, onclick: ctl('pause') }, 'Pause'),
    // A held run goes on with the button its hold names (a program stop: cycle start).
    h('button', { dataset: { need: 'motion', action: 'resume', off: off(['paused', 'interrupted', 'failed'].includes(s)) }, onclick: ctl('resume') },
      s === 'paused' && j.hold ? continueLabel(j.hold) : 'Resume'),
    h('button', { dataset: { need: 'motion', action: 'cancel', off: off(active || s === 'interrupted') }, class: 'danger small cancel', onclick: confirmCancel }, 'Cancel…'));
}

/** Run control; a resume the controller refuses because its part zero moved asks the operator. */
export async function control(id, action, body) {
  try {
    return await api('POST', `/jobs/${id}/${action}`, body);
  } catch (e) {
    if (action !== 'resume' || e.code !== 'part_zero_changed') throw e;
    const tuples = [...e.message.matchAll(/\(([-\d.]+), ([-\d.]+), ([-\d.]+)\)/g)].map((m) => m.slice(1).join(', '));
    const body = h('div', { id: 'part-zero-dialog' },
      h('p', {}, 'The controller reports another part zero than the one this run started with.'),
      h('table', {}, h('tr', {}, h('th', {}, 'Run started with'), h('td', { class: 'num' }, tuples[1] || '?')),
        h('tr', {}, h('th', {}, 'Controller reports now'), h('td', { class: 'num' }, tuples[0] || '?'))),
      h('p', { class: 'muted small' }, e.message));
    const answer = await dialog('Part zero changed', body, [['Keep stopped', 'no'], ['Resume with the new part zero', 'yes', 'danger']]);
    if (answer !== 'yes') throw new Error('resume not confirmed: the run stays paused');
    return api('POST', `/jobs/${id}/resume`, { confirm_part_zero: true });
  }
}

// --- Start at a line (issue 26) ---------------------------------------------------------------
// "Start at line…" asks for a line, shows what the server would do from where the machine stands
// (GET /jobs/{id}/start-preview: the modal state the lines before it leave and the preamble that
// brings the machine there), and only then offers to start there. A start that cannot be made is
// shown with its reason and line, and nothing is offered.

function startAtLine(j, after) {
  const box = h('div', { class: 'start-at', id: 'start-at' });
  const input = h('input', { type: 'number', id: 'start-line', min: 1, max: j.line_count, step: 1,
    value: Math.min(j.line_count, Math.max(1, (j.line || 0) + 1)), 'aria-label': 'line to start at', dataset: { need: 'operator' } });
  const result = h('div', { id: 'start-preview' });
  const active = ['running', 'paused'].includes(j.state);
  const preview = async () => {
    const line = Number(input.value);
    result.replaceChildren(h('p', { class: 'muted' }, `Planning the start at line ${line}…`));
    try {
      const p = await api('GET', `/jobs/${j.id}/start-preview?from_line=${line}`);
      const st = p.state;
      const s = p.start;
      const go = h('button', { class: 'danger', id: 'start-at-go', dataset: { need: 'motion', off: active ? '1' : '0' },
        onclick: (e) => act(e.currentTarget, () => api('POST', `/jobs/${j.id}/start`, { from_line: line }), `started at line ${line}`)
          .then(() => { result.replaceChildren(); after(); }).catch(() => {}) }, `Start at line ${line}`);
      result.replaceChildren(
        h('table', {}, [
          ['Start point (machine)', `X ${s.x.toFixed(3)} · Y ${s.y.toFixed(3)} · Z ${s.z.toFixed(3)} · A ${s.a.toFixed(3)}`],
          ['Safe Z (machine)', p.safe_z.toFixed(3) + ' mm'],
          ['Down at', p.approach_feed_mm_min.toFixed(0) + ' mm/min'],
          ['Tool', `T${st.tool_in_spindle} in the spindle` + (st.tool_length_offset === null ? ', no length offset' : `, G43 H${st.tool_length_offset}`)],
          ['Spindle / coolant', `${st.spindle} ${st.rpm} rpm · ${st.flood ? 'flood' : ''}${st.mist ? ' mist' : ''}${!st.flood && !st.mist ? 'off' : ''}`],
        ].map(([k, v]) => h('tr', {}, h('th', {}, k), h('td', {}, v)))),
        h('p', { class: 'muted small' }, 'What the machine does first, then line ' + line + ' and the rest of the program:'),
        h('pre', { class: 'gcode', id: 'start-preview-gcode' }, p.gcode),
        h('div', { class: 'row' }, go));
      gate(result);
    } catch (e) {
      result.replaceChildren(h('p', { class: 'error', id: 'start-refusal' }, errorText(e)));
    }
  };
  box.append(h('details', {}, h('summary', {}, 'Start at line…'),
    h('div', { class: 'row' }, h('label', {}, 'Line ', input),
      h('button', { id: 'start-at-preview', dataset: { need: 'operator' }, onclick: preview }, 'Preview')),
    result));
  return box;
}

// --- end of start at a line ----------------------------------------------------------------------

async function detail(page, id, events) {
  const j = await api('GET', `/jobs/${id}`);
  const info = h('div');
  const previewBox = h('div', { class: 'preview-box' });
  const preview = new ToolpathView(previewBox);
  const mapChoice = heightMapChoice(j.machine, id);
  const analysisBox = h('div', {}, analysisView(j.analysis));
  const refresh = async () => {
    forgetJob(id);
    const cur = await api('GET', `/jobs/${id}`);
    info.replaceChildren(
      h('p', {}, `Machine ${machineName(cur.machine)} · ${cur.line_count} lines · ${(cur.size_bytes / 1024).toFixed(1)} KB · uploaded ${time(cur.created_at)}`),
      h('p', {}, 'State ', h('span', { class: 'badge state-' + cur.state, id: 'job-state' }, cur.state),
        ' · line ', h('span', { id: 'job-line', dataset: { line: cur.line } }, `${fixed(cur.line)} / ${fixed(cur.line_count)}`), ' · ',
        h('span', { id: 'job-percent' }, cur.percent.toFixed(1) + ' %'),
        ' · remaining ', h('span', { id: 'job-remaining' }, '—'),
        cur.run && cur.run.message && !cur.hold ? ' · ' + cur.run.message : ''),
      cur.hold ? h('p', { id: 'job-hold', class: 'hold-reason' }, `Held: ${holdText(cur.hold)} — ${continueLabel(cur.hold)} goes on`,
        cur.hold.blocked ? h('span', { class: 'error' }, ` (${cur.hold.blocked})`) : '') : '',
      h('progress', { max: 100, value: cur.percent, id: 'job-progress' }),
      cur.run && cur.run.height_map_id ? h('p', { class: 'muted small', id: 'job-height-map' }, `run with height map ${cur.run.height_map_id}`) : '',
      mapChoice.el,
      runButtons(cur, refresh, mapChoice.body),
      startAtLine(cur, refresh));
    gate(info);
    preview.setProgress(cur.line);
  };
  page.append(h('p', {}, h('a', { href: '#/jobs' }, '← all jobs')), h('h1', {}, j.name),
    h('div', { class: 'cols' }, h('section', { class: 'card' }, info, analysisBox),
      h('section', { class: 'card' }, h('h2', {}, 'Toolpath'), previewBox)));
  await refresh();
  preview.load(id).catch((e) => previewBox.replaceChildren(h('p', { class: 'error' }, errorText(e))));
  // Line, percent and time left move with the run (the status's job: the server's estimate).
  const progress = (p) => {
    if (!p || p.job !== id) return;
    const line = p.line || 0;
    const pct = p.percent ?? (100 * line / j.line_count);
    const bar = info.querySelector('#job-progress');
    if (bar) bar.value = pct;
    const pe = info.querySelector('#job-percent');
    if (pe) pe.textContent = pct.toFixed(1) + ' %';
    const le = info.querySelector('#job-line');
    if (le) { le.textContent = `${fixed(line)} / ${fixed(j.line_count)}`; le.dataset.line = line; }
    const re = info.querySelector('#job-remaining');
    if (re && 'remaining_s' in p) { re.textContent = duration(p.remaining_s); re.dataset.seconds = p.remaining_s; }
    preview.setProgress(line, (state.status.get(j.machine) || {}).work_position);
  };
  const offs = [
    events.on('job.progress', (e) => progress(e.data)),
    events.on('job.state', (e) => { if (e.data.job === id) { refresh(); preview.setProgress(e.data.line); } }),
    events.on('status', (e) => {
      if (e.machine !== j.machine) return;
      if (e.data.job) progress(e.data.job);
      preview.setProgress(null, e.data.work_position);
    }),
  ];
  progress((state.status.get(j.machine) || {}).job);
  const onUnits = () => { analysisBox.replaceChildren(analysisView(j.analysis)); refresh().catch(() => {}); };
  document.addEventListener('fresa:units', onUnits);
  return () => { offs.forEach((f) => f()); preview.destroy(); document.removeEventListener('fresa:units', onUnits); };
}

export async function jobsPage(page, params, events) {
  if (params.job) return detail(page, params.job, events);
  const machines = [...state.machines.values()];
  const machineSel = h('select', { id: 'upload-machine', 'aria-label': 'machine' }, machines.map((m) => h('option', { value: m.id }, m.name)));
  const fileInput = h('input', { type: 'file', id: 'upload-file', accept: '.nc,.ngc,.gcode,.tap,.txt,text/plain', dataset: { need: 'operator' } });
  const bar = h('progress', { id: 'upload-progress', max: 1, value: 0, hidden: true });
  const result = h('div', { id: 'upload-result' });
  const drop = h('div', { class: 'drop', id: 'drop-zone' }, 'Drop a G-code file here, or ', h('label', { class: 'button' }, 'choose a file', fileInput));

  const send = async (file) => {
    if (!can_upload()) return;
    result.replaceChildren(h('p', {}, `Uploading ${file.name}…`));
    bar.hidden = false; bar.value = 0;
    try {
      const r = await upload(machineSel.value, file, (f) => { bar.value = f; });
      bar.value = 1;
      result.replaceChildren(h('h3', {}, `Stored as job ${r.id}: ${file.name}`),
        h('p', {}, h('a', { href: `#/jobs/${r.id}`, id: 'open-job' }, 'Open job ' + r.id + ' (toolpath, start)')),
        runButtons({ id: r.id, state: 'ready' }, reload), analysisView(r.analysis));
      gate(result);
      reload();
    } catch (e) {
      bar.hidden = true;
      const pos = position(e.message);
      const children = [h('h3', { class: 'error' }, 'Refused'), h('p', { class: 'error', id: 'refusal' }, errorText(e))];
      if (pos && file.size < 64 * 1024 * 1024) {
        children.push(h('p', {}, `Line ${pos.line}, column ${pos.column}:`), gcodeExcerpt(await file.text(), pos.line, pos.column));
      }
      result.replaceChildren(...children);
    }
  };
  const can_upload = () => !fileInput.disabled;
  fileInput.addEventListener('change', () => { if (fileInput.files[0]) send(fileInput.files[0]); fileInput.value = ''; });
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => {
    e.preventDefault();
    drop.classList.remove('over');
    const f = e.dataTransfer.files[0];
    if (f) send(f);
  });

  const filter = h('select', { id: 'jobs-filter', 'aria-label': 'filter by machine' }, h('option', { value: '' }, 'all machines'),
    machines.map((m) => h('option', { value: m.id }, m.name)));
  const tbody = h('tbody');
  let loading = null;
  const reload = async () => {
    if (loading) return loading;
    loading = (async () => {
      const q = filter.value ? `?machine=${filter.value}` : '';
      const jobs = await api('GET', '/jobs' + q);
      tbody.replaceChildren(...jobs.map((j) => h('tr', { dataset: { job: j.id } },
        h('td', {}, h('a', { href: `#/jobs/${j.id}` }, String(j.id))), h('td', {}, h('a', { href: `#/jobs/${j.id}` }, j.name)),
        h('td', {}, machineName(j.machine)), h('td', { class: 'num' }, j.line_count),
        h('td', {}, h('span', { class: 'badge state-' + j.state }, j.state)),
        h('td', {}, h('progress', { max: 100, value: j.percent }), ' ', j.percent.toFixed(1) + ' %'),
        h('td', {}, time(j.created_at)), h('td', {}, runButtons(j, reload)))));
      gate(tbody);
    })().finally(() => { loading = null; });
    return loading;
  };
  filter.addEventListener('change', reload);
  page.append(h('h1', {}, 'Jobs'),
    h('section', { class: 'card' }, h('h2', {}, 'Upload a program'), h('div', { class: 'row' }, h('label', {}, 'Machine ', machineSel)), drop, bar, result),
    h('section', { class: 'card' }, h('div', { class: 'row between' }, h('h2', {}, 'All jobs'), filter),
      h('table', { class: 'jobs' }, h('thead', {}, h('tr', {}, ['#', 'name', 'machine', 'lines', 'state', 'progress', 'uploaded', ''].map((t) => h('th', {}, t)))), tbody)));
  await reload().catch((e) => toast(errorText(e)));
  let timer = 0;
  const soon = () => { if (!timer) timer = setTimeout(() => { timer = 0; reload().catch(() => {}); }, 250); };
  const offs = [events.on('job.state', soon), events.on('job.created', soon), events.on('job.progress', soon), events.on('reloaded', soon)];
  return () => { offs.forEach((f) => f()); clearTimeout(timer); };
}
