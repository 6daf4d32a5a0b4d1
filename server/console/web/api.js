// The server: JSON calls with the session's token, uploads with progress, and the one event
// stream every page listens to. Nothing here touches the page.

const TOKEN_KEY = 'fresa.token';

export function token() {
  return sessionStorage.getItem(TOKEN_KEY) || '';
}

export function setToken(t) {
  if (t) sessionStorage.setItem(TOKEN_KEY, t);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** An API error: HTTP status, the server's stable code and its message. */
export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

function headers(extra) {
  const h = Object.assign({}, extra);
  const t = token();
  if (t) h['Authorization'] = 'Bearer ' + t;
  return h;
}

async function failure(res) {
  let code = 'http_' + res.status;
  let message = res.statusText || ('HTTP ' + res.status);
  try {
    const body = await res.json();
    if (body && body.code) { code = body.code; message = body.message || message; }
  } catch (_) { /* not JSON */ }
  return new ApiError(res.status, code, message);
}

/** `api('GET', '/machines')`: the JSON answer, or throws ApiError. */
export async function api(method, path, body) {
  const init = { method, headers: headers(body === undefined ? {} : { 'content-type': 'application/json' }) };
  if (body !== undefined) init.body = JSON.stringify(body);
  let res;
  try {
    res = await fetch('/api/v1' + path, init);
  } catch (e) {
    throw new ApiError(0, 'network', 'the server did not answer: ' + e.message);
  }
  if (!res.ok) throw await failure(res);
  if (res.status === 204) return null;
  const type = res.headers.get('content-type') || '';
  if (type.includes('application/json')) return res.json();
  if (type.includes('octet-stream')) return res.arrayBuffer();
  return res.text();
}

/** Uploads a program as multipart form with a progress callback (0..1). */
export function upload(machine, file, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open('POST', '/api/v1/jobs?machine=' + encodeURIComponent(machine) +
      '&name=' + encodeURIComponent(file.name.replace(/\.[^.]*$/, '').slice(0, 100)));
    const t = token();
    if (t) xhr.setRequestHeader('Authorization', 'Bearer ' + t);
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
    xhr.onerror = () => reject(new ApiError(0, 'network', 'the upload was interrupted'));
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch (_) { /* not JSON */ }
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else reject(new ApiError(xhr.status, body && body.code || 'http_' + xhr.status,
        body && body.message || xhr.statusText));
    };
    const form = new FormData();
    form.append('file', file, file.name);
    xhr.send(form);
  });
}

/**
 * The live event stream. `on(type, fn)` listens ('*' for all); `onConnection(fn)` hears
 * true/false as the stream comes and goes. EventSource reconnects by itself and sends
 * Last-Event-ID, so persisted events are not lost; listeners of 'open' reload their state.
 */
/** Every event type the server sends (README: event stream). */
export const EVENT_TYPES = ['status', 'machine.state', 'machine.io', 'job.progress', 'job.state', 'job.created',
  'machine.created', 'machine.offsets', 'machine.part_zero', 'machine.touch_off', 'machine.alarm', 'machine.command',
  'machine.jog', 'machine.jog_cancel', 'machine.mdi', 'pendant.created', 'pendant.connected', 'pendant.lost', 'pendant.bound',
  'pendant.macro', 'pendant.refused', 'pendant.deleted', 'pendant.upload', 'pendant.upload_rejected',
  'pendant.rewind', 'job.line_report', 'height_map.progress', 'height_map.ended', 'height_map.deleted',
  'queue.add', 'queue.remove', 'queue.move', 'queue.waiting_confirm', 'queue.confirm', 'queue.started', 'queue.hold',
  'queue.release', 'queue.done', 'queue.dispatch', 'resync'];

/** A machine's job queue changed (issue 28). */
export const QUEUE_EVENTS = EVENT_TYPES.filter((t) => t.startsWith('queue.'));

export class Events {
  constructor() {
    this.listeners = new Map();
    this.connListeners = new Set();
    this.connected = false;
    this.source = null;
  }

  on(type, fn) {
    if (!this.listeners.has(type)) this.listeners.set(type, new Set());
    this.listeners.get(type).add(fn);
    return () => this.listeners.get(type).delete(fn);
  }

  onConnection(fn) {
    this.connListeners.add(fn);
    return () => this.connListeners.delete(fn);
  }

  setConnected(c) {
    if (c === this.connected) return;
    this.connected = c;
    for (const fn of this.connListeners) fn(c);
  }

  dispatch(type, raw) {
    let ev;
    try { ev = JSON.parse(raw); } catch (_) { return; }
    for (const key of [type, '*']) {
      const set = this.listeners.get(key);
      if (set) for (const fn of set) fn(ev);
    }
  }

  /** Opens the stream; the types are those the server sends (see README: events). */
  start(types) {
    this.stop();
    const t = token();
    const url = '/api/v1/events' + (t ? '?access_token=' + encodeURIComponent(t) : '');
    const es = new EventSource(url);
    this.source = es;
    es.onopen = () => this.setConnected(true);
    es.onerror = () => {
      // CONNECTING: the browser retries; CLOSED: it gave up (e.g. 401), retry ourselves.
      this.setConnected(false);
      if (es.readyState === EventSource.CLOSED && this.source === es) {
        setTimeout(() => { if (this.source === es) this.start(types); }, 2000);
      }
    };
    for (const type of types) es.addEventListener(type, (m) => this.dispatch(type, m.data));
  }

  stop() {
    if (this.source) this.source.close();
    this.source = null;
  }
}

/** Opens a separate filtered stream (history replay + live) for the events page. */
export function eventStream(query, types, onEvent, onState) {
  const t = token();
  const params = new URLSearchParams(query);
  if (t) params.set('access_token', t);
  const es = new EventSource('/api/v1/events?' + params.toString());
  es.onopen = () => onState(true);
  es.onerror = () => onState(false);
  const handle = (m) => { try { onEvent(JSON.parse(m.data)); } catch (_) { /* skip */ } };
  for (const type of types) es.addEventListener(type, handle);
  return es;
}
