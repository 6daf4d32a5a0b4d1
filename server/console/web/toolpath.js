// Toolpath preview: the server's compact path (README: Toolpath format) drawn with raw WebGL2:
// a top view and an orbit/zoom 3D view, rapids and cuts in different colours, a grid with the
// origin's axes, the bounds box, the part's dimensions and a scale bar; while a job runs the
// remaining path is dimmed and the executed part drawn over it, with the tool as a marker.
//
// Cheap per status (issue 27): the canvas keeps what it drew (preserveDrawingBuffer), so when
// the run advances only the newly executed vertices are drawn on top (one small LINE_STRIP
// range); the tool marker, the dimensions and the scale bar are HTML over the canvas. The whole
// path is drawn again only when the view changes (zoom, pan, mode, size, theme, units) or the
// run goes back. Without WebGL a 2D canvas draws the top view.

import { api } from './api.js';
import { h, display, fixed } from './ui.js';
import { isDark } from './prefs.js';

const HEADER = 48;

/** Parses the binary toolpath. */
export function parseToolpath(buf) {
  const dv = new DataView(buf);
  const magic = String.fromCharCode(...new Uint8Array(buf, 0, 4));
  if (magic !== 'FTP1') throw new Error('not a toolpath (magic ' + JSON.stringify(magic) + ')');
  const n = dv.getUint32(4, true);
  const b = (i) => dv.getFloat32(16 + 4 * i, true);
  return {
    n,
    moves: dv.getUint32(8, true),
    decimation: dv.getFloat32(12, true),
    min: [b(0), b(1), b(2)],
    max: [b(3), b(4), b(5)],
    positions: new Float32Array(buf, HEADER, 3 * n),
    lines: new Uint32Array(buf, HEADER + 12 * n, n),
    kinds: new Uint8Array(buf, HEADER + 16 * n, n),
  };
}

/** How many vertices are executed once `line` is: those whose move's line is at most it
 *  (lines never decrease along the path, so a binary search). */
export function executedCount(lines, line) {
  let lo = 0, hi = lines.length;
  while (lo < hi) {
    const mid = (lo + hi) >>> 1;
    if (lines[mid] <= line) lo = mid + 1; else hi = mid;
  }
  return lo;
}

/** 1, 2 or 5 times a power of ten, at least `x`. */
function niceStep(x) {
  const p = Math.pow(10, Math.floor(Math.log10(x)));
  for (const m of [1, 2, 5, 10]) if (m * p >= x) return m * p;
  return 10 * p;
}

// ---- small matrix helpers (column-major, like GL) ----
function mul(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}
function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
}
function ortho(l, r, b, t, n, f) {
  return new Float32Array([2 / (r - l), 0, 0, 0, 0, 2 / (t - b), 0, 0, 0, 0, -2 / (f - n), 0,
    -(r + l) / (r - l), -(t + b) / (t - b), -(f + n) / (f - n), 1]);
}
function lookAt(eye, c, up) {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const norm = (v) => { const l = Math.hypot(...v) || 1; return v.map((x) => x / l); };
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const z = norm(sub(eye, c)), x = norm(cross(up, z)), y = cross(z, x);
  return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
}
/** Where `p` lands on a `w` x `hh` CSS-pixel canvas under `m`, or null behind the eye. */
function project(m, p, w, hh) {
  const x = m[0] * p[0] + m[4] * p[1] + m[8] * p[2] + m[12];
  const y = m[1] * p[0] + m[5] * p[1] + m[9] * p[2] + m[13];
  const ww = m[3] * p[0] + m[7] * p[1] + m[11] * p[2] + m[15];
  if (ww <= 0) return null;
  return [(x / ww + 1) / 2 * w, (1 - y / ww) / 2 * hh];
}

const VS = `#version 300 es
in vec3 pos; in uint kind;
uniform mat4 mvp; uniform vec4 cut; uniform vec4 rapid; uniform vec4 solid; uniform bool useSolid;
flat out vec4 color;
void main() {
  gl_Position = mvp * vec4(pos, 1.0);
  if (useSolid) color = solid;
  else if (kind == 0u) color = vec4(0.0);
  else if (kind == 1u) color = rapid;
  else color = cut;
}`;
const FS = `#version 300 es
precision mediump float; flat in vec4 color; out vec4 o;
void main() { if (color.a == 0.0) discard; o = color; }`;

// Colours: [r, g, b, a] for the program's path, the remaining part while a run goes on (dimmed),
// and the executed part (green, drawn over everything else).
const CUT = [0.18, 0.42, 0.86, 1], RAPID = [0.93, 0.55, 0.13, 0.6];
const CUT_DIM = [0.18, 0.42, 0.86, 0.28], RAPID_DIM = [0.93, 0.55, 0.13, 0.22];
const DONE = [0.13, 0.72, 0.27, 1], DONE_RAPID = [0.13, 0.72, 0.27, 0.45];

export class ToolpathView {
  constructor(box) {
    this.box = box;
    this.mode = 'top';
    this.yaw = -0.6; this.pitch = 0.9; this.zoom = 1; this.pan = [0, 0];
    this.done = 0; this.tool = null; this.path = null; this.frame = 0;
    // What the canvas shows: the executed vertex count drawn, and whether the view is current.
    this.drawnDone = 0; this.stale = true; this.dimmed = false;
    this.fullDraws = 0; this.partialDraws = 0;
    this.canvas = h('canvas', { class: 'toolpath', width: 800, height: 500, 'aria-label': 'toolpath preview' });
    this.dims = h('span', { class: 'tp-dims', id: 'toolpath-dims' });
    this.scaleLabel = h('span');
    this.scaleBar = h('i');
    this.scale = h('span', { class: 'tp-scale', id: 'toolpath-scale' }, this.scaleLabel, this.scaleBar);
    this.marker = h('span', { class: 'tp-tool', id: 'toolpath-tool', hidden: true, title: 'tool' });
    this.overlay = h('div', { class: 'tp-overlay' }, this.dims, this.scale, this.marker);
    this.stats = h('p', { class: 'muted small toolpath-stats' });
    const btn = (label, fn, id) => h('button', { class: 'small', onclick: fn, dataset: { view: id } }, label);
    this.buttons = h('div', { class: 'row wrap' },
      btn('Top', () => this.setMode('top'), 'top'), btn('3D', () => this.setMode('3d'), '3d'),
      btn('+', () => { this.zoom *= 1.25; this.redraw(); }, 'in'), btn('−', () => { this.zoom /= 1.25; this.redraw(); }, 'out'),
      btn('Fit', () => { this.zoom = 1; this.pan = [0, 0]; this.redraw(); }, 'fit'),
      h('span', { class: 'legend' }, h('i', { class: 'cut' }), 'cut ', h('i', { class: 'rapid' }), 'rapid ', h('i', { class: 'done' }), 'done ', h('i', { class: 'tool' }), 'tool'));
    box.replaceChildren(this.buttons, h('div', { class: 'tp-wrap' }, this.canvas, this.overlay), this.stats);
    this.gl = this.canvas.getContext('webgl2', { antialias: true, preserveDrawingBuffer: true });
    this.ctx2d = this.gl ? null : this.canvas.getContext('2d');
    if (this.gl) this.initGl();
    this.bindInput();
    this.resize = new ResizeObserver(() => this.redraw());
    this.resize.observe(this.canvas);
    this.onPrefs = () => this.redraw();
    document.addEventListener('fresa:theme', this.onPrefs);
    document.addEventListener('fresa:units', this.onPrefs);
  }

  initGl() {
    const gl = this.gl;
    const sh = (type, src) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, src); gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    };
    const p = gl.createProgram();
    gl.attachShader(p, sh(gl.VERTEX_SHADER, VS)); gl.attachShader(p, sh(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    this.prog = p;
    this.loc = { pos: gl.getAttribLocation(p, 'pos'), kind: gl.getAttribLocation(p, 'kind') };
    const u = (n) => gl.getUniformLocation(p, n);
    this.uni = { mvp: u('mvp'), cut: u('cut'), rapid: u('rapid'), solid: u('solid'), useSolid: u('useSolid') };
    this.vao = gl.createVertexArray();
    this.aux = gl.createVertexArray();
    this.auxBuf = gl.createBuffer();
  }

  async load(jobId) {
    const t0 = performance.now();
    const buf = await api('GET', `/jobs/${jobId}/toolpath`);
    const t1 = performance.now();
    const path = parseToolpath(buf);
    this.path = path;
    // For tests and the curious: the path as drawn.
    this.canvas.toolpath = path;
    const c = [0, 1, 2].map((i) => (path.min[i] + path.max[i]) / 2);
    this.center = c;
    this.radius = Math.max(1, Math.hypot(path.max[0] - path.min[0], path.max[1] - path.min[1], path.max[2] - path.min[2]) / 2);
    if (this.gl) {
      const gl = this.gl;
      gl.bindVertexArray(this.vao);
      const attr = (data, loc, size, type, integer) => {
        const b = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, b); gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
        gl.enableVertexAttribArray(loc);
        if (integer) gl.vertexAttribIPointer(loc, size, type, 0, 0);
        else gl.vertexAttribPointer(loc, size, type, false, 0, 0);
      };
      attr(path.positions, this.loc.pos, 3, gl.FLOAT, false);
      attr(path.kinds, this.loc.kind, 1, gl.UNSIGNED_BYTE, true);
      gl.bindVertexArray(null);
    }
    this.stale = true;
    this.drawNow();
    if (this.gl) this.gl.finish();
    const t2 = performance.now();
    this.canvas.dataset.vertices = path.n;
    this.canvas.dataset.decimation = path.decimation;
    this.canvas.dataset.fetchMs = (t1 - t0).toFixed(0);
    this.canvas.dataset.drawMs = (t2 - t1).toFixed(0);
    this.stats.textContent = `${path.n.toLocaleString('en-US')} vertices from ${path.moves.toLocaleString('en-US')} moves` +
      (path.decimation > 0 ? ` (simplified: within ${path.decimation.toPrecision(2)} mm of the exact path)` : '') +
      ` · fetched in ${(t1 - t0).toFixed(0)} ms, drawn in ${(t2 - t1).toFixed(0)} ms` + (this.gl ? '' : ' · 2D fallback (no WebGL)');
  }

  /** Executed up to source `line` (null: unchanged); the tool at `pos` ({x,y,z}) if given.
   *  Costs a binary search and, at the next frame, the newly executed segments only. */
  setProgress(line, pos) {
    if (line !== null && line !== undefined) this.done = line;
    if (pos) this.tool = [pos.x, pos.y, pos.z];
    this.draw();
  }

  setMode(m) { this.mode = m; this.redraw(); }

  /** The whole picture again at the next frame (the view changed). */
  redraw() { this.stale = true; this.draw(); }

  bindInput() {
    // One pointer drags (orbit in 3D, pan in the top view; shift pans in 3D); two pinch-zoom.
    const pointers = new Map();
    let pinch = 0;
    const spread = () => { const [a, b] = [...pointers.values()]; return Math.hypot(a[0] - b[0], a[1] - b[1]); };
    this.canvas.addEventListener('pointerdown', (e) => {
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      this.canvas.setPointerCapture(e.pointerId);
      if (pointers.size === 2) pinch = spread();
    });
    const up = (e) => { pointers.delete(e.pointerId); pinch = 0; };
    this.canvas.addEventListener('pointerup', up);
    this.canvas.addEventListener('pointercancel', up);
    this.canvas.addEventListener('pointermove', (e) => {
      const last = pointers.get(e.pointerId);
      if (!last) return;
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      if (pointers.size === 2) {
        const d = spread();
        if (pinch > 0) this.zoom *= d / pinch;
        pinch = d;
        this.redraw();
        return;
      }
      const dx = e.clientX - last[0], dy = e.clientY - last[1];
      if (this.mode === '3d' && !e.shiftKey) {
        this.yaw -= dx * 0.01;
        this.pitch = Math.max(0.05, Math.min(Math.PI - 0.05, this.pitch - dy * 0.01));
      } else {
        const s = (2 * this.radius * 1.1 / this.zoom) / Math.min(this.canvas.clientHeight, this.canvas.clientWidth);
        this.pan[0] -= dx * s; this.pan[1] += dy * s;
      }
      this.redraw();
    });
    this.canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.zoom *= Math.exp(-e.deltaY * 0.001);
      this.redraw();
    }, { passive: false });
  }

  /** The top view's half extents (mm) for an aspect ratio. */
  extents(aspect) {
    const r = this.radius / this.zoom * 1.1;
    return aspect >= 1 ? [r * aspect, r] : [r, r / aspect];
  }

  matrix(aspect) {
    const c = this.center;
    const cx = c[0] + this.pan[0], cy = c[1] + this.pan[1];
    if (this.mode === 'top') {
      const [w, hh] = this.extents(aspect);
      return ortho(cx - w, cx + w, cy - hh, cy + hh, -1e6, 1e6);
    }
    const d = this.radius * 3 / this.zoom;
    const eye = [cx + d * Math.sin(this.pitch) * Math.cos(this.yaw), cy + d * Math.sin(this.pitch) * Math.sin(this.yaw), c[2] + d * Math.cos(this.pitch)];
    return mul(perspective(0.8, aspect, d / 100, d * 10), lookAt(eye, [cx, cy, c[2]], [0, 0, 1]));
  }

  draw() {
    if (!this.frame) this.frame = requestAnimationFrame(() => { this.frame = 0; this.drawNow(); });
  }

  drawNow() {
    const cv = this.canvas, dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(cv.clientWidth * dpr)), hh = Math.max(1, Math.round(cv.clientHeight * dpr));
    if (cv.width !== w || cv.height !== hh) { cv.width = w; cv.height = hh; this.stale = true; }
    for (const b of this.buttons.querySelectorAll('[data-view]')) b.classList.toggle('active', b.dataset.view === this.mode);
    if (!this.path) return;
    const p = this.path;
    const k = executedCount(p.lines, this.done);
    // The remaining path is dimmed once a run has executed something.
    const dim = k > 1;
    if (dim !== this.dimmed || k < this.drawnDone) this.stale = true;
    this.dimmed = dim;
    const m = this.matrix(w / hh);
    this.m = m;
    if (this.stale) {
      if (this.gl) this.drawGl(m, w, hh, k); else this.draw2d(w, hh, k);
      this.stale = false;
      this.fullDraws++;
    } else if (k > this.drawnDone) {
      if (this.gl) this.drawExecutedGl(m, this.drawnDone, k); else this.draw2d(w, hh, k);
      this.partialDraws++;
    }
    this.drawnDone = k;
    cv.dataset.executed = k;
    cv.dataset.fullDraws = this.fullDraws;
    cv.dataset.partialDraws = this.partialDraws;
    this.drawOverlay(m);
  }

  /** Grid, origin axes, scale bar and dimensions for the view; the tool marker. */
  drawOverlay(m) {
    const cw = this.canvas.clientWidth, ch = this.canvas.clientHeight;
    const p = this.path;
    const unit = display.units === 'in' ? 25.4 : 1;
    const digits = display.units === 'in' ? 3 : 2;
    const size = [0, 1, 2].map((i) => fixed((p.max[i] - p.min[i]) / unit, digits));
    const text = `${size[0]} × ${size[1]} × ${size[2]} ${display.units}`;
    if (this.dims.textContent !== text) this.dims.textContent = text;
    this.dims.title = `X ${fixed(p.min[0] / unit, digits)}…${fixed(p.max[0] / unit, digits)} · Y ${fixed(p.min[1] / unit, digits)}…${fixed(p.max[1] / unit, digits)} · Z ${fixed(p.min[2] / unit, digits)}…${fixed(p.max[2] / unit, digits)} ${display.units}`;
    this.dims.dataset.size = [0, 1, 2].map((i) => (p.max[i] - p.min[i]).toFixed(3)).join(',');
    if (this.mode === 'top' && this.grid) {
      this.scale.hidden = false;
      const px = this.grid.stepMm * cw / (2 * this.extents(cw / ch)[0]);
      this.scaleBar.style.width = px.toFixed(1) + 'px';
      this.scaleLabel.textContent = `${this.grid.step} ${display.units}`;
    } else {
      this.scale.hidden = !this.grid;
      if (this.grid) { this.scaleBar.style.width = '0'; this.scaleLabel.textContent = `grid ${this.grid.step} ${display.units}`; }
    }
    const at = this.tool && project(m, this.tool, cw, ch);
    const inside = at && at[0] >= -20 && at[1] >= -20 && at[0] <= cw + 20 && at[1] <= ch + 20;
    this.marker.hidden = !inside;
    if (inside) this.marker.style.transform = `translate(${at[0].toFixed(1)}px, ${at[1].toFixed(1)}px)`;
  }

  /** Grid lines (a nice step in the display units, ~80 px apart in the top view), the bounds
   *  box and the origin's axes, as [lines..., counts per colour]. */
  helperLines(w, hh) {
    const p = this.path;
    const unit = display.units === 'in' ? 25.4 : 1;
    let lo, hi, z;
    let stepMm;
    if (this.mode === 'top') {
      const [ex, ey] = this.extents(w / hh);
      const cx = this.center[0] + this.pan[0], cy = this.center[1] + this.pan[1];
      stepMm = niceStep(80 * 2 * ex / (this.canvas.clientWidth || 800) / unit) * unit;
      lo = [cx - ex, cy - ey]; hi = [cx + ex, cy + ey]; z = p.min[2];
    } else {
      stepMm = niceStep(this.radius / 4 / unit) * unit;
      lo = [p.min[0] - stepMm, p.min[1] - stepMm]; hi = [p.max[0] + stepMm, p.max[1] + stepMm]; z = p.min[2];
    }
    const grid = [];
    const x0 = Math.floor(lo[0] / stepMm), x1 = Math.ceil(hi[0] / stepMm);
    const y0 = Math.floor(lo[1] / stepMm), y1 = Math.ceil(hi[1] / stepMm);
    if (x1 - x0 < 400 && y1 - y0 < 400) {
      for (let i = x0; i <= x1; i++) grid.push(i * stepMm, y0 * stepMm, z, i * stepMm, y1 * stepMm, z);
      for (let j = y0; j <= y1; j++) grid.push(x0 * stepMm, j * stepMm, z, x1 * stepMm, j * stepMm, z);
      this.grid = { step: +(stepMm / unit).toPrecision(6), stepMm };
    } else {
      this.grid = null;
    }
    const [a, b] = [p.min, p.max];
    const corners = [0, 1, 2, 3, 4, 5, 6, 7].map((i) => [(i & 1 ? b : a)[0], (i & 2 ? b : a)[1], (i & 4 ? b : a)[2]]);
    const edges = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
    const box = [];
    for (const [i, j] of edges) box.push(...corners[i], ...corners[j]);
    const l = Math.max(stepMm, this.radius * 0.15);
    return { grid, box, axes: [[0, 0, 0, l, 0, 0], [0, 0, 0, 0, l, 0], [0, 0, 0, 0, 0, l]] };
  }

  background() {
    const c = getComputedStyle(this.canvas).backgroundColor;
    const m = /rgba?\((\d+), (\d+), (\d+)/.exec(c);
    return m ? [m[1] / 255, m[2] / 255, m[3] / 255] : [0.97, 0.97, 0.96];
  }

  drawGl(m, w, hh, k) {
    const gl = this.gl, p = this.path;
    gl.viewport(0, 0, w, hh);
    const bg = this.background();
    gl.clearColor(bg[0], bg[1], bg[2], 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(this.prog);
    gl.uniformMatrix4fv(this.uni.mvp, false, m);
    // Helpers under the path: grid, bounds box, origin axes.
    const { grid, box, axes } = this.helperLines(w, hh);
    const dark = isDark();
    this.solidLines(grid, dark ? [1, 1, 1, 0.07] : [0, 0, 0, 0.08]);
    this.solidLines(box, dark ? [0.7, 0.7, 0.7, 0.6] : [0.45, 0.45, 0.45, 0.7]);
    // X red, Y magenta, Z cyan: none of them the executed path's green or the cuts' blue.
    const axisColours = [[0.9, 0.2, 0.2, 1], [0.8, 0.25, 0.75, 1], [0.1, 0.75, 0.85, 1]];
    axes.forEach((a, i) => { if (i < 2 || this.mode === '3d') this.solidLines(a, axisColours[i]); });
    // The path: whole (dimmed while a run goes on), then the executed part over it.
    gl.useProgram(this.prog);
    gl.uniform1i(this.uni.useSolid, 0);
    gl.bindVertexArray(this.vao);
    gl.uniform4fv(this.uni.cut, this.dimmed ? CUT_DIM : CUT);
    gl.uniform4fv(this.uni.rapid, this.dimmed ? RAPID_DIM : RAPID);
    gl.drawArrays(gl.LINE_STRIP, 0, p.n);
    gl.bindVertexArray(null);
    if (k > 1) this.drawExecutedGl(m, 0, k);
  }

  /** Draws the executed vertices `from`-1 .. `to`-1 over what the canvas shows. */
  drawExecutedGl(m, from, to) {
    const gl = this.gl;
    const first = Math.max(0, from - 1);
    if (to - first < 2) return;
    gl.useProgram(this.prog);
    gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.uniformMatrix4fv(this.uni.mvp, false, m);
    gl.uniform1i(this.uni.useSolid, 0);
    gl.uniform4fv(this.uni.cut, DONE);
    gl.uniform4fv(this.uni.rapid, DONE_RAPID);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.LINE_STRIP, first, to - first);
    gl.bindVertexArray(null);
  }

  /** Plain lines (x,y,z pairs) in one colour, from a small buffer of their own. */
  solidLines(coords, colour) {
    if (!coords.length) return;
    const gl = this.gl;
    gl.bindVertexArray(this.aux);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.auxBuf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(coords), gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(this.loc.pos);
    gl.vertexAttribPointer(this.loc.pos, 3, gl.FLOAT, false, 0, 0);
    // A generic value for the integer attribute this VAO does not feed: WebGL2 refuses a draw
    // whose default (float) attribute type differs from the shader's `uint`.
    gl.disableVertexAttribArray(this.loc.kind);
    gl.vertexAttribI4ui(this.loc.kind, 2, 0, 0, 0);
    gl.uniform1i(this.uni.useSolid, 1);
    gl.uniform4fv(this.uni.solid, colour);
    gl.drawArrays(gl.LINES, 0, coords.length / 3);
    gl.bindVertexArray(null);
  }

  draw2d(w, hh, k) {
    const ctx = this.ctx2d, p = this.path, r = this.radius / this.zoom * 1.1;
    const s = Math.min(w, hh) / (2 * r), cx = this.center[0] + this.pan[0], cy = this.center[1] + this.pan[1];
    const X = (x) => w / 2 + (x - cx) * s, Y = (y) => hh / 2 - (y - cy) * s;
    const bg = this.background().map((v) => Math.round(v * 255));
    ctx.fillStyle = `rgb(${bg.join(',')})`; ctx.fillRect(0, 0, w, hh);
    this.helperLines(w, hh);
    ctx.strokeStyle = '#999'; ctx.strokeRect(X(p.min[0]), Y(p.max[1]), (p.max[0] - p.min[0]) * s, (p.max[1] - p.min[1]) * s);
    // One path per colour: a stroke per segment would be far too slow for large programs.
    const pos = p.positions;
    const rgba = (c) => `rgba(${c.slice(0, 3).map((v) => Math.round(v * 255)).join(',')},${c[3]})`;
    const styles = [[1, 'rapid'], [2, 'cut'], [1, 'done'], [2, 'done']];
    for (const [kind, which] of styles) {
      const done = which === 'done';
      ctx.strokeStyle = rgba(done ? (kind === 2 ? DONE : DONE_RAPID) : kind === 2 ? (this.dimmed ? CUT_DIM : CUT) : (this.dimmed ? RAPID_DIM : RAPID));
      ctx.beginPath();
      const [from, to] = done ? [1, k] : [1, p.n];
      for (let i = from; i < to; i++) {
        if (p.kinds[i] !== kind) continue;
        ctx.moveTo(X(pos[3 * i - 3]), Y(pos[3 * i - 2]));
        ctx.lineTo(X(pos[3 * i]), Y(pos[3 * i + 1]));
      }
      ctx.stroke();
    }
  }

  destroy() {
    this.resize.disconnect();
    document.removeEventListener('fresa:theme', this.onPrefs);
    document.removeEventListener('fresa:units', this.onPrefs);
    if (this.frame) cancelAnimationFrame(this.frame);
    const ext = this.gl && this.gl.getExtension('WEBGL_lose_context');
    if (ext) ext.loseContext();
  }
}
