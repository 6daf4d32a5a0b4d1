// One machine: DRO, step jog, cycle controls, outputs, MDI, offsets, part zeros, and the run
// screen (the running job: listing, toolpath, pause/resume/cancel). STOP and feed hold stay on
// screen (sticky bar). Controls that cannot act now (a job runs, the machine moves, the live
// stream is lost) are disabled, each card saying why (`data-when`, `ui.gate`).

import { api, QUEUE_EVENTS } from './api.js';
import { state, h, gate, mm, coord, feed as feedText, act, toast, errorText, position, ioLamps, time } from './ui.js';
import { urgentButtons, stateBadge } from './overview.js';
import { holdBlock, queueBanner } from './holds.js';
import { runScreen } from './runscreen.js';
import { recordsCard } from './records.js';

const AXES = ['x', 'y', 'z', 'a'];
const STEPS = [0.001, 0.01, 0.1, 1, 10];
const OFFSETS = ['G54', 'G55', 'G56', 'G57', 'G58', 'G59'];
const OUTPUTS = [['spindle', 'Spindle'], ['coolant', 'Coolant'], ['z_lift', 'Z lift']];

/** A G-code line with the character at `column` marked (1-based). */
export function markColumn(line, column) {
  const i = Math.max(0, Math.min(line.length, column - 1));
  return h('code', { class: 'gline' }, line.slice(0, i),
    h('mark', { class: 'col' }, line.slice(i, i + 1) || ' '), line.slice(i + 1));
}

/** A card whose disabled controls say why in its `.why` line (see `ui.gate`). */
function card(title, ...children) {
  return h('section', { class: 'card', dataset: { whyGroup: '' } }, h('h2', {}, title), h('p', { class: 'why', hidden: true }), ...children);
}

/** MDI history per machine in this browser: the last 50 distinct lines, newest last. */
function mdiHistory(id) {
  const key = `fresa.mdi.${id}`;
  let lines = [];
  try { lines = JSON.parse(localStorage.getItem(key) || '[]').filter((l) => typeof l === 'string'); } catch (_) { /* none */ }
  let at = lines.length;
  let draft = '';
  return {
    add(line) {
      lines = lines.filter((l) => l !== line);
      lines.push(line);
      lines = lines.slice(-50);
      localStorage.setItem(key, JSON.stringify(lines));
      at = lines.length;
    },
    /** The line ArrowUp (-1) or ArrowDown (+1) brings, from what is typed now. */
    step(dir, typed) {
      if (at === lines.length) draft = typed;
      at = Math.max(0, Math.min(lines.length, at + dir));
      return at === lines.length ? draft : lines[at];
    },
  };
}

export async function machinePage(page, { id }, events) {
  const m = state.machines.get(id) || await api('GET', `/machines/${id}`);
  page.dataset.gateMachine = id;
  const cmd = (command, extra) => api('POST', `/machines/${id}/commands`, Object.assign({ command }, extra || {}));

  // Counters, maintenance and utilisation (records.js); its due badge sits in the header.
  const records = recordsCard(id);

  // Header with the urgent buttons, sticky on small screens.
  const badge = h('span');
  const header = h('div', { class: 'sticky-bar' },
    h('h1', {}, m.name, ' ', h('span', { class: 'muted small' }, m.backend)), badge, records.badge,
    h('div', { class: 'row urgent' }, urgentButtons(id)));

  // DRO.
  const dro = {};
  const mpos = {};
  const droEl = h('div', { class: 'dro' }, AXES.map((a) => h('div', { class: 'dro-axis' },
    h('span', { class: 'dro-label' }, a.toUpperCase()),
    (dro[a] = h('span', { class: 'dro-value num', dataset: { dro: a } }, '—')),
    (mpos[a] = h('span', { class: 'dro-m num muted', dataset: { mpos: a } }, '—')))));
  const droInfo = h('div', { class: 'muted' });
  const lamps = h('div');

  // Step jog, bounded by the machine's limits (the server refuses anything past them too), or
  // hold-to-jog ("Hold" in the step list): the axis moves while the button or key is held
  // (at most max_jog_mm), kept alive every 100 ms; released, it is cancelled. A tab that
  // closes or loses its link sends no keep-alive, and the server stops the move within 250 ms.
  const steps = STEPS.filter((s) => s <= m.max_jog_mm);
  const stepSel = h('select', { id: 'jog-step', 'aria-label': 'jog step (mm)' },
    steps.map((s) => h('option', { value: s, selected: s === 1 }, s + ' mm')),
    h('option', { value: 'hold' }, 'Hold (continuous)'));
  const feed = h('input', { id: 'jog-feed', type: 'number', min: 1, max: m.max_feed_mm_min, step: 1,
    value: Math.min(1000, m.max_feed_mm_min), 'aria-label': 'jog feed (mm/min)' });
  const jogError = h('p', { class: 'error', id: 'jog-error' });
  const jogFeed = () => {
    const f = parseFloat(feed.value);
    if (f > 0 && f <= m.max_feed_mm_min) return f;
    jogError.textContent = `feed must be 1..${m.max_feed_mm_min} mm/min`;
    return null;
  };
  const holding = () => stepSel.value === 'hold';
  const stepJog = async (axis, sign, el) => {
    jogError.textContent = '';
    const f = jogFeed();
    if (f === null) return;
    const distance = sign * parseFloat(stepSel.value);
    try {
      await act(el, () => api('POST', `/machines/${id}/jog`, { axis: axis.toUpperCase(), distance, feed: f }));
    } catch (e) { jogError.textContent = errorText(e); }
  };
  // The hold under way: { key, timer, released }. One at a time, as the server allows.
  let held = null;
  const startHold = async (axis, sign, key) => {
    if (held) return;
    jogError.textContent = '';
    const f = jogFeed();
    if (f === null) return;
    const mine = held = { key, timer: 0, released: false };
    jogPad.dataset.holding = key;
    try {
      await api('POST', `/machines/${id}/jog`, { axis: axis.toUpperCase(), direction: sign > 0 ? '+' : '-', feed: f, continuous: true });
    } catch (e) {
      jogError.textContent = errorText(e);
      if (held === mine) { held = null; delete jogPad.dataset.holding; }
      return;
    }
    // Released while the start was on its way: end it now.
    if (mine.released) { cancelHold(); return; }
    mine.timer = setInterval(() => {
      api('POST', `/machines/${id}/jog/keepalive`).catch(() => {
        // It ended (its whole way, a stop, a missed keep-alive): nothing to keep alive.
        clearInterval(mine.timer);
        if (held === mine) { held = null; delete jogPad.dataset.holding; }
      });
    }, 100);
  };
  const cancelHold = () => api('POST', `/machines/${id}/jog/cancel`)
    .catch((e) => { jogError.textContent = errorText(e); });
  const endHold = () => {
    const mine = held;
    if (!mine) return;
    held = null;
    delete jogPad.dataset.holding;
    mine.released = true;
    // Not started yet: the start ends it when its answer comes.
    if (mine.timer) { clearInterval(mine.timer); cancelHold(); }
  };
  const jogButton = (a, sign) => {
    const key = a.toUpperCase() + (sign > 0 ? '+' : '-');
    const b = h('button', { dataset: { need: 'motion', when: 'no-run', toolChange: 'ok', jog: key } }, a.toUpperCase() + (sign > 0 ? '+' : '−'));
    b.addEventListener('click', (ev) => { if (!holding()) stepJog(a, sign, ev.currentTarget); });
    b.addEventListener('pointerdown', (ev) => {
      if (!holding() || b.disabled) return;
      b.setPointerCapture?.(ev.pointerId);
      startHold(a, sign, key);
    });
    for (const end of ['pointerup', 'pointercancel', 'lostpointercapture']) b.addEventListener(end, endHold);
    return b;
  };
  const jogPad = h('div', { class: 'jog' }, AXES.map((a) => h('div', { class: 'jog-axis' },
    jogButton(a, -1), jogButton(a, 1))));

  // Keyboard jog, off until switched on (a stray arrow key must not move a machine): arrows
  // X/Y, PgUp/PgDn Z, each a step or, with "Hold", held until the key is released. Keys typed
  // into a field are never jogs.
  const KEYS = { ArrowLeft: ['x', -1], ArrowRight: ['x', 1], ArrowUp: ['y', 1], ArrowDown: ['y', -1], PageUp: ['z', 1], PageDown: ['z', -1] };
  let keyboard = false;
  const kbSwitch = h('button', { id: 'keyboard-jog', 'aria-pressed': 'false', dataset: { need: 'motion' } }, 'Keyboard jog');
  const kbBadge = h('span', { id: 'keyboard-jog-on', class: 'badge keyboard', hidden: true }, 'keyboard jog on');
  kbSwitch.addEventListener('click', () => {
    keyboard = !keyboard;
    kbSwitch.setAttribute('aria-pressed', String(keyboard));
    kbBadge.hidden = !keyboard;
    if (!keyboard) endHold();
  });
  const typing = (t) => t && (t.isContentEditable || ['INPUT', 'SELECT', 'TEXTAREA'].includes(t.tagName));
  const onKeyDown = (ev) => {
    const k = KEYS[ev.key];
    if (!k || !keyboard || kbSwitch.disabled || typing(ev.target)) return;
    ev.preventDefault();
    if (ev.repeat) return;
    const [axis, sign] = k;
    if (holding()) startHold(axis, sign, 'key:' + ev.key);
    else stepJog(axis, sign, null);
  };
  const onKeyUp = (ev) => { if (held && held.key === 'key:' + ev.key) endHold(); };
  const onHidden = () => { if (document.hidden) endHold(); };
  document.addEventListener('keydown', onKeyDown);
  document.addEventListener('keyup', onKeyUp);
  window.addEventListener('blur', endHold);
  document.addEventListener('visibilitychange', onHidden);
  const keyboardOff = () => {
    endHold();
    document.removeEventListener('keydown', onKeyDown);
    document.removeEventListener('keyup', onKeyUp);
    window.removeEventListener('blur', endHold);
    document.removeEventListener('visibilitychange', onHidden);
  };
  // Ends the jog under way and drops every jog still queued (taps, pendant wheel); like STOP,
  // it needs no live stream.
  const jogCancel = h('button', { id: 'jog-cancel', class: 'hold', dataset: { need: 'operator' }, onclick: (ev) => {
    jogError.textContent = '';
    act(ev.currentTarget, () => api('POST', `/machines/${id}/jog/cancel`), 'Jog cancelled')
      .catch((e) => { jogError.textContent = errorText(e); });
  } }, 'Cancel jog');

  const button = (label, command, when, extra) => h('button', { dataset: { need: 'motion', when, cmd: command },
    onclick: (ev) => act(ev.currentTarget, () => cmd(command, extra), label + ' sent').catch(() => {}) }, label);
  const cycle = h('div', { class: 'row wrap' },
    button('Cycle start', 'cycle_start'), button('Resume', 'resume'),
    button('Reset', 'reset'), button('Home', 'home', 'no-run'),
    button('Go to zero', 'go_to_zero', 'no-run'));
  const zeros = h('div', { class: 'row wrap' }, h('span', { class: 'muted' }, 'Zero'),
    AXES.map((a) => button(a.toUpperCase(), 'zero', 'still', { axis: a.toUpperCase() })),
    button('All', 'zero', 'still'));
  const outputs = h('div', { class: 'row wrap' });
  const drawOutputs = () => {
    const io = (state.io.get(id) || {}).outputs;
    outputs.replaceChildren(h('span', { class: 'muted' }, 'Outputs'), ...OUTPUTS
      .filter(([name]) => !io || Object.keys(io).some((k) => k === name || k.startsWith(name + '_')))
      .map(([name, label]) => h('button', { dataset: { need: 'motion', when: name === 'z_lift' ? undefined : 'not-cutting', output: name },
        onclick: (ev) => act(ev.currentTarget, () => cmd('toggle_output', { name }), label + ' toggled').catch(() => {}) }, label)));
    gate(outputs);
  };

  // MDI: the server checks the line; a 422 shows the line with its column marked.
  const mdiInput = h('input', { id: 'mdi', type: 'text', placeholder: 'G91 G0 Z5', autocomplete: 'off', spellcheck: 'false' });
  const mdiError = h('div', { class: 'error', id: 'mdi-error' });
  const mdiForm = h('form', { class: 'row' }, mdiInput,
    h('button', { type: 'submit', dataset: { need: 'motion', when: 'no-run' } }, 'Send MDI'));
  // ↑ and ↓ bring back the lines sent before (kept per machine in this browser).
  const history = mdiHistory(id);
  mdiInput.addEventListener('keydown', (ev) => {
    if (ev.key !== 'ArrowUp' && ev.key !== 'ArrowDown') return;
    ev.preventDefault();
    mdiInput.value = history.step(ev.key === 'ArrowUp' ? -1 : 1, mdiInput.value);
  });
  mdiForm.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    mdiError.replaceChildren();
    const line = mdiInput.value;
    if (mdiForm.querySelector('button').disabled) return;
    try {
      await api('POST', `/machines/${id}/mdi`, { line });
      history.add(line);
      mdiInput.value = '';
      toast('MDI sent', 'ok');
    } catch (e) {
      const pos = position(e.message);
      mdiError.replaceChildren(h('p', {}, errorText(e)), pos ? markColumn(line, pos.column) : '');
    }
  });

  // Offsets G54..G59, editable.
  const offsetsBody = h('tbody');
  const loadOffsets = async () => {
    const o = await api('GET', `/machines/${id}/offsets`);
    offsetsBody.replaceChildren(...OFFSETS.map((name) => {
      const v = o.offsets[name] || {};
      const inputs = AXES.map((a) => h('input', { type: 'number', step: 'any', value: v[a] ?? 0, 'aria-label': `${name} ${a}`, dataset: { need: 'motion', when: 'still' } }));
      const save = h('button', { dataset: { need: 'motion', when: 'still' }, onclick: async (ev) => {
        const body = {};
        AXES.forEach((a, i) => { body[a] = parseFloat(inputs[i].value); });
        await act(ev.currentTarget, () => api('PUT', `/machines/${id}/offsets/${name}`, body), name + ' saved').catch(() => {});
      } }, 'Save');
      const select = h('button', { dataset: { need: 'motion', when: 'still' }, onclick: (ev) =>
        act(ev.currentTarget, () => cmd('select_offset', { offset: name }), name + ' active').then(loadOffsets).catch(() => {}) }, 'Use');
      return h('tr', { class: o.active === name ? 'active' : '', dataset: { offset: name } },
        h('th', {}, name, o.active === name ? ' ●' : ''), inputs.map((i) => h('td', {}, i)), h('td', { class: 'row' }, save, select));
    }));
    gate(offsetsBody);
  };

  // Touch-off: probe down onto a plate of known thickness; Z then reads the thickness where the
  // tool touched. The plate is remembered per machine in this browser; the probe's lamp sits
  // beside the button, and without a probe input the panel says so instead.
  const plateKey = `fresa.plate.${id}`;
  const numberField = (fid, label, value, max) => h('label', {}, label + ' ',
    h('input', { id: fid, type: 'number', min: 0, max, step: 'any', value, 'aria-label': label }));
  const plateField = numberField('touch-plate', 'Plate mm', localStorage.getItem(plateKey) || '15', 100);
  const distField = numberField('touch-distance', 'Distance mm', Math.min(50, m.max_jog_mm), m.max_jog_mm);
  const probeFeed = m.max_probe_feed_mm_min || 300;
  const feedField = numberField('touch-feed', 'Feed mm/min', Math.min(100, probeFeed), probeFeed);
  const retractField = numberField('touch-retract', 'Retract mm', 5, m.max_jog_mm);
  // Z down onto a plate, or an edge: X/Y toward + or -, with the tool's diameter.
  const axisSel = h('select', { id: 'touch-axis', 'aria-label': 'touch-off axis' },
    [['Z', 'Z (plate on top)'], ['X+', 'X+ (left edge)'], ['X-', 'X− (right edge)'], ['Y+', 'Y+ (front edge)'], ['Y-', 'Y− (back edge)']]
      .map(([v, label]) => h('option', { value: v }, label)));
  const diameterField = numberField('touch-diameter', 'Tool Ø mm', 6, 100);
  const showAxis = () => {
    const edge = axisSel.value !== 'Z';
    diameterField.hidden = !edge;
    touchButton.textContent = 'Touch off ' + axisSel.value.replace('-', '−');
  };
  axisSel.addEventListener('change', showAxis);
  const value = (label) => parseFloat(label.querySelector('input').value);
  const probeLamp = h('span', { id: 'probe-lamp', class: 'lamp unknown in' }, 'probe');
  const touchResult = h('p', { id: 'touch-result', class: 'muted' });
  const touchButton = h('button', { id: 'touch-off', dataset: { need: 'motion', when: 'no-run', toolChange: 'ok' }, onclick: async (ev) => {
    const choice = axisSel.value;
    const axis = choice[0];
    const body = { axis, plate_mm: value(plateField), distance: value(distField), feed: value(feedField), retract_mm: value(retractField) };
    if (axis !== 'Z') {
      body.toward = choice[1];
      body.tool_diameter_mm = value(diameterField);
    }
    localStorage.setItem(plateKey, String(body.plate_mm));
    touchResult.className = 'muted';
    touchResult.textContent = 'Probing…';
    try {
      const r = await act(ev.currentTarget, () => api('POST', `/machines/${id}/touch-off`, body), axis + ' set from the plate');
      const a = axis.toLowerCase();
      touchResult.textContent = `Touched at machine ${axis} ${mm(r.trip[a])}: ${r.offset} ${axis} ${mm(r.before[a])} → ${mm(r.after[a])}; ${axis} reads ${mm(r.work_position[a])} (${mm(r.overshoot_mm)} mm overshoot)`;
    } catch (e) {
      touchResult.className = 'error';
      touchResult.textContent = errorText(e);
    }
  } }, 'Touch off Z');
  const drawProbe = () => {
    const inputs = (state.io.get(id) || {}).inputs || {};
    const has = Object.prototype.hasOwnProperty.call(inputs, 'probe');
    const v = inputs.probe;
    probeLamp.className = `lamp ${v === null || v === undefined ? 'unknown' : v ? 'on' : 'off'} in`;
    probeLamp.title = has ? `probe ${v === null ? 'unknown' : v ? 'closed (touching)' : 'open'}` : 'no probe input';
    touchButton.dataset.off = has ? '' : '1';
    touchButton.dataset.tip = has ? '' : 'this machine reports no probe input';
    if (!has) touchResult.textContent = 'This machine reports no probe input: touch-off needs one.';
    else if (touchResult.textContent.startsWith('This machine reports no probe')) touchResult.textContent = '';
  };
  showAxis();
  const touchCard = h('section', { class: 'card', id: 'touch-card', dataset: { whyGroup: '' } }, h('h2', {}, 'Touch-off'), h('p', { class: 'why', hidden: true }),
    h('div', { class: 'row wrap' }, h('label', {}, 'Axis ', axisSel), plateField, diameterField, distField, feedField, retractField),
    h('div', { class: 'row' }, touchButton, probeLamp), touchResult,
    h('p', {}, h('a', { href: `#/machines/${id}/height-maps`, id: 'height-maps-link' }, 'Height maps (probe a grid) →')));

  // Overrides: feed and spindle by slider (sent on release) or ±10 %, rapid at 25/50/100 %,
  // each within the machine's range; allowed during a run (that is when they matter). What the
  // machine reports is what is shown, so a slider snaps back if the machine refused.
  const lim = m.override_limits || { feed_min: 10, feed_max: 200, spindle_min: 50, spindle_max: 150, rapid_min: 25 };
  const ovrError = h('p', { class: 'error', id: 'override-error' });
  const setOverride = async (el, kind, value) => {
    ovrError.textContent = '';
    try {
      await act(el, () => api('POST', `/machines/${id}/overrides`, { [kind]: value }), `${kind} override ${value} %`);
    } catch (e) { ovrError.textContent = errorText(e); }
    drawOverrides();
  };
  const sliders = {};
  const values = {};
  const sliderRow = (kind, label, min, max) => {
    const clamp = (v) => Math.max(min, Math.min(max, v));
    const slider = (sliders[kind] = h('input', { type: 'range', id: `override-${kind}`, min, max, step: 1, value: 100,
      'aria-label': `${label} override (%)`, dataset: { need: 'motion' } }));
    slider.addEventListener('input', () => { values[kind].textContent = slider.value + ' %'; });
    slider.addEventListener('change', () => setOverride(slider, kind, parseFloat(slider.value)));
    const step = (d) => h('button', { dataset: { need: 'motion', override: `${kind}${d > 0 ? '+' : '-'}` },
      onclick: (ev) => setOverride(ev.currentTarget, kind, clamp(parseFloat(slider.value) + d)) }, (d > 0 ? '+' : '−') + Math.abs(d));
    values[kind] = h('span', { class: 'num', dataset: { overrideValue: kind } }, '100 %');
    return h('div', { class: 'row override' }, h('span', { class: 'override-label' }, label), step(-10), slider, step(10), values[kind]);
  };
  values.rapid = h('span', { class: 'num', dataset: { overrideValue: 'rapid' } }, '100 %');
  const rapidButtons = [25, 50, 100].filter((v) => v >= lim.rapid_min).map((v) => h('button', {
    dataset: { need: 'motion', override: `rapid${v}` },
    onclick: (ev) => setOverride(ev.currentTarget, 'rapid', v) }, v + ' %'));
  const drawOverrides = () => {
    const st = state.status.get(id) || {};
    for (const [kind, key] of [['feed', 'feed_override'], ['spindle', 'spindle_override']]) {
      const v = st[key] ?? 100;
      if (document.activeElement !== sliders[kind]) sliders[kind].value = v;
      values[kind].textContent = v + ' %';
    }
    const r = st.rapid_override ?? 100;
    values.rapid.textContent = r + ' %';
    rapidButtons.forEach((b) => b.classList.toggle('active', parseFloat(b.textContent) === r));
  };
  const overrideCard = h('section', { class: 'card', id: 'override-card', dataset: { whyGroup: '' } }, h('h2', {}, 'Overrides'), h('p', { class: 'why', hidden: true }),
    sliderRow('feed', 'Feed', lim.feed_min, lim.feed_max),
    sliderRow('spindle', 'Spindle', lim.spindle_min, lim.spindle_max),
    h('div', { class: 'row override' }, h('span', { class: 'override-label' }, 'Rapid'), ...rapidButtons, values.rapid),
    ovrError);

  const hold = holdBlock(id, page);
  // The job queue's banner (issue 28): the next part waits for its confirm, or the queue holds.
  const queue = queueBanner(id);

  // Part-zero history.
  const pzList = h('tbody');
  const loadPartZeros = async () => {
    const rows = await api('GET', `/machines/${id}/part-zero`);
    pzList.replaceChildren(...(rows.length ? rows.slice(0, 20).map((r) => {
      const p = r.position || r;
      return h('tr', {}, h('td', {}, time(r.created_at || r.time || 0)),
        AXES.map((a) => h('td', { class: 'num' }, coord(p[a]))), h('td', {}, r.source || ''), h('td', {}, r.actor || ''), h('td', {}, r.note || ''));
    }) : [h('tr', {}, h('td', { colspan: 8, class: 'muted' }, 'none recorded'))]));
  };
  const note = h('input', { type: 'text', placeholder: 'note (optional)', maxlength: 200, 'aria-label': 'part zero note' });
  const record = h('button', { id: 'record-part-zero', dataset: { need: 'motion', when: 'still' }, onclick: (ev) =>
    act(ev.currentTarget, () => api('POST', `/machines/${id}/part-zero`, note.value ? { note: note.value } : {}), 'Part zero recorded')
      .then(loadPartZeros).catch(() => {}) }, 'Record here');

  // The run screen: the running job, its listing and toolpath (runscreen.js).
  const run = runScreen(id);

  // Why the machine holds and the button that goes on (issue 26), under the header.
  page.append(header, hold.banner, queue.el,
    h('div', { class: 'cols' },
      card('Position', droEl, droInfo, lamps),
      Object.assign(card('Jog',
        h('div', { class: 'row wrap' }, h('label', {}, 'Step ', stepSel), h('label', {}, 'Feed ', feed, ' mm/min')),
        h('p', { class: 'muted small limits-hint' }, `At most ${m.max_jog_mm} mm per step and ${m.max_feed_mm_min} mm/min.`),
        jogPad, h('div', { class: 'row wrap' }, jogCancel, kbSwitch, kbBadge),
        h('p', { class: 'muted small' }, 'Keys: ← → X, ↑ ↓ Y, PgUp PgDn Z.'), jogError), { className: 'card jog-card' })),
    run.el,
    h('div', { class: 'cols' },
      card('Cycle', cycle, zeros, outputs),
      card('MDI', mdiForm, h('p', { class: 'muted small' }, '↑ ↓: lines sent before'), mdiError)),
    h('div', { class: 'cols' }, overrideCard, touchCard),
    hold.el,
    card('Work offsets',
      h('table', { class: 'offsets' }, h('thead', {}, h('tr', {}, h('th', {}, ''), AXES.map((a) => h('th', {}, a.toUpperCase())), h('th', {}, ''))), offsetsBody)),
    card('Part zero', h('div', { class: 'row' }, note, record),
      h('table', {}, h('thead', {}, h('tr', {}, h('th', {}, 'when'), AXES.map((a) => h('th', {}, a.toUpperCase())), h('th', {}, 'source'), h('th', {}, 'who'), h('th', {}, 'note'))), pzList)),
    records.el);

  const update = () => {
    const s = state.status.get(id) || {};
    const row = state.machines.get(id) || m;
    badge.replaceChildren(stateBadge(s.state || row.state, row.reason || s.reason || s.alarm));
    for (const a of AXES) {
      const w = coord((s.work_position || {})[a]), mp = 'M ' + coord((s.machine_position || {})[a]);
      if (dro[a].textContent !== w) dro[a].textContent = w;
      if (mpos[a].textContent !== mp) mpos[a].textContent = mp;
    }
    droInfo.textContent = `offset ${s.active_offset || '—'} · feed ${feedText(s.feed)} · override ${s.feed_override ?? '—'} %`;
    drawOverrides();
    run.update();
    const l = ioLamps(id);
    lamps.replaceChildren(...(l ? [l] : []));
    drawProbe();
    hold.update();
    gate(page);
  };
  let frame = 0;
  const schedule = () => {
    if (!frame) frame = requestAnimationFrame(() => { frame = 0; update(); });
  };
  update();
  drawOutputs();
  await Promise.all([loadOffsets(), loadPartZeros(), queue.load(), records.load()]).catch((e) => toast(errorText(e)));
  const mine = (fn) => (e) => { if (e.machine === id) fn(e); };
  const offs = [
    events.on('status', mine(schedule)),
    events.on('machine.state', mine(schedule)),
    events.on('machine.io', mine(() => { schedule(); drawOutputs(); })),
    events.on('runs', schedule),
    events.on('reloaded', schedule),
    events.on('machine.offsets', mine(() => loadOffsets().catch(() => {}))),
    events.on('machine.part_zero', mine(() => loadPartZeros().catch(() => {}))),
    ...QUEUE_EVENTS.map((t) => events.on(t, mine(queue.load))),
    events.on('machine.maintenance_due', mine(() => records.load())),
    events.on('machine.maintenance_done', mine(() => records.load())),
  ];
  // Counters and the chart move slowly: a reload a minute.
  const recordsTick = setInterval(() => records.load(), 60000);
  const onUnits = () => { schedule(); loadPartZeros().catch(() => {}); };
  document.addEventListener('fresa:units', onUnits);
  const tick = setInterval(schedule, 1000);
  return () => {
    offs.forEach((f) => f()); clearInterval(tick); clearInterval(recordsTick); cancelAnimationFrame(frame); run.destroy(); keyboardOff();
    document.removeEventListener('fresa:units', onUnits);
  };
}
