// Height maps (issue 25): probe a grid over an area (form), follow it live, show a map as a
// colour plot with its legend, list and delete maps; and the "with height map" choice a job's
// start offers (`heightMapChoice`), with how the chosen map fits the program.

import { api } from './api.js';
import { state, h, gate, act, toast, errorText, time, machineName } from './ui.js';

/** Blue (low) → cyan → green → yellow → red (high), for t in 0..1. */
export function colour(t) {
  const stops = [[0, [49, 54, 149]], [0.25, [69, 160, 210]], [0.5, [102, 189, 99]], [0.75, [254, 224, 90]], [1, [215, 48, 39]]];
  const x = Math.max(0, Math.min(1, isFinite(t) ? t : 0.5));
  for (let k = 1; k < stops.length; k++) {
    const [t1, c1] = stops[k];
    const [t0, c0] = stops[k - 1];
    if (x <= t1) {
      const f = (x - t0) / (t1 - t0);
      return c0.map((v, i) => Math.round(v + (c1[i] - v) * f));
    }
  }
  return stops[stops.length - 1][1];
}

/**
 * Draws `map` (as the API shows it) on `canvas`: each pixel coloured by the height there,
 * bilinear between the four points around it where they are probed (as the job applies it),
 * the nearest probed point's otherwise, grey where nothing near is probed yet; the points as
 * dots. Returns the range drawn ([min, max]) or null.
 */
export function drawMap(canvas, map) {
  const ctx = canvas.getContext('2d');
  const W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  const { nx, ny, points } = map;
  const probed = points.filter((z) => typeof z === 'number');
  if (!probed.length) {
    ctx.fillStyle = '#ddd';
    ctx.fillRect(0, 0, W, H);
    return null;
  }
  const lo = Math.min(...probed), hi = Math.max(...probed);
  const span = hi - lo || 1;
  const at = (i, j) => points[j * nx + i];
  const img = ctx.createImageData(W, H);
  for (let py = 0; py < H; py++) {
    // Y up on screen: the first row of the map is at the bottom.
    const v = (1 - py / (H - 1)) * (ny - 1);
    const j = Math.min(ny - 2, Math.floor(v)), fy = v - j;
    for (let px = 0; px < W; px++) {
      const u = (px / (W - 1)) * (nx - 1);
      const i = Math.min(nx - 2, Math.floor(u)), fx = u - i;
      const c = [at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1)];
      let z;
      if (c.every((q) => typeof q === 'number')) {
        z = (c[0] * (1 - fx) + c[1] * fx) * (1 - fy) + (c[2] * (1 - fx) + c[3] * fx) * fy;
      } else {
        z = at(Math.round(u), Math.round(v));
      }
      const o = (py * W + px) * 4;
      const rgb = typeof z === 'number' ? colour((z - lo) / span) : [221, 221, 221];
      img.data[o] = rgb[0]; img.data[o + 1] = rgb[1]; img.data[o + 2] = rgb[2]; img.data[o + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  ctx.fillStyle = '#000';
  for (let j = 0; j < ny; j++) {
    for (let i = 0; i < nx; i++) {
      const x = (i / (nx - 1)) * (W - 1), y = (1 - j / (ny - 1)) * (H - 1);
      ctx.beginPath();
      ctx.arc(Math.max(2, Math.min(W - 2, x)), Math.max(2, Math.min(H - 2, y)), typeof at(i, j) === 'number' ? 2 : 1, 0, 2 * Math.PI);
      ctx.fill();
    }
  }
  return [lo, hi];
}

/** The colour scale with the range (mm). */
function legend(range) {
  if (!range) return h('p', { class: 'muted', id: 'hm-legend' }, 'no point probed yet');
  const bar = h('canvas', { width: 200, height: 12, class: 'hm-scale' });
  const ctx = bar.getContext('2d');
  for (let x = 0; x < 200; x++) {
    const [r, g, b] = colour(x / 199);
    ctx.fillStyle = `rgb(${r},${g},${b})`;
    ctx.fillRect(x, 0, 1, 12);
  }
  return h('div', { class: 'row hm-legend', id: 'hm-legend' },
    h('span', { class: 'num', dataset: { min: range[0] } }, range[0].toFixed(4)), bar,
    h('span', { class: 'num', dataset: { max: range[1] } }, range[1].toFixed(4)),
    h('span', { class: 'muted' }, `mm (range ${(range[1] - range[0]).toFixed(4)} mm)`));
}

const FIELDS = [
  ['x0', 'X from', 0], ['x1', 'X to', 50], ['y0', 'Y from', 0], ['y1', 'Y to', 30],
  ['nx', 'points X', 6], ['ny', 'points Y', 4], ['clearance', 'clearance Z', 2],
  ['distance', 'probe depth', 5], ['feed', 'probe feed', 100],
];

/** The page `#/machines/{id}/height-maps`. */
export async function heightMapPage(page, { id }, events) {
  const m = state.machines.get(id) || await api('GET', `/machines/${id}`);
  const inputs = {};
  const form = h('form', { class: 'row wrap', id: 'hm-form' }, FIELDS.map(([k, label, v]) =>
    h('label', {}, label + ' ', (inputs[k] = h('input', { type: 'number', step: 'any', value: v, name: k, id: 'hm-' + k, 'aria-label': label, required: true })))),
  h('button', { type: 'submit', class: 'primary', dataset: { need: 'motion' }, id: 'hm-start' }, 'Probe grid'));
  const formError = h('p', { class: 'error', id: 'hm-error' });
  const progress = h('progress', { id: 'hm-progress', max: 1, value: 0, hidden: true });
  const canvas = h('canvas', { width: 480, height: 320, id: 'hm-plot', class: 'hm-plot' });
  const legendBox = h('div');
  const title = h('h2', { id: 'hm-title' }, 'Map');
  const info = h('p', { class: 'muted', id: 'hm-info' });
  const tbody = h('tbody');
  let shown = null;  // the map on the plot

  const show = (map) => {
    shown = map;
    title.textContent = `Map ${map.id} · ${map.state}`;
    info.textContent = `X ${map.x0}…${map.x1} · Y ${map.y0}…${map.y1} · ${map.nx} × ${map.ny} points · ` +
      `${map.probed} probed · by ${map.created_by}, ${time(map.created_at)}${map.message ? ' · ' + map.message : ''}`;
    legendBox.replaceChildren(legend(drawMap(canvas, map)));
  };

  const reload = async () => {
    const maps = await api('GET', `/machines/${id}/height-maps`);
    tbody.replaceChildren(...(maps.length ? maps.map((map) => h('tr', { dataset: { map: map.id } },
      h('td', {}, String(map.id)),
      h('td', {}, h('span', { class: 'badge state-' + (map.state === 'complete' ? 'completed' : map.state) }, map.state)),
      h('td', { class: 'num' }, `${map.probed}/${map.nx * map.ny}`),
      h('td', { class: 'num' }, map.min === null ? '—' : `${map.min.toFixed(3)} … ${map.max.toFixed(3)}`),
      h('td', {}, map.created_by), h('td', {}, time(map.created_at)),
      h('td', {}, h('div', { class: 'row wrap' },
        h('button', { onclick: () => show(map), dataset: { show: map.id } }, 'Show'),
        h('button', { class: 'danger', dataset: { need: 'operator', delete: map.id, off: map.state === 'probing' ? '1' : '' },
          onclick: (ev) => act(ev.currentTarget, () => api('DELETE', `/machines/${id}/height-maps/${map.id}`), `Map ${map.id} deleted`)
            .then(reload).catch(() => {}) }, 'Delete'))))) :
      [h('tr', {}, h('td', { colspan: 7, class: 'muted' }, 'no maps yet'))]));
    gate(tbody);
    if (!shown && maps.length) show(maps[0]);
    else if (shown) {
      const again = maps.find((x) => x.id === shown.id);
      if (again) show(again);
    }
  };

  form.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    formError.textContent = '';
    const body = {};
    for (const [k] of FIELDS) body[k] = parseFloat(inputs[k].value);
    try {
      const map = await act(form.querySelector('button'), () => api('POST', `/machines/${id}/height-maps`, body), 'Probing started');
      progress.hidden = false; progress.max = map.nx * map.ny; progress.value = 0;
      show(map);
      await reload();
    } catch (e) { formError.textContent = errorText(e); }
  });

  page.append(h('p', {}, h('a', { href: `#/machines/${id}` }, `← ${m.name}`)),
    h('h1', {}, `Height maps · ${machineName(id)}`),
    h('section', { class: 'card' }, h('h2', {}, 'Probe a grid'),
      h('p', { class: 'muted small' }, 'Work coordinates, mm. Zero Z on the stock first: each point records the work Z where the probe touches, ' +
        'and a job run with the map adds the height under the tool to every Z. STOP ends the grid.'),
      form, formError, progress),
    h('div', { class: 'cols' },
      h('section', { class: 'card' }, title, canvas, legendBox, info),
      h('section', { class: 'card' }, h('h2', {}, 'Maps'),
        h('table', { class: 'jobs', id: 'hm-list' }, h('thead', {}, h('tr', {}, ['#', 'state', 'points', 'Z range', 'by', 'when', ''].map((t) => h('th', {}, t)))), tbody))));
  await reload();

  const offs = [
    events.on('height_map.progress', (e) => {
      if (e.machine !== id) return;
      const d = e.data;
      progress.hidden = false; progress.max = d.total; progress.value = d.done;
      if (shown && shown.id === d.map) {
        shown.points[d.j * shown.nx + d.i] = d.z;
        shown.probed = d.done;
        show(shown);
      }
    }),
    events.on('height_map.ended', (e) => {
      if (e.machine !== id) return;
      progress.hidden = true;
      if (e.data.state !== 'complete') toast(`Height map ${e.data.map} ${e.data.state}: ${e.data.message || ''}`);
      reload().catch(() => {});
    }),
    events.on('height_map.deleted', (e) => { if (e.machine === id) reload().catch(() => {}); }),
  ];
  return () => offs.forEach((f) => f());
}

/**
 * The "with height map" choice of a job's start: a select of the machine's complete maps and
 * how the chosen one fits the job (`GET .../fit`: overhang, correction range). `body()` is what
 * the start sends (`{height_map: id}`, or undefined without a map).
 */
export function heightMapChoice(machine, job) {
  const sel = h('select', { id: 'start-height-map', 'aria-label': 'height map' }, h('option', { value: '' }, 'no height map'));
  const fit = h('span', { class: 'muted small', id: 'height-map-fit' });
  const load = async () => {
    try {
      const maps = (await api('GET', `/machines/${machine}/height-maps`)).filter((m) => m.state === 'complete');
      const keep = sel.value;
      sel.replaceChildren(h('option', { value: '' }, 'no height map'), ...maps.map((m) =>
        h('option', { value: m.id }, `map ${m.id}: ${m.nx}×${m.ny}, X ${m.x0}…${m.x1} Y ${m.y0}…${m.y1}`)));
      sel.value = keep;
    } catch (_) { /* the select stays as it was */ }
  };
  sel.addEventListener('change', async () => {
    fit.textContent = '';
    fit.className = 'muted small';
    if (!sel.value) return;
    try {
      const f = await api('GET', `/machines/${machine}/height-maps/${sel.value}/fit?job=${job}`);
      fit.textContent = f.fits
        ? `fits · Z correction ${f.correction_min.toFixed(4)} … ${f.correction_max.toFixed(4)} mm over the program`
        : f.overhang;
      if (!f.fits) fit.className = 'error small';
    } catch (e) { fit.textContent = errorText(e); fit.className = 'error small'; }
  });
  load();
  return {
    el: h('div', { class: 'row wrap' }, h('label', {}, 'Start with ', sel), fit),
    body: () => (sel.value ? { height_map: +sel.value } : undefined),
  };
}
