// Why a machine holds (issue 26) and the one button that goes on, on the machine page and the
// job page; and the tool setter's "Measure tool" (issue 25). The reason is the status's `hold`
// (the job view's for a job), as the server explains it.

import { api } from './api.js';
import { state, h, gate, act, errorText, mm } from './ui.js';

/** The hold in words: its message, with the program's own `(MSG, ...)` text. */
export function holdText(hold) {
  if (!hold) return '';
  const msg = hold.program_message;
  return msg && !hold.message.includes(msg) ? `${hold.message}: ${msg}` : hold.message;
}

/** The button that goes on after `hold`. */
export function continueLabel(hold) {
  return hold && hold.continue_with === 'cycle_start' ? 'Cycle start' : 'Resume';
}

/** The machine page's hold banner (under the header, while it holds: the reason and the button
 *  that applies, also marked among the Cycle card's) and its tool-change card (Measure tool,
 *  idle or held for a tool change: then for the new tool). */
export function holdBlock(id, page) {
  const reason = h('p', { id: 'hold-reason', class: 'hold-reason' });
  const blocked = h('p', { id: 'hold-blocked', class: 'error' });
  const go = h('button', { id: 'hold-continue', class: 'applies', dataset: { need: 'motion' }, onclick: (ev) => {
    const command = ev.currentTarget.dataset.continue;
    act(ev.currentTarget, () => api('POST', `/machines/${id}/commands`, { command }), `${ev.currentTarget.textContent} sent`).catch(() => {});
  } }, 'Cycle start');
  const tool = h('input', { id: 'measure-tool-number', type: 'number', min: 1, step: 1, value: 1, 'aria-label': 'tool number' });
  const result = h('p', { id: 'measure-result', class: 'muted' });
  const measure = h('button', { id: 'measure-tool', dataset: { need: 'motion', when: 'no-run', toolChange: 'ok' }, onclick: async (ev) => {
    const n = parseInt(tool.value, 10);
    result.className = 'muted';
    result.textContent = `Measuring T${n} on the tool setter…`;
    try {
      const r = await act(ev.currentTarget, () => api('POST', `/machines/${id}/tools/${n}/measure`), `T${n} measured`);
      let text = `T${n}: tripped at machine Z ${mm(r.trip_z)}, length ${mm(r.length_mm)} mm (from the reference at Z ${mm(r.reference_z)})`;
      if (r.rezero) text += `; ${r.rezero.offset} Z ${mm(r.rezero.before.z)} → ${mm(r.rezero.after.z)} for the new tool`;
      if (r.note) text += `; ${r.note}`;
      result.textContent = text;
    } catch (e) {
      result.className = 'error';
      result.textContent = errorText(e);
    }
  } }, 'Measure tool');
  const banner = h('section', { class: 'card hold-banner', id: 'hold-banner', hidden: true },
    h('div', { class: 'row wrap' }, reason, go), blocked);
  const el = h('section', { class: 'card', id: 'hold-card', dataset: { whyGroup: '' } }, h('h2', {}, 'Tool setter'), h('p', { class: 'why', hidden: true }),
    h('div', { class: 'row wrap' }, h('label', {}, 'Tool ', tool), measure), result);
  let shownTool = null;
  return {
    banner,
    el,
    update() {
      const s = state.status.get(id) || {};
      const hold = s.hold;
      reason.textContent = hold ? `Held: ${holdText(hold)}` : s.state === 'paused' ? 'Paused' : 'Not held';
      blocked.textContent = (hold && hold.blocked) || '';
      banner.hidden = !hold && s.state !== 'paused';
      go.hidden = !hold;
      if (hold) {
        go.textContent = continueLabel(hold);
        go.dataset.continue = hold.continue_with;
      }
      // The new tool of a change is the one to measure.
      const to = hold && hold.tool_change ? hold.tool_change.to : null;
      if (to !== shownTool && document.activeElement !== tool) {
        if (to) tool.value = to;
        shownTool = to;
      }
      for (const b of page.querySelectorAll('[data-cmd="cycle_start"], [data-cmd="resume"]')) {
        b.classList.toggle('applies', !!hold && b.dataset.cmd === hold.continue_with);
      }
      gate(banner);
      gate(el);
    },
  };
}

/** The machine's job queue (issue 28): a banner while it waits for the next part (which part,
 *  and the button that starts it once it is loaded) or holds (why, and Release). */
export function queueBanner(id) {
  const text = h('p', { id: 'queue-text', class: 'hold-reason' });
  const load = () => api('GET', `/machines/${id}/queue`).then(show).catch(() => {});
  const confirm = h('button', { id: 'queue-confirm', class: 'applies', dataset: { need: 'motion' }, onclick: (ev) =>
    act(ev.currentTarget, () => api('POST', `/machines/${id}/queue/confirm`), 'Part started').then(load).catch(() => {}) }, 'Part loaded: start');
  const release = h('button', { id: 'queue-release', dataset: { need: 'motion' }, onclick: (ev) =>
    act(ev.currentTarget, () => api('POST', `/machines/${id}/queue/release`), 'Queue released').then(load).catch(() => {}) }, 'Release');
  const el = h('section', { class: 'card hold-banner', id: 'queue-banner', hidden: true },
    h('div', { class: 'row wrap' }, text, confirm, release));
  function show(q) {
    const entry = (q.entries || []).find((e) => e.id === q.entry);
    el.hidden = q.state !== 'waiting_confirm' && q.state !== 'held';
    confirm.hidden = q.state !== 'waiting_confirm';
    release.hidden = q.state !== 'held';
    text.textContent = q.state === 'held' ? `Queue held: ${q.reason || 'no reason recorded'}`
      : entry ? `Queue: part ${entry.done + 1} of ${entry.count} (job ${entry.job}) waits for its confirm`
      : 'Queue: the next part waits for its confirm';
    gate(el);
  }
  return { el, load };
}
