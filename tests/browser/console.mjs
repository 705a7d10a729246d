// The console's browser test, driven by tests/tests/console.rs (which starts a service, the
// plants and the console, and reads this script's stdout). Debian's Chromium, headless,
// through playwright-core (installed by tests/browser/setup.sh; no browser of its own).
//
// Environment:
//   MFC_CONSOLE_URL          the console's page, e.g. http://127.0.0.1:8080/
//   MFC_NODE_PREFIX          where setup.sh installed playwright-core
//   MFC_CHROMIUM             the browser (default /usr/bin/chromium)
//   MFC_CONSOLE_DEVICE       the device that runs throughout (aero-1)
//   MFC_CONSOLE_LATE_DEVICE  a device whose plant starts after the page loaded and stops (aero-2)
//   MFC_CONSOLE_SCREENSHOTS  directory for console-*.png
//   MFC_CONSOLE_PROFILE      a fresh, empty directory for the browser's profile
//
// Protocol: one line `STAGE <name> <json>` per step passed; the test starts the late
// device's plant on `STAGE loaded`. Any failure: a message on stderr and exit status 1.

import { createRequire } from 'node:module';
import path from 'node:path';

const env = (k, d) => {
  const v = process.env[k] ?? d;
  if (v === undefined) { console.error(`console.mjs: ${k} is not set`); process.exit(2); }
  return v;
};
const url = env('MFC_CONSOLE_URL');
const prefix = env('MFC_NODE_PREFIX');
const chromiumPath = env('MFC_CHROMIUM', '/usr/bin/chromium');
const device = env('MFC_CONSOLE_DEVICE', 'aero-1');
const late = env('MFC_CONSOLE_LATE_DEVICE', 'aero-2');
const shots = env('MFC_CONSOLE_SCREENSHOTS');
const profile = env('MFC_CONSOLE_PROFILE');

const require = createRequire(path.join(prefix, 'package.json'));
const { chromium } = require('playwright-core');

const stage = (name, data) => console.log(`STAGE ${name} ${JSON.stringify(data ?? {})}`);
const t0 = Date.now();
const since = () => (Date.now() - t0) / 1000;

// Generous deadlines: the machine may be busy; each wait ends as soon as its condition holds.
const LONG = 60_000;

const context = await chromium.launchPersistentContext(profile, {
  executablePath: chromiumPath,
  headless: true,
  viewport: { width: 1440, height: 1100 },
  args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
         '--disable-background-networking', '--disable-component-update', '--disable-sync'],
});
const errors = [];
let failed = false;
try {
  const page = context.pages()[0] ?? await context.newPage();
  page.on('pageerror', (e) => errors.push(String(e)));
  // Nothing may be fetched from anywhere but the console (the page works offline).
  const foreign = [];
  page.on('request', (r) => { if (!r.url().startsWith(url) && !r.url().startsWith('data:')) foreign.push(r.url()); });

  await page.goto(url, { waitUntil: 'load', timeout: LONG });
  const item = (id, alive) => `#devices li[data-device="${id}"][data-alive="${alive}"]`;
  await page.waitForSelector(item(device, true), { timeout: LONG });
  stage('loaded', { at: since() });

  // Plots: points are drawn, and more of them, later in plant time, a moment after.
  await page.click(`#devices li[data-device="${device}"]`);
  const read = () => page.evaluate(() => {
    const c = (id) => {
      const e = document.getElementById(id);
      return e ? { points: Number(e.dataset.points), last: Number(e.dataset.lastTime || 'NaN') } : null;
    };
    return { y0: c('plot-y-0'), v0: c('plot-v-0'), y1: c('plot-y-1'), v1: c('plot-v-1') };
  });
  await page.waitForFunction(() => {
    const e = document.getElementById('plot-y-0');
    return e && Number(e.dataset.points) >= 50;
  }, null, { timeout: LONG });
  const first = await read();
  await page.waitForFunction((t) => {
    const e = document.getElementById('plot-y-0');
    return e && Number(e.dataset.lastTime) >= t + 1.0;
  }, first.y0.last, { timeout: LONG });
  const second = await read();
  for (const k of ['y0', 'v0', 'y1', 'v1']) {
    if (!second[k] || !(second[k].points > 0)) throw new Error(`plot ${k} drew nothing: ${JSON.stringify(second)}`);
  }
  if (!(second.y0.last > first.y0.last && second.y0.points >= first.y0.points)) {
    throw new Error(`the plots did not advance: ${JSON.stringify({ first, second })}`);
  }
  stage('plots', { first, second, at: since() });

  // The late device appears, live, while the page is open.
  await page.waitForSelector(item(late, true), { timeout: LONG });
  stage('appeared', { at: since() });

  // One gain of channel 1 (the AERO's pitch: its iPD has kp 9; 12 stays well damped).
  await page.waitForSelector('#gain-fields input[data-field="kp"]', { timeout: LONG });
  await page.selectOption('#gain-channel', '1');
  await page.waitForFunction(() => document.getElementById('gain-law').textContent.includes('law'));
  await page.fill('#gain-fields input[data-field="kp"]', '12');
  await page.click('#gain-apply');
  await page.waitForSelector('#gain-result[data-state="accepted"], #gain-result[data-state="refused"]', { timeout: LONG });
  const gain = await page.textContent('#gain-result');
  if ((await page.getAttribute('#gain-result', 'data-state')) !== 'accepted') throw new Error(`gain change: ${gain}`);
  // The page shows the new value from the service's configuration.
  await page.waitForFunction(() => {
    const td = document.querySelector('#gain-fields td[data-now="kp"]');
    return td && td.textContent === '12';
  }, null, { timeout: LONG });
  stage('gain', { result: gain, at: since() });
  // The accepted change is in the console's audit view: who, and the gain's old and new value.
  await page.waitForFunction(() => [...document.querySelectorAll('#audit tr[data-state="accepted"]')]
    .some((tr) => tr.textContent.includes('channel 1 kp: 9 → 12')), null, { timeout: LONG });
  const audited = await page.textContent('#audit tr[data-state="accepted"]');
  stage('audit', { row: audited, at: since() });
  await page.screenshot({ path: path.join(shots, 'console-gain.png'), fullPage: true });

  // A limit outside the envelope: refused, with the reason, and nothing sent.
  await page.fill('#gain-fields input[data-field="max"]', '100');
  await page.click('#gain-apply');
  await page.waitForSelector('#gain-result[data-state="refused"]', { timeout: LONG });
  const refusal = await page.textContent('#gain-result');
  if (!refusal.includes('envelope')) throw new Error(`the refusal does not name the envelope: ${refusal}`);
  stage('envelope-refused', { result: refusal, at: since() });

  // A constant reference: channel 1 (pitch) to 0.05 rad, channel 0 as it is.
  if ((await page.inputValue('#ref-0')).trim() === '') await page.fill('#ref-0', '0');
  await page.fill('#ref-1', '0.05');
  await page.click('#ref-apply');
  await page.waitForSelector('#ref-result[data-state="accepted"], #ref-result[data-state="refused"]', { timeout: LONG });
  const ref = await page.textContent('#ref-result');
  if ((await page.getAttribute('#ref-result', 'data-state')) !== 'accepted') throw new Error(`reference: ${ref}`);
  stage('reference', { result: ref, at: since() });

  // Commissioning the azimuth velocity (channel 0): +-3 for 4 periods of 1 s, at most
  // 0.003 rad/ms away; the proposal, then its confirmation. (The service waits for the
  // loop to settle first.)
  await page.selectOption('#com-channel', '0');
  await page.fill('#com-amplitude', '3');
  await page.fill('#com-deviation', '0.003');
  await page.fill('#com-period', '1');
  await page.fill('#com-cycles', '4');
  await page.click('#com-start');
  await page.waitForSelector('#com-result[data-state="accepted"], #com-result[data-state="refused"]', { timeout: LONG });
  const started = await page.textContent('#com-result');
  if ((await page.getAttribute('#com-result', 'data-state')) !== 'accepted') throw new Error(`commission start: ${started}`);
  await page.waitForSelector('#com-state[data-phase="proposed"], #com-state[data-phase="aborted"]', { timeout: 2 * LONG });
  const proposal = await page.textContent('#com-state');
  if ((await page.getAttribute('#com-state', 'data-phase')) !== 'proposed') throw new Error(`commissioning: ${proposal}`);
  await page.screenshot({ path: path.join(shots, 'console-commission.png'), fullPage: true });
  await page.click('#com-confirm');
  await page.waitForSelector('#com-state[data-phase="applied"]', { timeout: LONG });
  const applied = await page.textContent('#com-state');
  await page.waitForFunction(() => [...document.querySelectorAll('#audit tr[data-state="accepted"]')]
    .some((tr) => tr.textContent.includes('channel 0 alpha:')), null, { timeout: LONG });
  stage('commission', { proposal, applied, at: since() });

  // The late device's plant ends: it stays listed, marked gone.
  await page.waitForSelector(item(late, false), { timeout: 2 * LONG });
  stage('gone', { at: since() });
  await page.screenshot({ path: path.join(shots, 'console-fleet.png'), fullPage: true });

  if (errors.length) throw new Error(`errors in the page: ${errors.join('; ')}`);
  if (foreign.length) throw new Error(`the page fetched from elsewhere: ${foreign.join(', ')}`);
  // The console's own counters (what it took and what it refused), for the test's report.
  const counters = await page.evaluate(async () => (await (await fetch('api/devices')).json()).counters);
  stage('done', { at: since(), counters });
} catch (e) {
  failed = true;
  console.error(`console.mjs: ${e && e.stack ? e.stack : e}`);
  if (errors.length) console.error(`errors in the page: ${errors.join('; ')}`);
  try {
    const page = context.pages()[0];
    if (page) await page.screenshot({ path: path.join(shots, 'console-failure.png'), fullPage: true });
  } catch (_) { /* nothing more to show */ }
} finally {
  await context.close();
}
process.exit(failed ? 1 : 0);
