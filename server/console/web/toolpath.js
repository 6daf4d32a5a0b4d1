// Toolpath preview: the server's compact path (README: Toolpath format) drawn with raw WebGL2:
// a top view and an orbit/zoom 3D view, rapids and cuts in different colours, the bounds box,
// the executed part and the tool position while a job runs. Without WebGL a 2D canvas draws
// the top view.

import { api } from './api.js';
import { h } from './ui.js';

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

const VS = `#version 300 es
in vec3 pos; in uint line; in uint kind;
uniform mat4 mvp; uniform uint done; uniform vec4 solid; uniform bool useSolid;
flat out vec4 color;
void main() {
  gl_Position = mvp * vec4(pos, 1.0);
  if (useSolid) { color = solid; return; }
  if (kind == 0u) color = vec4(0.0);
  else if (line <= done) color = vec4(0.16, 0.66, 0.27, 1.0);
  else if (kind == 1u) color = vec4(0.93, 0.55, 0.13, 0.55);
  else color = vec4(0.18, 0.42, 0.86, 1.0);
}`;
const FS = `#version 300 es
precision mediump float; flat in vec4 color; out vec4 o;
void main() { if (color.a == 0.0) discard; o = color; }`;

export class ToolpathView {
  constructor(box) {
    this.box = box;
    this.mode = 'top';
    this.yaw = -0.6; this.pitch = 0.9; this.zoom = 1; this.pan = [0, 0];
    this.done = 0; this.tool = null; this.path = null; this.frame = 0;
    this.canvas = h('canvas', { class: 'toolpath', width: 800, height: 500, 'aria-label': 'toolpath preview' });
    this.stats = h('p', { class: 'muted small toolpath-stats' });
    const btn = (label, fn, id) => h('button', { class: 'small', onclick: fn, dataset: { view: id } }, label);
    this.buttons = h('div', { class: 'row' },
      btn('Top', () => this.setMode('top'), 'top'), btn('3D', () => this.setMode('3d'), '3d'),
      btn('+', () => { this.zoom *= 1.25; this.draw(); }, 'in'), btn('−', () => { this.zoom /= 1.25; this.draw(); }, 'out'),
      btn('Fit', () => { this.zoom = 1; this.pan = [0, 0]; this.draw(); }, 'fit'),
      h('span', { class: 'legend' }, h('i', { class: 'cut' }), 'cut ', h('i', { class: 'rapid' }), 'rapid ', h('i', { class: 'done' }), 'done ', h('i', { class: 'tool' }), 'tool'));
    box.replaceChildren(this.buttons, this.canvas, this.stats);
    this.gl = this.canvas.getContext('webgl2', { antialias: true, preserveDrawingBuffer: true });
    this.ctx2d = this.gl ? null : this.canvas.getContext('2d');
    if (this.gl) this.initGl();
    this.bindInput();
    this.resize = new ResizeObserver(() => this.draw());
    this.resize.observe(this.canvas);
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
    this.loc = { pos: gl.getAttribLocation(p, 'pos'), line: gl.getAttribLocation(p, 'line'), kind: gl.getAttribLocation(p, 'kind') };
    this.uni = { mvp: gl.getUniformLocation(p, 'mvp'), done: gl.getUniformLocation(p, 'done'), solid: gl.getUniformLocation(p, 'solid'), useSolid: gl.getUniformLocation(p, 'useSolid') };
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
      attr(path.lines, this.loc.line, 1, gl.UNSIGNED_INT, true);
      attr(path.kinds, this.loc.kind, 1, gl.UNSIGNED_BYTE, true);
      gl.bindVertexArray(null);
    }
    this.drawNow();
    if (this.gl) this.gl.finish();
    const t2 = performance.now();
    this.canvas.dataset.vertices = path.n;
    this.canvas.dataset.fetchMs = (t1 - t0).toFixed(0);
    this.canvas.dataset.drawMs = (t2 - t1).toFixed(0);
    this.stats.textContent = `${path.n.toLocaleString()} vertices from ${path.moves.toLocaleString()} moves` +
      (path.decimation > 0 ? ` (merged below ${path.decimation.toPrecision(2)} mm)` : '') +
      ` · fetched in ${(t1 - t0).toFixed(0)} ms, drawn in ${(t2 - t1).toFixed(0)} ms` + (this.gl ? '' : ' · 2D fallback (no WebGL)');
  }

  /** Executed up to source `line` (null: unchanged); the tool at `pos` ({x,y,z}) if given. */
  setProgress(line, pos) {
    if (line !== null && line !== undefined) this.done = line;
    if (pos) this.tool = [pos.x, pos.y, pos.z];
    this.draw();
  }

  setMode(m) { this.mode = m; this.draw(); }

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
        this.draw();
        return;
      }
      const dx = e.clientX - last[0], dy = e.clientY - last[1];
      if (this.mode === '3d' && !e.shiftKey) {
        this.yaw -= dx * 0.01;
        this.pitch = Math.max(0.05, Math.min(Math.PI - 0.05, this.pitch - dy * 0.01));
      } else {
        const s = (2 * this.radius / this.zoom) / this.canvas.clientHeight;
        this.pan[0] -= dx * s; this.pan[1] += dy * s;
      }
      this.draw();
    });
    this.canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.zoom *= Math.exp(-e.deltaY * 0.001);
      this.draw();
    }, { passive: false });
  }

  matrix(aspect) {
    const c = this.center, r = this.radius / this.zoom;
    const cx = c[0] + this.pan[0], cy = c[1] + this.pan[1];
    if (this.mode === 'top') {
      const w = aspect >= 1 ? r * 1.1 * aspect : r * 1.1, hh = aspect >= 1 ? r * 1.1 : r * 1.1 / aspect;
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
    if (cv.width !== w || cv.height !== hh) { cv.width = w; cv.height = hh; }
    for (const b of this.buttons.querySelectorAll('[data-view]')) b.classList.toggle('active', b.dataset.view === this.mode);
    if (!this.path) return;
    const m = this.matrix(w / hh);
    if (this.gl) this.drawGl(m, w, hh); else this.draw2d(w, hh);
  }

  drawGl(m, w, hh) {
    const gl = this.gl, p = this.path;
    gl.viewport(0, 0, w, hh);
    gl.clearColor(0.97, 0.97, 0.96, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(this.prog);
    gl.uniformMatrix4fv(this.uni.mvp, false, m);
    gl.uniform1ui(this.uni.done, this.done >>> 0);
    gl.uniform1i(this.uni.useSolid, 0);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.LINE_STRIP, 0, p.n);
    // Bounds box and tool: plain lines in one colour each.
    const [a, b] = [p.min, p.max];
    const corners = [0, 1, 2, 3, 4, 5, 6, 7].map((i) => [(i & 1 ? b : a)[0], (i & 2 ? b : a)[1], (i & 4 ? b : a)[2]]);
    const edges = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
    const lines = [];
    for (const [i, j] of edges) lines.push(...corners[i], ...corners[j]);
    const boxCount = lines.length / 3;
    if (this.tool) {
      const [x, y, z] = this.tool, s = this.radius * 0.06;
      lines.push(x - s, y, z, x + s, y, z, x, y - s, z, x, y + s, z, x, y, z, x, y, z + 3 * s);
    }
    gl.bindVertexArray(this.aux);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.auxBuf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(lines), gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(this.loc.pos);
    gl.vertexAttribPointer(this.loc.pos, 3, gl.FLOAT, false, 0, 0);
    // Generic values for the integer attributes this VAO does not feed: WebGL2 refuses a draw
    // whose default (float) attribute type differs from the shader's `uint`.
    gl.disableVertexAttribArray(this.loc.line);
    gl.disableVertexAttribArray(this.loc.kind);
    gl.vertexAttribI4ui(this.loc.line, 0, 0, 0, 0);
    gl.vertexAttribI4ui(this.loc.kind, 2, 0, 0, 0);
    gl.uniform1i(this.uni.useSolid, 1);
    gl.uniform4f(this.uni.solid, 0.55, 0.55, 0.55, 0.8);
    gl.drawArrays(gl.LINES, 0, boxCount);
    if (this.tool) {
      gl.uniform4f(this.uni.solid, 0.85, 0.1, 0.1, 1);
      gl.drawArrays(gl.LINES, boxCount, 6);
    }
    gl.bindVertexArray(null);
  }

  draw2d(w, hh) {
    const ctx = this.ctx2d, p = this.path, r = this.radius / this.zoom * 1.1;
    const s = Math.min(w, hh) / (2 * r), cx = this.center[0] + this.pan[0], cy = this.center[1] + this.pan[1];
    const X = (x) => w / 2 + (x - cx) * s, Y = (y) => hh / 2 - (y - cy) * s;
    ctx.fillStyle = '#f7f7f5'; ctx.fillRect(0, 0, w, hh);
    ctx.strokeStyle = '#999'; ctx.strokeRect(X(p.min[0]), Y(p.max[1]), (p.max[0] - p.min[0]) * s, (p.max[1] - p.min[1]) * s);
    // One path per colour: a stroke per segment would be far too slow for large programs.
    const pos = p.positions;
    const styles = ['#2a4', 'rgba(237,140,33,0.55)', '#2e6bdb'];
    for (let style = 0; style < 3; style++) {
      ctx.strokeStyle = styles[style];
      ctx.beginPath();
      for (let i = 1; i < p.n; i++) {
        const k = p.lines[i] <= this.done ? 0 : p.kinds[i];
        if (k !== style) continue;
        ctx.moveTo(X(pos[3 * i - 3]), Y(pos[3 * i - 2]));
        ctx.lineTo(X(pos[3 * i]), Y(pos[3 * i + 1]));
      }
      ctx.stroke();
    }
    if (this.tool) { ctx.fillStyle = '#d11'; ctx.beginPath(); ctx.arc(X(this.tool[0]), Y(this.tool[1]), 5, 0, 7); ctx.fill(); }
  }

  destroy() {
    this.resize.disconnect();
    if (this.frame) cancelAnimationFrame(this.frame);
    const ext = this.gl && this.gl.getExtension('WEBGL_lose_context');
    if (ext) ext.loseContext();
  }
}
