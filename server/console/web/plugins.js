// Loaded plugins, load failures and skipped libraries.

import { api } from './api.js';
import { h } from './ui.js';

export async function pluginsPage(page) {
  const p = await api('GET', '/plugins');
  const table = (head, rows) => h('table', {}, h('thead', {}, h('tr', {}, head.map((t) => h('th', {}, t)))), h('tbody', {}, rows));
  page.append(h('h1', {}, 'Plugins'), h('p', { class: 'muted' }, `Host ABI ${p.abi}`),
    h('section', { class: 'card' }, h('h2', {}, 'Loaded'), table(['name', 'version', 'kinds', 'ABI', 'path'],
      p.plugins.map((x) => h('tr', { dataset: { plugin: x.name } }, h('td', {}, x.name), h('td', {}, x.version), h('td', {}, (x.kinds || []).join(', ')), h('td', {}, x.abi), h('td', { class: 'path' }, x.path))))),
    h('section', { class: 'card' }, h('h2', {}, 'Failed to load'), p.failures.length ? table(['path', 'reason'],
      p.failures.map((x) => h('tr', { class: 'error' }, h('td', { class: 'path' }, x.path), h('td', {}, x.reason || x.error || JSON.stringify(x))))) : h('p', { class: 'muted', id: 'no-failures' }, 'none')),
    h('section', { class: 'card' }, h('h2', {}, 'Skipped'), p.skipped.length ? table(['path', 'reason'],
      p.skipped.map((x) => h('tr', {}, h('td', { class: 'path' }, x.path), h('td', {}, x.reason)))) : h('p', { class: 'muted' }, 'none')));
}
