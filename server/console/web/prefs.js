// Display preferences kept in this browser (issue 27): the colour theme, which follows the
// system until the switch is used, and the units positions are shown in (mm or inch; the API
// is always mm). Both are buttons in the header.

import { h, display, setUnits } from './ui.js';

const THEME_KEY = 'fresa.theme';
const system = window.matchMedia('(prefers-color-scheme: dark)');

/** Whether the page is dark now (the switch's choice, else the system's). */
export function isDark() {
  const t = document.documentElement.dataset.theme;
  return t ? t === 'dark' : system.matches;
}

function applyTheme() {
  const t = localStorage.getItem(THEME_KEY);
  if (t === 'dark' || t === 'light') document.documentElement.dataset.theme = t;
  else delete document.documentElement.dataset.theme;
  document.dispatchEvent(new CustomEvent('fresa:theme'));
}

/** Applies the stored theme and fills the header's switches. */
export function initPrefs() {
  applyTheme();
  const theme = h('button', { id: 'theme-switch', type: 'button', title: 'dark or light (follows the system until switched)' });
  const units = h('button', { id: 'units-switch', type: 'button', title: 'show positions in mm or inch' });
  const label = () => {
    theme.textContent = isDark() ? '☀ Light' : '☾ Dark';
    theme.dataset.dark = String(isDark());
    units.textContent = display.units === 'in' ? 'inch' : 'mm';
    units.setAttribute('aria-label', `units: ${units.textContent} (switch)`);
  };
  theme.addEventListener('click', () => {
    localStorage.setItem(THEME_KEY, isDark() ? 'light' : 'dark');
    applyTheme();
    label();
  });
  units.addEventListener('click', () => { setUnits(display.units === 'in' ? 'mm' : 'in'); label(); });
  system.addEventListener('change', () => { if (!localStorage.getItem(THEME_KEY)) applyTheme(); label(); });
  document.addEventListener('fresa:units', label);
  label();
  document.getElementById('prefs').replaceChildren(theme, units);
}
