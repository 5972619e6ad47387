// The station page in a real browser: Debian's Chromium, headless, driven by
// playwright-core, against `station serve` on loopback with the simulated scanner.
// Scans the bundled mustard bottle from the page, waits for the mesh, checks the
// 3-D viewer drew it in the bottle's colours, downloads it and compares it byte
// for byte with `station run` on the same session. Run by scripts/web_test.sh.
//
// Environment: STATION_BIN (default build/bin/station), STATION_WEB_OUT (default
// build/web-test: screenshots), STATION_WEB_SCREENSHOT (also save the finished
// page there, e.g. docs/serve.png), CHROMIUM (default /usr/bin/chromium).
import { chromium } from 'playwright-core';
import { spawn, execFileSync } from 'node:child_process';
import { createHash } from 'node:crypto';
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '../..');
const station = process.env.STATION_BIN || path.join(root, 'build/bin/station');
const outDir = process.env.STATION_WEB_OUT || path.join(root, 'build/web-test');
const chromiumPath = process.env.CHROMIUM || '/usr/bin/chromium';
fs.mkdirSync(outDir, { recursive: true });
const data = fs.mkdtempSync(path.join(os.tmpdir(), 'station-web-'));

let failures = 0;
function check(ok, what) {
  console.log(`${ok ? 'ok  ' : 'FAIL'} ${what}`);
  if (!ok) failures++;
}
const md5 = (file) => createHash('md5').update(fs.readFileSync(file)).digest('hex');

// ---- the server ------------------------------------------------------------------
function startServer() {
  return new Promise((resolve, reject) => {
    const child = spawn(station, ['serve', '--port', '0', '--data', data, '--threads', '2'], {
      stdio: ['ignore', 'pipe', 'pipe'],
    });
    let out = '';
    const timer = setTimeout(() => reject(new Error(`station serve did not start: ${out}`)), 30000);
    child.stdout.on('data', (b) => {
      out += b;
      const m = out.match(/station page: (http:\/\/127\.0\.0\.1:\d+\/)/);
      if (m) { clearTimeout(timer); resolve({ child, url: m[1] }); }
    });
    child.stderr.on('data', (b) => { out += b; });
    child.exited = new Promise((done) => child.on('exit', (code, signal) => done(code ?? signal)));
    child.on('exit', (code) => { clearTimeout(timer); reject(new Error(`station serve exited ${code}: ${out}`)); });
  });
}

// Pixel figures of a PNG screenshot, decoded by the browser itself.
async function pixelStats(page, png, reference) {
  return page.evaluate(async ([b64, refB64]) => {
    const decode = async (s) => {
      const img = new Image();
      img.src = 'data:image/png;base64,' + s;
      await img.decode();
      const c = document.createElement('canvas');
      c.width = img.width; c.height = img.height;
      const g = c.getContext('2d');
      g.drawImage(img, 0, 0);
      return g.getImageData(0, 0, c.width, c.height).data;
    };
    const a = await decode(b64);
    const b = refB64 ? await decode(refB64) : null;
    let differ = 0, yellow = 0, grey = 0;
    const n = a.length / 4;
    for (let i = 0; i < a.length; i += 4) {
      const [r, g, bl] = [a[i], a[i + 1], a[i + 2]];
      if (b && (Math.abs(r - b[i]) + Math.abs(g - b[i + 1]) + Math.abs(bl - b[i + 2]) > 30)) differ++;
      // The mustard bottle's yellow: red and green high, blue low.
      if (r > 140 && g > 110 && bl < 100 && r - bl > 90) yellow++;
      if (r > 90 && Math.abs(r - g) < 12 && Math.abs(g - bl) < 16) grey++;
    }
    return { pixels: n, differ: differ / n, yellow: yellow / n, grey: grey / n };
  }, [png.toString('base64'), reference ? reference.toString('base64') : null]);
}

async function waitJobEnd(page) {
  // The job's end, or an error shown (a start that was refused).
  await page.waitForFunction(
    () => ['finished', 'failed', 'stopped'].includes(document.getElementById('job-state').dataset.state) ||
      !document.getElementById('error').hidden,
    null, { timeout: 300000, polling: 500 });
  return page.evaluate(() => document.getElementById('job-state').dataset.state);
}

const { child: server, url } = await startServer();
console.log(`station serve at ${url}, data ${data}`);
let browser;
try {
  try {
    browser = await chromium.launch({
      executablePath: chromiumPath,
      headless: true,
      args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--disable-dev-shm-usage',
             '--no-first-run', '--disable-background-networking', '--disable-component-update', '--disable-sync'],
    });
  } catch (e) {
    // Not a skip: the browser tests fail when the browser cannot start.
    console.error(`web test: Chromium (${chromiumPath}) cannot start: ${e.message.split('\n')[0]}`);
    process.exitCode = 1;
    throw e;
  }
  const context = await browser.newContext({ viewport: { width: 1280, height: 900 }, acceptDownloads: true });
  const page = await context.newPage();
  const consoleErrors = [];
  page.on('pageerror', (e) => consoleErrors.push(e.message));
  page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });

  await page.goto(url);
  await page.waitForFunction(() => document.querySelectorAll('#profile option').length > 0, null, { timeout: 30000 });
  check(await page.inputValue('#profile') === 'default.yaml', 'the page offers the profiles, default.yaml first');
  check(await page.locator('#scanner option').count() >= 1, 'the page offers scanners');
  const canvas = page.locator('#viewer canvas');
  check(await canvas.count() === 1, 'the 3-D viewer has a WebGL canvas');
  const empty = await canvas.screenshot();

  // Live preview: the simulator's rendered view.
  await page.click('#preview-toggle');
  await page.waitForFunction(() => document.getElementById('preview').naturalWidth > 0, null, { timeout: 60000 });
  check(true, 'the live preview shows a frame');
  await page.click('#preview-toggle');

  // A scan of the bundled bottle with the default profile, then the whole job.
  await page.fill('#session-name', 'bottle');
  await page.click('#start');
  const ended = await waitJobEnd(page);
  const errorText = await page.locator('#error').textContent();
  check(ended === 'finished', `the scan and run finished (${ended}${errorText ? ': ' + errorText : ''})`);
  const views = await page.locator('#views-strip img').count();
  check(views === 12, `each view's colour image arrived (${views} of 12)`);
  const loaded = await page.evaluate(() => {
    const imgs = [...document.querySelectorAll('#views-strip img')];
    return imgs.length > 0 && imgs.every((i) => i.naturalWidth > 0);
  });
  check(loaded, 'the view images loaded');
  for (const s of ['register', 'consolidate', 'surface']) {
    const t = await page.locator(`#stages tr[data-stage="${s}"] td:nth-child(3)`).textContent().catch(() => '');
    check(Number(t) > 0, `stage ${s} shows its time (${t} s)`);
  }
  const priors = await page.$$eval('#registration tbody tr td:nth-child(3)', (tds) => tds.map((t) => t.textContent));
  check(priors.length === 12 && priors.every((p) => ['used', 'corrected', 'none'].includes(p)),
        `the registration table lists every view's prior (${priors.join(' ')})`);

  // Downloads: the mesh as PLY equals `station run`'s on the same session; OBJ too.
  const [plyDl] = await Promise.all([page.waitForEvent('download'), page.click('#download-ply')]);
  const pagePly = path.join(data, 'page-mesh.ply');
  await plyDl.saveAs(pagePly);
  // The OBJ link, fetched as the browser would (a second browser download in a
  // row does not always start in headless Chromium).
  const objHref = new URL(await page.getAttribute('#download-obj', 'href'), url);
  const objRes = await fetch(objHref);
  const obj = await objRes.text();
  check(objRes.ok && /attachment/.test(objRes.headers.get('content-disposition') || ''), `the OBJ link downloads (${objRes.status})`);
  check(/\nv [-0-9.e]+ [-0-9.e]+ [-0-9.e]+ [0-9.]+ /.test(obj) && obj.includes('\nf '), 'the OBJ download has coloured vertices and faces');
  execFileSync(station, ['run', path.join(data, 'bottle'), '-o', path.join(data, 'cli-run'), '--threads', '2',
                         '--quiet', '--no-report']);
  const a = md5(pagePly), b = md5(path.join(data, 'cli-run', 'mesh.ply'));
  check(a === b, `the page's mesh equals station run's on the same session (${a} / ${b})`);

  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'mesh-colour', null, { timeout: 60000 });
  await page.waitForTimeout(300);
  const coloured = await canvas.screenshot();
  fs.writeFileSync(path.join(outDir, 'viewer-mesh.png'), coloured);
  const sc = await pixelStats(page, coloured, empty);
  check(sc.differ > 0.05, `the viewer drew the mesh (${(100 * sc.differ).toFixed(1)} % of pixels changed)`);
  check(sc.yellow > 0.01, `the mesh shows the bottle's yellow (${(100 * sc.yellow).toFixed(1)} % of pixels)`);

  await page.uncheck('#mesh-colour');
  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'mesh-plain', null, { timeout: 30000 });
  await page.waitForTimeout(300);
  const plain = await pixelStats(page, await canvas.screenshot(), empty);
  check(plain.differ > 0.05 && plain.yellow < 0.2 * sc.yellow,
        `without colour the mesh is grey (yellow ${(100 * plain.yellow).toFixed(2)} %, grey ${(100 * plain.grey).toFixed(1)} %)`);
  await page.check('#mesh-colour');
  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'mesh-colour', null, { timeout: 30000 });

  await page.click('#viewer-modes button[data-mode="registered"]');
  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'registered', null, { timeout: 30000 });
  await page.waitForTimeout(300);
  const byView = await pixelStats(page, await canvas.screenshot(), coloured);
  check(byView.differ > 0.02, `the registered cloud, coloured by view, replaced the mesh (${(100 * byView.differ).toFixed(1)} % changed)`);
  await page.click('#viewer-modes button[data-mode="mesh"]');
  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'mesh-colour', null, { timeout: 30000 });
  await page.waitForTimeout(300);
  if (process.env.STATION_WEB_SCREENSHOT) {
    await page.evaluate(() => window.scrollTo(0, 0));
    await page.screenshot({ path: process.env.STATION_WEB_SCREENSHOT, fullPage: true });
    console.log(`screenshot: ${process.env.STATION_WEB_SCREENSHOT}`);
  }
  await page.screenshot({ path: path.join(outDir, 'page.png') });

  check(consoleErrors.length === 0, `no errors in the page's console (${consoleErrors.join('; ')})`);
  // An error is shown as the station's one-line message (the browser logs the 400).
  await page.click('#start');
  await page.waitForFunction(() => !document.getElementById('error').hidden, null, { timeout: 30000 });
  const err = await page.locator('#error').textContent();
  check(/session bottle: exists already/.test(err), `a second scan into the same session shows the error (${err})`);

  // Past sessions re-open after a reload.
  await page.reload();
  await page.waitForSelector('#sessions li[data-name="bottle"]', { timeout: 30000 });
  await page.click('#sessions li[data-name="bottle"]');
  await page.waitForFunction(() => document.getElementById('viewer').dataset.shown === 'mesh-colour', null, { timeout: 60000 });
  const rows = await page.locator('#registration tbody tr').count();
  check(rows === 12, `a past session re-opens with its results (${rows} views)`);
} catch (e) {
  console.error(`web test: ${e.message}`);
  failures++;
} finally {
  if (browser) await browser.close();
  server.kill('SIGINT');
  const code = await server.exited;
  check(code === 0, `station serve stopped cleanly on Ctrl-C (exit ${code})`);
  fs.rmSync(data, { recursive: true, force: true });
}
console.log(failures ? `web test: ${failures} checks failed` : 'web test: all checks passed');
process.exit(failures ? 1 : 0);
