// End-to-end tests of the web viewer: playwright-core drives Debian's chromium (headless, WebGL
// through SwiftShader) against a live `shapeseek serve` started by scripts/browser-test.sh.
//
// Env: SHAPESEEK_URL (the server), SAMPLES_DIR (from `shapeseek samples`), HOLD_OUT (a sample id
// that was not ingested: uploaded as the query), SCREENSHOT_DIR (where PNGs go), CHROMIUM
// (default /usr/bin/chromium).
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { readFileSync, mkdirSync, mkdtempSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { chromium } from 'playwright-core';
import { MeshoptEncoder } from 'meshoptimizer';

const URL_ = process.env.SHAPESEEK_URL;
const SAMPLES = process.env.SAMPLES_DIR;
const HOLD_OUT = process.env.HOLD_OUT || 'quadruped-iso2';
const SHOTS = process.env.SCREENSHOT_DIR;
if (!URL_ || !SAMPLES || !SHOTS) throw new Error('run through scripts/browser-test.sh (SHAPESEEK_URL, SAMPLES_DIR, SCREENSHOT_DIR)');
mkdirSync(SHOTS, { recursive: true });

const manifest = readFileSync(join(SAMPLES, 'manifest.csv'), 'utf8').trim().split('\n').slice(1)
  .map((l) => { const [id, path, cls] = l.split(','); return { id, path, cls }; });
const classOf = Object.fromEntries(manifest.map((m) => [m.id, m.cls]));
const holdOut = manifest.find((m) => m.id === HOLD_OUT);
assert.ok(holdOut, `HOLD_OUT ${HOLD_OUT} is in the manifest`);

let browser;
let page;
const consoleErrors = [];
// Answers of 400 and above to requests outside the API (the page's own files, the icon).
const failedPageRequests = [];

before(async () => {
  browser = await chromium.launch({
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--no-first-run', '--disable-background-networking',
      '--disable-component-update', '--disable-sync', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
  page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
  page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
  page.on('pageerror', (e) => consoleErrors.push(String(e)));
  page.on('response', (r) => {
    if (r.status() >= 400 && r.url().startsWith(URL_) && !new URL(r.url()).pathname.startsWith('/v1/')) {
      failedPageRequests.push(`${r.status()} ${r.url()}`);
    }
  });
  // The page must fetch nothing but its own origin.
  await page.route('**/*', (route) => {
    const u = route.request().url();
    if (u.startsWith(URL_) || u.startsWith('data:') || u.startsWith('blob:')) return route.continue();
    consoleErrors.push(`foreign request: ${u}`);
    return route.abort();
  });
});

after(async () => {
  if (browser) await browser.close();
});

/** For each element matching `selector`: the fraction of its area where the WebGL canvas shows
 * something other than the view background, and the mean colour of those pixels. Reads the
 * canvas back (preserveDrawingBuffer) after forcing a frame. */
async function viewPixels(selector, withMask = false) {
  return page.evaluate(([sel, withMask]) => {
    window.shapeseekViewer.render();
    const gl = document.getElementById('gl');
    const ratio = gl.width / gl.clientWidth;
    const c2 = document.createElement('canvas');
    c2.width = gl.width; c2.height = gl.height;
    const ctx = c2.getContext('2d', { willReadFrequently: true });
    ctx.drawImage(gl, 0, 0);
    return [...document.querySelectorAll(sel)].map((el) => {
      const r = el.getBoundingClientRect();
      const x = Math.max(0, Math.floor(r.left * ratio)), y = Math.max(0, Math.floor(r.top * ratio));
      const w = Math.min(c2.width - x, Math.floor(r.width * ratio)), h = Math.min(c2.height - y, Math.floor(r.height * ratio));
      if (w <= 0 || h <= 0) return { fraction: 0, visible: false };
      const d = ctx.getImageData(x, y, w, h).data;
      let n = 0, sr = 0, sg = 0, sb = 0, bg = 0;
      const mask = withMask ? new Array(w * h).fill(0) : null;
      for (let i = 0; i < d.length; i += 4) {
        // background #f7f9fc
        const dist = Math.abs(d[i] - 0xf7) + Math.abs(d[i + 1] - 0xf9) + Math.abs(d[i + 2] - 0xfc);
        if (d[i + 3] === 0) continue;
        bg++;
        if (dist > 40) {
          n++; sr += d[i]; sg += d[i + 1]; sb += d[i + 2];
          if (mask) mask[i / 4] = 1;
        }
      }
      return { visible: true, painted: bg / (w * h), fraction: n / (w * h), mean: n ? [sr / n, sg / n, sb / n] : null, mask };
    });
  }, [selector, withMask]);
}

async function waitRendered(selector, count) {
  await page.waitForFunction(([sel, n]) => {
    const v = [...document.querySelectorAll(sel)];
    return v.length >= n && v.every((e) => e.dataset.rendered === '1' || e.dataset.rendered === 'error');
  }, [selector, count], { timeout: 120_000 });
  const states = await page.$$eval(selector, (v) => v.map((e) => e.dataset.rendered + ':' + e.textContent));
  assert.deepEqual(states.filter((s) => !s.startsWith('1:')), [], 'every view rendered a mesh');
}

test('the page loads from the server alone and lists the stored shapes with their tags', async () => {
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length > 0);
  const info = await page.textContent('#index-info');
  assert.match(info, new RegExp(`^${manifest.length - 1} stored shapes`));
  const rows = await page.$$eval('#shape-list li[data-id]', (li) => li.map((l) => ({
    name: l.querySelector('.name').textContent, tags: [...l.querySelectorAll('.tag')].map((t) => t.textContent) })));
  assert.equal(rows.length, 10, 'a page holds 10 shapes');
  for (const r of rows) assert.deepEqual(r.tags, [classOf[r.name]], `${r.name} shows its class tag`);
  assert.equal(await page.isHidden('#error'), true);
});

test('paging: next and previous pages of the stored shapes, and the tag filter', async () => {
  const names = () => page.$$eval('#shape-list li[data-id] .name', (n) => n.map((x) => x.textContent));
  const first = await names();
  await page.click('#next');
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 2');
  const second = await names();
  assert.equal(second.length, 10);
  assert.equal(second.filter((n) => first.includes(n)).length, 0, 'page 2 has other shapes');
  await page.click('#next');
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 3');
  const third = await names();
  assert.equal(third.length, manifest.length - 1 - 20, 'the last page holds the rest');
  assert.equal(await page.isDisabled('#next'), true, 'no page after the last');
  await page.click('#prev');
  await page.click('#prev');
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 1');
  assert.deepEqual(await names(), first);
  await page.fill('#tag-filter', 'ring');
  await page.waitForFunction(() => [...document.querySelectorAll('#shape-list li[data-id]')].length === 5
    && [...document.querySelectorAll('#shape-list .tag')].every((t) => t.textContent === 'ring'));
  await page.fill('#tag-filter', '');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length === 10);
});

test('upload a mesh: the query and its hits are drawn in 3D with ranks and scores', async () => {
  await page.setInputFiles('#file', join(SAMPLES, holdOut.path));
  await page.waitForFunction(() => document.querySelectorAll('[data-testid=hit-card]').length > 0, null, { timeout: 120_000 });
  const topk = Number(await page.inputValue('#topk'));
  assert.equal(await page.locator('[data-testid=hit-card]').count(), topk);
  await waitRendered('#grid .view', topk + 1);
  const caps = await page.$$eval('[data-testid=hit-card] figcaption', (f) => f.map((c) => ({
    rank: c.querySelector('.rank').textContent, name: c.children[1].textContent, score: Number(c.querySelector('.score').textContent) })));
  caps.forEach((c, i) => assert.equal(c.rank, `#${i + 1}`));
  for (let i = 1; i < caps.length; i++) assert.ok(caps[i].score >= caps[i - 1].score, 'scores ascend with rank');
  // The held-out pose of a class finds its class first.
  assert.equal(classOf[caps[0].name], holdOut.cls, `top hit ${caps[0].name} is a ${holdOut.cls}`);
  const px = await viewPixels('#grid .view');
  px.forEach((p, i) => {
    assert.ok(p.visible && p.fraction > 0.03, `view ${i} shows a mesh (${(100 * p.fraction).toFixed(1)}% of its pixels)`);
  });
  const [q, ...hits] = px;
  assert.ok(q.mean[2] > q.mean[0] + 20, `the query is drawn blue (${q.mean.map(Math.round)})`);
  for (const h of hits) assert.ok(h.mean[0] > h.mean[2] + 20, `hits are drawn orange (${h.mean.map(Math.round)})`);
  // Orbit: dragging one view turns the one camera, so every view changes.
  const before = await page.evaluate(() => document.getElementById('gl').toDataURL());
  const box = await page.locator('#grid .view').first().boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width / 2 + 80, box.y + box.height / 2 + 20, { steps: 5 });
  await page.mouse.up();
  const afterOrbit = await page.evaluate(() => { window.shapeseekViewer.render(); return document.getElementById('gl').toDataURL(); });
  assert.notEqual(afterOrbit, before, 'orbiting changes the picture');
  await page.screenshot({ path: join(SHOTS, 'viewer-upload-search.png') });
  assert.match(await page.textContent('#status'), /hits of \d+ candidates · stages: scan → reciprocal ·/);
});

test('open a hit next to the query and plot the distance distributions', async () => {
  // A stored query: both distributions are available.
  const row = page.locator('#shape-list li[data-id]').filter({ hasText: 'biped-null' });
  if (await row.count() === 0) await page.fill('#tag-filter', 'biped');
  await page.locator('#shape-list li[data-id]').filter({ hasText: 'biped-null' }).locator('[data-testid=search-stored]').click();
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes('biped-null'));
  await waitRendered('#grid .view', 9);
  await page.locator('[data-testid=hit-card]').first().click();
  await page.waitForSelector('#compare:not([hidden])');
  await waitRendered('#compare .view', 2);
  await page.waitForSelector('#plot svg path[data-series="1"]');
  assert.equal(await page.locator('#plot svg path[data-series]').count(), 2, 'query and hit');
  const channels = await page.$$eval('#channel option', (o) => o.map((x) => x.value));
  assert.ok(channels.length >= 1, 'channels to choose from');
  const px = await viewPixels('#compare .view');
  px.forEach((p, i) => assert.ok(p.fraction > 0.03, `compare view ${i} shows a mesh`));
  // The density curve has area ≈ 1, the CDF ends at 1: check the drawn paths are not flat.
  const heights = await page.$$eval('#plot svg path[data-series]', (ps) => ps.map((p) => {
    const ys = p.getAttribute('d').split(/[ML]/).filter(Boolean).map((s) => Number(s.split(',')[1]));
    return Math.max(...ys) - Math.min(...ys);
  }));
  for (const h of heights) assert.ok(h > 50, `a distribution spans ${h} px`);
  await page.screenshot({ path: join(SHOTS, 'viewer-compare.png') });
  await page.check('input[name=plot-kind][value=cdf]');
  await page.waitForSelector('#plot svg[data-kind=cdf]');
  if (channels.length > 1) {
    await page.selectOption('#channel', channels[channels.length - 1]);
    await page.waitForFunction((c) => document.querySelector('#plot svg')?.textContent.includes(`channel ${c}`), channels[channels.length - 1]);
  }
  await page.click('#compare-close');
  assert.equal(await page.isHidden('#compare'), true);
  await page.fill('#tag-filter', '');
});

test('re-ranking stages: the scan alone, or chosen stages', async () => {
  await page.check('[data-testid=rerank-custom]');
  await page.locator('#shape-list li[data-id]').first().locator('[data-testid=search-stored]').click();
  await page.waitForFunction(() => /stages: scan ·/.test(document.getElementById('status').textContent));
  await page.check('[data-testid=st-exact]');
  await page.locator('#shape-list li[data-id]').first().locator('[data-testid=search-stored]').click();
  await page.waitForFunction(() => /stages: scan → exact ·/.test(document.getElementById('status').textContent));
  await page.uncheck('[data-testid=st-exact]');
  await page.check('[data-testid=rerank-default]');
});

test('double clicks: "next" turns one page, and "delete" asks again', async () => {
  const names = () => page.$$eval('#shape-list li[data-id] .name', (n) => n.map((x) => x.textContent));
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 1');
  const first = await names();
  // Before: the second click came before page 2 and took page 1's cursor again, so "page 3"
  // showed page 2's shapes.
  await page.dblclick('#next');
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 2' && !document.getElementById('prev').disabled);
  await page.waitForTimeout(300);
  assert.equal(await page.textContent('#page'), 'page 2');
  const second = await names();
  assert.equal(second.filter((n) => first.includes(n)).length, 0, 'page 2 has other shapes');
  await page.click('#prev');
  await page.waitForFunction(() => document.getElementById('page').textContent === 'page 1' && !document.getElementById('next').disabled);
  assert.deepEqual(await names(), first);
  // Before: a double click on "delete" armed and confirmed at once.
  const deletes = [];
  const seen = (req) => { if (req.method() === 'DELETE') deletes.push(req.url()); };
  page.on('request', seen);
  const row = page.locator('#shape-list li[data-id]').first();
  await row.locator('[data-testid=delete]').dblclick();
  await page.waitForTimeout(500);
  assert.equal(await row.locator('[data-testid=delete]').textContent(), 'sure?');
  assert.deepEqual(deletes, [], 'no DELETE sent');
  assert.deepEqual(await names(), first);
  page.off('request', seen);
  // Left as it was: unarmed after its 4 s.
  await page.waitForFunction(() => document.querySelector('#shape-list li[data-id] [data-testid=delete]').textContent === 'delete', null, { timeout: 10_000 });
});

test('a malformed upload shows the API\'s problem+json error', async () => {
  await page.setInputFiles('#file', { name: 'broken.obj', mimeType: 'model/obj', buffer: Buffer.from('v 1 2 oops\nf 1 2 3\n') });
  await page.waitForSelector('#error:not([hidden])');
  const code = await page.getAttribute('#error', 'data-code');
  const text = await page.textContent('#error');
  assert.match(code, /^mesh\./, `a mesh error code (${code})`);
  assert.match(text, /HTTP 4\d\d/);
  assert.ok(text.includes(code));
  assert.match(await page.textContent('#status'), /broken\.obj: not searched/);
  await page.screenshot({ path: join(SHOTS, 'viewer-error.png') });
});

test('delete a stored shape from the list', async () => {
  const info0 = await page.textContent('#index-info');
  const n0 = parseInt(info0, 10);
  const row = page.locator('#shape-list li[data-id]').first();
  const id = await row.getAttribute('data-id');
  await row.locator('[data-testid=delete]').click();
  assert.equal(await row.locator('[data-testid=delete]').textContent(), 'sure?');
  await row.locator('[data-testid=delete]').click();
  await page.waitForFunction((i) => !document.querySelector(`#shape-list li[data-id="${i}"]`), id);
  await page.waitForFunction((n) => parseInt(document.getElementById('index-info').textContent, 10) === n - 1, n0);
  const resp = await page.request.get(`${URL_}/v1/shapes/${id}`);
  assert.equal(resp.status(), 404);
  assert.match(resp.headers()['content-type'], /problem\+json/);
});

test('a search still being analysed does not draw over a later one', async () => {
  // The upload's search is held back until a stored shape's search has been drawn.
  let release;
  const held = new Promise((r) => { release = r; });
  const isUpload = (req) => req.method() === 'POST' && (req.headers()['content-type'] || '').startsWith('multipart/');
  const slow = async (route) => {
    if (isUpload(route.request())) await held;
    return route.continue();
  };
  await page.route('**/v1/search', slow);
  await page.setInputFiles('#file', join(SAMPLES, holdOut.path));
  await page.waitForFunction(() => /analysing/.test(document.getElementById('status').textContent));
  const row = page.locator('#shape-list li[data-id]').first();
  const name = await row.locator('.name').textContent();
  await row.locator('[data-testid=search-stored]').click();
  await page.waitForFunction((n) => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes(n), name);
  await page.waitForFunction(() => /hits of \d+ candidates/.test(document.getElementById('status').textContent));
  const hitNames = () => page.$$eval('[data-testid=hit-card] figcaption', (f) => f.map((c) => c.children[1].textContent));
  const drawn = await hitNames();
  assert.ok(drawn.length > 0);
  const uploadAnswered = page.waitForResponse((r) => r.url().endsWith('/v1/search') && isUpload(r.request()));
  release();
  await uploadAnswered;
  // Before: the upload's hits were drawn under the stored shape's query card, and the status
  // line became the upload's.
  await page.waitForTimeout(1000);
  const caption = await page.textContent('[data-testid=query-card] figcaption');
  assert.ok(caption.includes(name), `the query card shows ${name}: ${caption}`);
  assert.deepEqual(await hitNames(), drawn, 'the stored shape\'s hits stay');
  assert.doesNotMatch(await page.textContent('#status'), /analysing the upload/);
  await page.unroute('**/v1/search', slow);
});

test('a view whose mesh failed to load is loaded again by the next search', async () => {
  // A fresh page: no mesh loaded yet.
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length > 0);
  const row = page.locator('#shape-list li[data-id]').first();
  const id = await row.getAttribute('data-id');
  const busy = (route) => route.fulfill({
    status: 503, contentType: 'application/problem+json', headers: { 'retry-after': '1' },
    body: JSON.stringify({ title: 'Service Unavailable', status: 503, code: 'server.busy', detail: 'the test says so' }),
  });
  await page.route(`**/v1/shapes/${id}/mesh*`, busy);
  await row.locator('[data-testid=search-stored]').click();
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] .view')?.dataset.rendered === 'error');
  await page.unroute(`**/v1/shapes/${id}/mesh*`, busy);
  // Before: the failure was kept, and the shape showed "cannot display" until a reload.
  await row.locator('[data-testid=search-stored]').click();
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] .view')?.dataset.rendered === '1', null, { timeout: 60_000 });
});

test('a file over the server\'s upload limit is refused before it is sent', async () => {
  const small = async (route) => {
    const resp = await route.fetch();
    const info = await resp.json();
    info.limits.max_body_bytes = 5000;
    return route.fulfill({ response: resp, json: info });
  };
  await page.route('**/v1/index', small);
  const posts = [];
  const watch = (req) => { if (req.method() === 'POST') posts.push(req.url()); };
  page.on('request', watch);
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => /stored shapes/.test(document.getElementById('index-info').textContent));
  await page.setInputFiles('#file', { name: 'big.obj', mimeType: 'model/obj', buffer: Buffer.from(`# ${'x'.repeat(10_000)}\n`) });
  await page.waitForSelector('#error:not([hidden])');
  assert.equal(await page.getAttribute('#error', 'data-code'), 'limit.bytes');
  assert.match(await page.textContent('#error'), /big\.obj has 10003 bytes; the server takes uploads up to 5000 bytes/);
  assert.deepEqual(posts, [], 'nothing was sent');
  page.off('request', watch);
  await page.unroute('**/v1/index', small);
  // The file chooser is reachable from the keyboard (it was display: none).
  assert.notEqual(await page.$eval('#file', (e) => getComputedStyle(e).display), 'none');
  await page.focus('#file');
  assert.equal(await page.evaluate(() => document.activeElement.id), 'file');
});

test('a page opened while the server loads its index says so, and lists the shapes once it is ready', async () => {
  const notReady = (route) => route.fulfill({
    status: 503, contentType: 'application/problem+json', headers: { 'retry-after': '1' },
    body: JSON.stringify({ title: 'Service Unavailable', status: 503, code: 'server.not_ready', detail: 'not ready: the index is loading' }),
  });
  let indexLeft = 2;
  const index = (route) => (indexLeft-- > 0 ? notReady(route) : route.continue());
  let listLeft = 1;
  const list = (route) => (listLeft-- > 0 ? notReady(route) : route.continue());
  await page.route('**/v1/index', index);
  await page.route('**/v1/shapes?*', list);
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => /loading its index; asking again in 1 s/.test(document.getElementById('index-info').textContent));
  assert.equal(await page.isHidden('#error'), true, 'a loading server is not an error');
  // Before: "index unavailable", the 503 in the error box and an empty list until a reload.
  await page.waitForFunction(() => /stored shapes/.test(document.getElementById('index-info').textContent), null, { timeout: 20_000 });
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length > 0);
  assert.equal(await page.isHidden('#error'), true);
  await page.unroute('**/v1/index', index);
  await page.unroute('**/v1/shapes?*', list);
});

test('hits open from the keyboard, and the wheel over a view scrolls the page (Ctrl+wheel zooms)', async () => {
  await page.setViewportSize({ width: 1000, height: 500 });
  await page.locator('#shape-list li[data-id]').first().locator('[data-testid=search-stored]').click();
  await waitRendered('#grid .view', 9);
  // Keyboard: a hit card takes the focus and Enter opens it (it opened only on a click).
  await page.focus('[data-testid=hit-card]');
  await page.keyboard.press('Enter');
  await page.waitForSelector('#compare:not([hidden])');
  await page.click('#compare-close');
  // The wheel over a view scrolls the page and leaves the camera where it is (it zoomed, and
  // the page did not scroll).
  const distance = () => page.evaluate(() => [...window.shapeseekViewer.views.values()][0].controls.object.position.length());
  await page.evaluate(() => window.scrollTo(0, 0));
  const d0 = await distance();
  const box = await page.locator('#grid .view').first().boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  await page.mouse.wheel(0, 200);
  await page.waitForFunction(() => window.scrollY > 0);
  assert.equal(await distance(), d0, 'the wheel alone does not zoom');
  await page.evaluate(() => window.scrollTo(0, 0));
  const b2 = await page.locator('#grid .view').first().boundingBox();
  await page.mouse.move(b2.x + b2.width / 2, b2.y + b2.height / 2);
  await page.keyboard.down('Control');
  await page.mouse.wheel(0, 200);
  await page.keyboard.up('Control');
  await page.waitForFunction((d) => [...window.shapeseekViewer.views.values()][0].controls.object.position.length() !== d, d0);
  assert.equal(await page.evaluate(() => window.scrollY), 0, 'Ctrl+wheel zooms instead of scrolling');
  await page.setViewportSize({ width: 1400, height: 1000 });
});

test('stored shapes are drawn whatever form the server read them from: glTF without scenes, NCOFF, OBJ named .ply', async () => {
  // Three copies of a stored shape, in forms the server reads and the page's own readers did
  // not: the server hands the page every stored shape as binary PLY (`?format=ply`).
  const [rec] = (await (await fetch(`${URL_}/v1/shapes?limit=1`)).json()).items;
  const as = async (f) => (await fetch(`${URL_}/v1/shapes/${rec.id}/mesh?format=${f}`)).text();
  const gltf = JSON.parse(await as('gltf'));
  delete gltf.scene;
  delete gltf.scenes;
  const off = (await as('off')).replace(/^OFF/, 'NCOFF');
  assert.ok(off.startsWith('NCOFF'));
  const obj = `${await as('obj')}# a copy\n`;
  const files = [['no-scene.gltf', JSON.stringify(gltf)], ['header.off', off], ['text.ply', obj]];
  const ids = [];
  for (const [name, text] of files) {
    const r = await fetch(`${URL_}/v1/shapes?name=${name}&tags=oddform`, {
      method: 'POST', headers: { 'content-type': 'application/octet-stream' }, body: text,
    });
    assert.equal(r.status, 201, `${name}: ${await r.clone().text()}`);
    ids.push((await r.json()).id);
  }
  await page.goto(URL_ + '/');
  await page.fill('#tag-filter', 'oddform');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length === 3);
  for (const [name] of files) {
    const row = page.locator('#shape-list li[data-id]', { hasText: name });
    await row.locator('[data-testid=search-stored]').click();
    await page.waitForFunction((n) => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes(n), name);
    // Before: "cannot display" for the glTF (no scene) and the NCOFF file.
    await waitRendered('[data-testid=query-card] .view', 1);
  }
  // An upload named against its content is read by what it holds, as the server does.
  await page.setInputFiles('#file', { name: 'upload.ply', mimeType: 'application/octet-stream', buffer: Buffer.from(`${obj}# again\n`) });
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes('upload.ply'), null, { timeout: 120_000 });
  await waitRendered('[data-testid=query-card] .view', 1);
  // An upload without scenes whose material names an image elsewhere: drawn by the page's own
  // reader, and nothing is fetched from elsewhere (the worker has no image to load).
  const textured = JSON.parse(JSON.stringify(gltf));
  textured.images = [{ uri: 'http://example.invalid/texture.png' }];
  textured.textures = [{ source: 0 }];
  textured.materials = [{ pbrMetallicRoughness: { baseColorTexture: { index: 0 } } }];
  textured.meshes[0].primitives[0].material = 0;
  const requested = [];
  const onRequest = (r) => requested.push(r.url());
  page.context().on('request', onRequest);
  const noHits = (route) => route.fulfill({
    status: 200, contentType: 'application/json', body: JSON.stringify({ hits: [], candidates: 0, stages: [], timings: {} }),
  });
  await page.route('**/v1/search', noHits);
  await page.setInputFiles('#file', { name: 'textured.gltf', mimeType: 'model/gltf+json', buffer: Buffer.from(JSON.stringify(textured)) });
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes('textured.gltf'), null, { timeout: 60_000 });
  await waitRendered('[data-testid=query-card] .view', 1);
  // The same as GLB (its JSON chunk rewritten by the page's reader, the binary chunk kept).
  const glb = Buffer.from(await (await fetch(`${URL_}/v1/shapes/${rec.id}/mesh?format=glb`)).arrayBuffer());
  const jsonLen = glb.readUInt32LE(12);
  const glbJson = JSON.parse(glb.subarray(20, 20 + jsonLen).toString('utf8'));
  Object.assign(glbJson, { images: textured.images, textures: textured.textures, materials: textured.materials });
  glbJson.meshes[0].primitives[0].material = 0;
  let text = Buffer.from(JSON.stringify(glbJson));
  text = Buffer.concat([text, Buffer.alloc((4 - (text.length % 4)) % 4, 0x20)]);
  const header = Buffer.alloc(20);
  header.write('glTF', 0);
  header.writeUInt32LE(2, 4);
  header.writeUInt32LE(20 + text.length + glb.length - 20 - jsonLen, 8);
  header.writeUInt32LE(text.length, 12);
  header.writeUInt32LE(0x4e4f534a, 16);
  const texturedGlb = Buffer.concat([header, text, glb.subarray(20 + jsonLen)]);
  await page.setInputFiles('#file', { name: 'textured.glb', mimeType: 'model/gltf-binary', buffer: texturedGlb });
  await page.waitForFunction(() => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes('textured.glb'), null, { timeout: 60_000 });
  await waitRendered('[data-testid=query-card] .view', 1);
  await page.unroute('**/v1/search', noHits);
  page.context().off('request', onRequest);
  assert.deepEqual(requested.filter((u) => !u.startsWith(URL_) && !u.startsWith('data:') && !u.startsWith('blob:')), []);
  await page.fill('#tag-filter', '');
  for (const id of ids) assert.equal((await fetch(`${URL_}/v1/shapes/${id}`, { method: 'DELETE' })).status, 204);
});

/** A UV sphere of `n` × 2n segments as OBJ text. */
function sphereObj(n) {
  const lines = [];
  for (let i = 0; i <= n; i++) {
    const th = (Math.PI * i) / n;
    for (let j = 0; j < 2 * n; j++) {
      const ph = (Math.PI * j) / n;
      lines.push(`v ${(Math.sin(th) * Math.cos(ph)).toFixed(6)} ${(Math.sin(th) * Math.sin(ph)).toFixed(6)} ${Math.cos(th).toFixed(6)}`);
    }
  }
  const v = (i, j) => i * 2 * n + (j % (2 * n)) + 1;
  for (let i = 0; i < n; i++) {
    for (let j = 0; j < 2 * n; j++) lines.push(`f ${v(i, j)} ${v(i + 1, j)} ${v(i + 1, j + 1)}`, `f ${v(i, j)} ${v(i + 1, j + 1)} ${v(i, j + 1)}`);
  }
  return `${lines.join('\n')}\n`;
}

test('a large upload is read off the main thread: the page keeps answering while it parses', async () => {
  const obj = sphereObj(300); // 180 600 vertices, 360 000 faces, about 13 MB of text
  // The search is answered here (no hits): only the page's reading of the file is measured.
  const noHits = (route) => route.fulfill({
    status: 200, contentType: 'application/json', body: JSON.stringify({ hits: [], candidates: 0, stages: [], timings: {} }),
  });
  await page.route('**/v1/search', noHits);
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length > 0);
  // The main thread's long tasks (Long Tasks API), the moment the page gets the file (its
  // `change` event) and the moment the query's view has its geometry (`data-rendered`): the
  // reading is everything between the two. (Handing the test's file to the page is itself a
  // long task, before `change`; drawing the mesh, after.)
  await page.evaluate(() => {
    const t = (window.readTimes = { tasks: [] });
    new PerformanceObserver((l) => {
      for (const e of l.getEntries()) t.tasks.push([e.startTime, e.duration]);
    }).observe({ type: 'longtask' });
    document.getElementById('file').addEventListener('change', () => { t.change = performance.now(); }, { capture: true });
    new MutationObserver(() => {
      const v = document.querySelector('[data-testid=query-card] .view');
      if (v && v.dataset.rendered && !t.rendered) t.rendered = performance.now();
    }).observe(document.body, { subtree: true, attributes: true, childList: true });
  });
  await page.setInputFiles('#file', { name: 'big.obj', mimeType: 'model/obj', buffer: Buffer.from(obj) });
  await waitRendered('[data-testid=query-card] .view', 1);
  await page.waitForTimeout(500);
  const t = await page.evaluate(() => window.readTimes);
  const during = t.tasks.filter(([start]) => start >= t.change && start < t.rendered);
  const longest = Math.max(0, ...during.map(([, d]) => d));
  console.log(`a ${(obj.length / 1e6).toFixed(1)} MB OBJ read in ${(t.rendered - t.change).toFixed(0)} ms; `
    + `longest main-thread task meanwhile ${longest.toFixed(0)} ms; all: ${JSON.stringify(t.tasks.map(([s, d]) => [Math.round(s - t.change), Math.round(d)]))}`);
  // Before (read on the main thread): one task of about 1 000 ms in that window.
  assert.ok(longest < 250, `the main thread was blocked for ${longest.toFixed(0)} ms while the file was read`);
  await page.unroute('**/v1/search', noHits);
});

/** A GLB of a JSON chunk `text` and a BIN chunk `body` (both already padded to 4 bytes). */
function glbOf(text, body) {
  const chunk = (type, data) => {
    const h = Buffer.alloc(8);
    h.writeUInt32LE(data.length, 0);
    h.write(type, 4, 'latin1');
    return Buffer.concat([h, data]);
  };
  const chunks = Buffer.concat([chunk('JSON', text), chunk('BIN\0', body)]);
  const head = Buffer.alloc(12);
  head.write('glTF', 0, 'latin1');
  head.writeUInt32LE(2, 4);
  head.writeUInt32LE(12 + chunks.length, 8);
  return Buffer.concat([head, chunks]);
}

/** The parts of a one-primitive GLB: its JSON, BIN chunk, primitive, position accessor, the
 * byte offset of the first position and the positions' stride. */
function glbParts(glb) {
  const jsonLen = glb.readUInt32LE(12);
  const json = JSON.parse(glb.subarray(20, 20 + jsonLen).toString('utf8'));
  const bin = glb.subarray(20 + jsonLen + 8);
  const prim = json.meshes[0].primitives[0];
  const acc = json.accessors[prim.attributes.POSITION];
  const view = json.bufferViews[acc.bufferView];
  const at = (view.byteOffset || 0) + (acc.byteOffset || 0);
  return { json, bin, prim, acc, at, stride: view.byteStride || 12 };
}

/** A float-position GLB (one mesh, one primitive, as `shapeseek samples` writes it) rewritten as
 * gltfpack writes it by default: positions as normalized u16 in an 8-byte stride, the node's
 * scale and translation undoing the quantization, `KHR_mesh_quantization` required. */
function quantizeGlb(glb) {
  const { json, bin, prim, acc, at, stride } = glbParts(glb);
  const lo = acc.min;
  const span = Math.max(...acc.max.map((x, k) => x - lo[k]));
  const pos = Buffer.alloc(acc.count * 8);
  for (let i = 0; i < acc.count; i++) {
    for (let k = 0; k < 3; k++) {
      const x = bin.readFloatLE(at + i * stride + 4 * k);
      pos.writeUInt16LE(Math.round(((x - lo[k]) / span) * 65535), 8 * i + 2 * k);
    }
  }
  const idx = json.accessors[prim.indices];
  const iview = json.bufferViews[idx.bufferView];
  const ibytes = bin.subarray(iview.byteOffset || 0, (iview.byteOffset || 0) + iview.byteLength);
  const out = {
    asset: { version: '2.0' },
    extensionsUsed: ['KHR_mesh_quantization'],
    extensionsRequired: ['KHR_mesh_quantization'],
    buffers: [{ byteLength: pos.length + ibytes.length }],
    bufferViews: [
      { buffer: 0, byteLength: pos.length, byteStride: 8, target: 34962 },
      { buffer: 0, byteOffset: pos.length, byteLength: ibytes.length, target: 34963 },
    ],
    accessors: [
      { bufferView: 0, componentType: 5123, normalized: true, count: acc.count, type: 'VEC3', min: [0, 0, 0], max: [65535, 65535, 65535] },
      { bufferView: 1, componentType: idx.componentType, count: idx.count, type: 'SCALAR' },
    ],
    meshes: [{ primitives: [{ attributes: { POSITION: 0 }, indices: 1 }] }],
    nodes: [{ mesh: 0, scale: [span, span, span], translation: lo }],
    scenes: [{ nodes: [0] }],
    scene: 0,
  };
  let text = Buffer.from(JSON.stringify(out));
  text = Buffer.concat([text, Buffer.alloc((4 - (text.length % 4)) % 4, 0x20)]);
  let body = Buffer.concat([pos, ibytes]);
  body = Buffer.concat([body, Buffer.alloc((4 - (body.length % 4)) % 4)]);
  return glbOf(text, body);
}

/** A float-position GLB (as `shapeseek samples` writes it) with its positions and indices
 * meshopt-compressed as `gltfpack -cc` writes them (`EXT_meshopt_compression`: the encoded bytes
 * in the BIN chunk, the views in a fallback buffer without data). */
async function meshoptGlb(glb) {
  await MeshoptEncoder.ready;
  const { json, bin, prim, acc, at, stride } = glbParts(glb);
  const pos = new Uint8Array(acc.count * 12);
  for (let i = 0; i < acc.count; i++) {
    pos.set(bin.subarray(at + i * stride, at + i * stride + 12), 12 * i);
  }
  const idx = json.accessors[prim.indices];
  const iview = json.bufferViews[idx.bufferView];
  const isize = idx.componentType === 5125 ? 4 : 2;
  const ibytes = new Uint8Array(bin.subarray(iview.byteOffset || 0, (iview.byteOffset || 0) + idx.count * isize));
  const vEnc = Buffer.from(MeshoptEncoder.encodeGltfBuffer(pos, acc.count, 12, 'ATTRIBUTES'));
  const iEnc = Buffer.from(MeshoptEncoder.encodeGltfBuffer(ibytes, idx.count, isize, 'TRIANGLES'));
  const pad = (b, byte = 0) => Buffer.concat([b, Buffer.alloc((4 - (b.length % 4)) % 4, byte)]);
  const vPad = pad(vEnc);
  const ext = 'EXT_meshopt_compression';
  const out = {
    asset: { version: '2.0' },
    extensionsUsed: [ext],
    extensionsRequired: [ext],
    buffers: [
      { byteLength: vPad.length + iEnc.length },
      { byteLength: pos.length + ibytes.length, extensions: { [ext]: { fallback: true } } },
    ],
    bufferViews: [
      { buffer: 1, byteLength: pos.length, byteStride: 12, target: 34962,
        extensions: { [ext]: { buffer: 0, byteLength: vEnc.length, byteStride: 12, count: acc.count, mode: 'ATTRIBUTES' } } },
      { buffer: 1, byteOffset: pos.length, byteLength: ibytes.length, target: 34963,
        extensions: { [ext]: { buffer: 0, byteOffset: vPad.length, byteLength: iEnc.length, byteStride: isize, count: idx.count, mode: 'TRIANGLES' } } },
    ],
    accessors: [
      { bufferView: 0, componentType: 5126, count: acc.count, type: 'VEC3', min: acc.min, max: acc.max },
      { bufferView: 1, componentType: idx.componentType, count: idx.count, type: 'SCALAR' },
    ],
    meshes: [{ primitives: [{ attributes: { POSITION: 0 }, indices: 1 }] }],
    nodes: [{ mesh: 0 }],
    scenes: [{ nodes: [0] }],
    scene: 0,
  };
  const text = pad(Buffer.from(JSON.stringify(out)), 0x20);
  const body = pad(Buffer.concat([vPad, iEnc]));
  return glbOf(text, body);
}

test('a quantized glTF (KHR_mesh_quantization, as gltfpack writes it) and a meshopt-compressed one are drawn as their float original', async () => {
  const sample = manifest.find((m) => m.path.endsWith('.glb'));
  assert.ok(sample, 'a GLB among the samples');
  const dir = mkdtempSync(join(tmpdir(), 'quantized-'));
  const quantized = join(dir, `${sample.id}-quantized.glb`);
  writeFileSync(quantized, quantizeGlb(readFileSync(join(SAMPLES, sample.path))));
  await page.goto(URL_ + '/');
  await page.waitForFunction(() => document.querySelectorAll('#shape-list li[data-id]').length > 0);
  const drawn = async (file) => {
    const name = file.split('/').pop();
    await page.setInputFiles('#file', file);
    await page.waitForFunction((n) => document.querySelector('[data-testid=query-card] figcaption')?.textContent.includes(n)
      && document.querySelectorAll('[data-testid=hit-card]').length > 0, name, { timeout: 120_000 });
    await waitRendered('#grid .view', 2);
    const [q] = await viewPixels('#grid .view', true);
    const top = await page.$eval('[data-testid=hit-card] figcaption', (c) => c.children[1].textContent);
    return { ...q, top };
  };
  const float = await drawn(join(SAMPLES, sample.path));
  const quant = await drawn(quantized);
  assert.equal(quant.mask.length, float.mask.length);
  let both = 0, either = 0;
  float.mask.forEach((f, i) => { both += f & quant.mask[i]; either += f | quant.mask[i]; });
  const iou = both / either;
  console.log(`${sample.id}: query view covered ${(100 * float.fraction).toFixed(1)}% as float, `
    + `${(100 * quant.fraction).toFixed(1)}% quantized, overlap (IoU) ${iou.toFixed(3)}; top hits ${float.top}, ${quant.top}`);
  // The same surface to 1/65535 of its size: the same picture. Before, positions were
  // transformed in their u16 array and clamped to it: a box.
  assert.ok(iou > 0.95, `the quantized file's drawing overlaps the float one's by ${iou.toFixed(3)}`);
  // And the server read it as the same shape.
  assert.equal(classOf[quant.top], sample.cls);

  // Meshopt-compressed (gltfpack -cc): the worker decodes it (WebAssembly, which its policy
  // allows), the server too. Before, the server refused it (422 naming the extension) and the
  // page's loader failed ("setMeshoptDecoder must be called before loading compressed files").
  const compressed = join(dir, `${sample.id}-meshopt.glb`);
  writeFileSync(compressed, await meshoptGlb(readFileSync(join(SAMPLES, sample.path))));
  const packed = await drawn(compressed);
  both = 0; either = 0;
  float.mask.forEach((f, i) => { both += f & packed.mask[i]; either += f | packed.mask[i]; });
  const iouPacked = both / either;
  console.log(`${sample.id}: meshopt-compressed, ${readFileSync(compressed).length} bytes against `
    + `${readFileSync(join(SAMPLES, sample.path)).length}: covered ${(100 * packed.fraction).toFixed(1)}%, `
    + `overlap (IoU) ${iouPacked.toFixed(3)}; top hit ${packed.top}`);
  // Lossless: the same picture (the same surface as the float original).
  assert.ok(iouPacked > 0.98, `the compressed file's drawing overlaps the float one's by ${iouPacked.toFixed(3)}`);
  assert.equal(classOf[packed.top], sample.cls);
});

test('no script errors and no foreign requests', () => {
  // The malformed upload's 4xx, and the 503s a test answers in the server's place, are logged
  // by the browser as failed resources; nothing else.
  const unexpected = consoleErrors.filter((e) => !/status of (4\d\d|503)/.test(e));
  assert.deepEqual(unexpected, []);
  // Every file the page or the browser asked for was there (before the page named its icon,
  // the browser's /favicon.ico request was a 404, hidden by the filter above).
  assert.deepEqual(failedPageRequests, []);
});
