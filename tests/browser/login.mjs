// The console's login, in the browser, driven by tests/tests/console.rs: the console runs
// over HTTPS with two users (alice, an operator; vera, a viewer), both with passwords.
//
// Environment (besides console.mjs's MFC_NODE_PREFIX, MFC_CHROMIUM, MFC_CONSOLE_PROFILE,
// MFC_CONSOLE_SCREENSHOTS):
//   MFC_CONSOLE_URL       the console's page, https://127.0.0.1:PORT/
//   MFC_CONSOLE_DEVICE    a device that runs throughout (aero-1)
//   MFC_LOGIN_OPERATOR    alice:PASSWORD
//   MFC_LOGIN_VIEWER      vera:PASSWORD
//
// Stages: `refused` (no login: the page asks for one, the API answers 401), `wrong` (a
// wrong password refused), `viewer` (vera sees the device, cannot change: the form is off
// and the API answers 403), `out` (logged out: 401 again), `operator` (alice changes a
// gain; the console's audit view shows it under her name), `done`.

import { createRequire } from 'node:module';
import path from 'node:path';

const env = (k) => {
  const v = process.env[k];
  if (v === undefined) { console.error(`login.mjs: ${k} is not set`); process.exit(2); }
  return v;
};
const url = env('MFC_CONSOLE_URL');
const device = env('MFC_CONSOLE_DEVICE');
const shots = env('MFC_CONSOLE_SCREENSHOTS');
const [alice, alicePw] = env('MFC_LOGIN_OPERATOR').split(':');
const [vera, veraPw] = env('MFC_LOGIN_VIEWER').split(':');
const require = createRequire(path.join(env('MFC_NODE_PREFIX'), 'package.json'));
const { chromium } = require('playwright-core');

const stage = (name, data) => console.log(`STAGE ${name} ${JSON.stringify(data ?? {})}`);
const LONG = 60_000;

// The console's certificate is the deployment's (its CA is not the browser's): the test's
// Rust side checks the chain; the browser is told to go on.
const context = await chromium.launchPersistentContext(env('MFC_CONSOLE_PROFILE'), {
  executablePath: env('MFC_CHROMIUM'),
  headless: true,
  ignoreHTTPSErrors: true,
  viewport: { width: 1440, height: 1000 },
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
         '--disable-background-networking', '--disable-component-update', '--disable-sync'],
});
const errors = [];
let failed = false;
// What the page's own origin gets from the API (status and body), with the page's cookies.
const call = (page, p, body) => page.evaluate(async ([p, body]) => {
  const init = body === undefined ? {} : {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) };
  const r = await fetch(p, init);
  let j = {};
  try { j = await r.json(); } catch (_) { /* not JSON */ }
  return { status: r.status, body: j };
}, [p, body]);
const logIn = async (page, name, pw) => {
  await page.fill('#login-name', name);
  await page.fill('#login-password', pw);
  await page.click('#login-apply');
};
try {
  const page = context.pages()[0] ?? await context.newPage();
  page.on('pageerror', (e) => errors.push(String(e)));
  await page.goto(url, { waitUntil: 'load', timeout: LONG });

  // Nobody logged in: the form, no device list, and the API refuses.
  await page.waitForSelector('#login:not([hidden])', { timeout: LONG });
  if (await page.isVisible('#main')) throw new Error('the console shows its devices before a login');
  const anon = await call(page, 'api/devices');
  const anonChange = await call(page, `api/devices/${device}/gains`, { channel: 1, fields: { kp: 11 } });
  if (anon.status !== 401 || anonChange.status !== 401) {
    throw new Error(`without a login: devices ${anon.status}, change ${anonChange.status}`);
  }
  stage('refused', { devices: anon, change: anonChange });

  await logIn(page, vera, 'not-her-password');
  await page.waitForSelector('#login-result[data-state="refused"]', { timeout: LONG });
  const wrong = await page.textContent('#login-result');
  if (!(await page.isVisible('#login'))) throw new Error('a wrong password let someone in');
  stage('wrong', { result: wrong });

  // The viewer: sees the device and its plots, may not change anything.
  await logIn(page, vera, veraPw);
  await page.waitForSelector('#main:not([hidden])', { timeout: LONG });
  await page.waitForSelector(`#devices li[data-device="${device}"][data-alive="true"]`, { timeout: LONG });
  await page.click(`#devices li[data-device="${device}"]`);
  await page.waitForFunction(() => Number(document.getElementById('plot-y-0')?.dataset.points) >= 20, null, { timeout: LONG });
  const who = await page.textContent('#who');
  const disabled = await page.isDisabled('#gain-apply') && await page.isDisabled('#ref-apply');
  const viewerChange = await call(page, `api/devices/${device}/gains`, { channel: 1, fields: { kp: 11 } });
  const viewerRef = await call(page, `api/devices/${device}/reference`, { values: [0, 0.02] });
  if (!disabled || viewerChange.status !== 403 || viewerRef.status !== 403) {
    throw new Error(`the viewer could change: disabled ${disabled}, gains ${JSON.stringify(viewerChange)}, reference ${viewerRef.status}`);
  }
  await page.screenshot({ path: path.join(shots, 'console-viewer.png'), fullPage: true });
  stage('viewer', { who, change: viewerChange, reference: viewerRef.status });

  await page.click('#logout');
  await page.waitForSelector('#login:not([hidden])', { timeout: LONG });
  const after = await call(page, 'api/devices');
  if (after.status !== 401) throw new Error(`after logging out: devices ${after.status}`);
  stage('out', { status: after.status });

  // The operator: changes one gain; the audit view names her.
  await logIn(page, alice, alicePw);
  await page.waitForSelector('#main:not([hidden])', { timeout: LONG });
  await page.click(`#devices li[data-device="${device}"]`);
  await page.waitForSelector('#gain-fields input[data-field="kp"]', { timeout: LONG });
  await page.selectOption('#gain-channel', '1');
  await page.waitForFunction(() => document.getElementById('gain-law').textContent.includes('law'));
  await page.fill('#gain-fields input[data-field="kp"]', '12');
  await page.click('#gain-apply');
  await page.waitForSelector('#gain-result[data-state="accepted"], #gain-result[data-state="refused"]', { timeout: LONG });
  const gain = await page.textContent('#gain-result');
  if ((await page.getAttribute('#gain-result', 'data-state')) !== 'accepted') throw new Error(`alice's change: ${gain}`);
  await page.waitForFunction((name) => [...document.querySelectorAll('#audit tr[data-state="accepted"]')]
    .some((tr) => tr.dataset.operator === name && tr.textContent.includes('channel 1 kp: 9 → 12')), alice, { timeout: LONG });
  const row = await page.textContent(`#audit tr[data-state="accepted"][data-operator="${alice}"]`);
  await page.screenshot({ path: path.join(shots, 'console-login.png'), fullPage: true });
  stage('operator', { who: await page.textContent('#who'), gain, row });

  if (errors.length) throw new Error(`errors in the page: ${errors.join('; ')}`);
  stage('done', {});
} catch (e) {
  failed = true;
  console.error(`login.mjs: ${e && e.stack ? e.stack : e}`);
  if (errors.length) console.error(`errors in the page: ${errors.join('; ')}`);
  try {
    const page = context.pages()[0];
    if (page) await page.screenshot({ path: path.join(shots, 'console-login-failure.png'), fullPage: true });
  } catch (_) { /* nothing more to show */ }
} finally {
  await context.close();
}
process.exit(failed ? 1 : 0);
