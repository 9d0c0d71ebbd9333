// shapeseek viewer: the query and its hits in 3D (three.js), distance distributions, stored
// shapes. Talks only to the same-origin REST API (see /openapi.yaml).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { formatOf } from './format.js';
import { distributionFromSketch, plotDistributions } from './plot.js';

const $ = (id) => document.getElementById(id);
const PAGE = 10;

// ---------------------------------------------------------------------------------------------
// API calls; every error becomes an ApiError carrying the problem+json fields.

class ApiError extends Error {
  constructor(problem) {
    super(problem.detail || problem.title || 'request failed');
    this.problem = problem;
  }
}

async function api(method, path, body, headers = {}) {
  let resp;
  try {
    resp = await fetch(path, { method, body, headers });
  } catch (e) {
    throw new ApiError({ title: 'network error', code: 'client.network', detail: String(e) });
  }
  if (resp.ok) return resp;
  const ct = resp.headers.get('content-type') || '';
  let problem;
  if (ct.includes('json')) {
    try { problem = await resp.json(); } catch { /* fall through */ }
  }
  if (!problem) problem = { title: resp.statusText, status: resp.status, detail: await resp.text().catch(() => '') };
  problem.status = problem.status || resp.status;
  const err = new ApiError(problem);
  err.retryAfter = parseInt(resp.headers.get('retry-after') || '', 10) || null;
  throw err;
}

const getJson = async (path) => (await api('GET', path)).json();
const postJson = async (path, obj) =>
  (await api('POST', path, JSON.stringify(obj), { 'content-type': 'application/json' })).json();

function showError(err) {
  const box = $('error');
  if (!err) { box.hidden = true; box.textContent = ''; return; }
  const p = err.problem || { title: 'error', detail: String(err && err.message || err) };
  box.replaceChildren();
  const strong = document.createElement('strong');
  strong.textContent = `${p.title || 'error'}${p.status ? ` (HTTP ${p.status})` : ''}`;
  box.append(strong);
  if (p.code) {
    const code = document.createElement('code');
    code.textContent = p.code;
    box.append(' ', code);
  }
  box.append(`: ${p.detail || ''}`);
  box.dataset.code = p.code || '';
  box.hidden = false;
}

function setStatus(text) { $('status').textContent = text; }

// ---------------------------------------------------------------------------------------------
// Meshes are read in a worker (parse-worker.js, parse.js): a large file parses while the page
// stays responsive. One worker, requests answered in order.

let worker = null;
let workerSeq = 0;
const pending = new Map(); // request id -> { resolve, reject }

function meshWorker() {
  if (!worker) {
    worker = new Worker(new URL('./parse-worker.js', import.meta.url), { type: 'module' });
    worker.onmessage = ({ data }) => {
      const p = pending.get(data.id);
      if (!p) return;
      pending.delete(data.id);
      if (data.error) p.reject(new Error(data.error));
      else p.resolve(data);
    };
    worker.onerror = (e) => {
      // The worker itself failed (not a file it could not read): it is stopped, every request
      // fails, and the next one starts a new worker.
      const err = new Error(`the mesh reader stopped: ${e.message || 'worker error'}`);
      worker.terminate();
      for (const p of pending.values()) p.reject(err);
      pending.clear();
      worker = null;
    };
  }
  return worker;
}

/** `bytes` of `format` as a drawable geometry (welded, normalised; see parse.js). */
async function readGeometry(bytes, format, align, transfer = false) {
  const id = ++workerSeq;
  const data = await new Promise((resolve, reject) => {
    pending.set(id, { resolve, reject });
    meshWorker().postMessage({ id, bytes, format, align }, transfer ? [bytes.buffer] : []);
  });
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(data.position, 3));
  g.setAttribute('normal', new THREE.BufferAttribute(data.normal, 3));
  if (data.index) g.setIndex(new THREE.BufferAttribute(data.index, 1));
  g.computeBoundingSphere();
  return g;
}

// ---------------------------------------------------------------------------------------------
// Rendering: one canvas behind the page, one scene per view element, one shared camera.

const canvas = $('gl');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true, alpha: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
renderer.setScissorTest(true);
const camera = new THREE.PerspectiveCamera(35, 1, 0.05, 20);
camera.position.set(0.6, 0.8, 3.2);
const views = new Map(); // element -> { scene, controls }
let dirty = true;

function makeScene(geometry, color) {
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf7f9fc);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x8899aa, 1.3));
  const light = new THREE.DirectionalLight(0xffffff, 2.2); // follows the camera (renderAll)
  scene.add(light);
  scene.userData.light = light;
  const mat = new THREE.MeshStandardMaterial({ color, roughness: 0.6, metalness: 0.05, side: THREE.DoubleSide });
  scene.add(new THREE.Mesh(geometry, mat));
  return scene;
}

// The wheel over a view scrolls the page (the views fill it: zooming on every wheel turn made
// the page hard to scroll); with Ctrl held it zooms (Shift turns the wheel sideways in
// Chromium), within bounds that keep the shape in sight.
function zoomOnlyWithModifier(ev) {
  const v = views.get(ev.currentTarget);
  if (v) v.controls.enableZoom = ev.ctrlKey;
}

function attachView(el, geometry, color) {
  detachView(el);
  const controls = new OrbitControls(camera, el);
  controls.enableDamping = false;
  controls.enableZoom = false;
  controls.minDistance = 1.2;
  controls.maxDistance = 8;
  controls.addEventListener('change', () => { dirty = true; });
  // Before OrbitControls' own listener (capture phase), which cancels the scroll when zooming.
  el.addEventListener('wheel', zoomOnlyWithModifier, { capture: true });
  views.set(el, { scene: makeScene(geometry, color), controls });
  dirty = true;
}

function detachView(el) {
  const v = views.get(el);
  if (!v) return;
  v.controls.dispose();
  el.removeEventListener('wheel', zoomOnlyWithModifier, { capture: true });
  v.scene.traverse((o) => { if (o.isMesh) { o.geometry.dispose(); o.material.dispose(); } });
  views.delete(el);
  dirty = true;
}

function renderAll() {
  const w = canvas.clientWidth;
  const h = canvas.clientHeight;
  if (canvas.width !== Math.floor(w * renderer.getPixelRatio()) || canvas.height !== Math.floor(h * renderer.getPixelRatio())) {
    renderer.setSize(w, h, false);
  }
  renderer.setScissor(0, 0, w, h);
  renderer.setClearColor(0x000000, 0);
  renderer.clear();
  for (const [el, v] of views) {
    if (!el.isConnected) { detachView(el); continue; }
    const r = el.getBoundingClientRect();
    if (r.bottom < 0 || r.top > h || r.right < 0 || r.left > w || r.width === 0) continue;
    const bottom = h - r.bottom;
    renderer.setViewport(r.left, bottom, r.width, r.height);
    renderer.setScissor(r.left, bottom, r.width, r.height);
    camera.aspect = r.width / r.height;
    camera.updateProjectionMatrix();
    v.scene.userData.light.position.copy(camera.position).add(camera.up.clone().multiplyScalar(0.8));
    renderer.render(v.scene, camera);
  }
}

function loop() {
  if (dirty) { dirty = false; renderAll(); }
  requestAnimationFrame(loop);
}
window.addEventListener('scroll', () => { dirty = true; }, { passive: true });
window.addEventListener('resize', () => { dirty = true; });
new ResizeObserver(() => { dirty = true; }).observe(document.body);
requestAnimationFrame(loop);

// ---------------------------------------------------------------------------------------------
// Shapes: geometry cache by id, the cards.

const geometryCache = new Map();

async function loadStoredGeometry(rec) {
  const align = $('align').checked;
  const key = `${rec.id}:${align}`;
  if (!geometryCache.has(key)) {
    const p = (async () => {
      // The mesh as the server read it, as binary PLY: every format the server stores is drawn.
      // (The answer has an ETag: asked again, e.g. for the other alignment, the browser's cache
      // revalidates it and the server converts nothing.) A busy server is asked again after
      // its Retry-After, twice.
      const path = `/v1/shapes/${encodeURIComponent(rec.id)}/mesh?format=ply`;
      for (let attempt = 0; ; attempt++) {
        try {
          const resp = await api('GET', path);
          const bytes = new Uint8Array(await resp.arrayBuffer());
          return await readGeometry(bytes, 'ply', align, true);
        } catch (e) {
          if (attempt >= 2 || !(e.problem && e.problem.status === 503)) throw e;
          await new Promise((r) => setTimeout(r, 1000 * Math.min(10, e.retryAfter || 1)));
        }
      }
    })();
    geometryCache.set(key, p);
    // A failed load (a 503, a network blip) is tried again next time, not kept.
    p.catch(() => { if (geometryCache.get(key) === p) geometryCache.delete(key); });
  }
  return (await geometryCache.get(key)).clone();
}

function note(el, text) {
  const d = document.createElement('div');
  d.className = 'note';
  d.textContent = text;
  el.replaceChildren(d);
}

function tagsEl(tags) {
  const span = document.createElement('span');
  for (const t of tags || []) {
    const s = document.createElement('span');
    s.className = 'tag';
    s.textContent = t;
    span.append(s);
  }
  return span;
}

function fmtScore(s) {
  if (s === null || s === undefined) return '∞';
  return Math.abs(s) >= 1000 || (Math.abs(s) < 0.01 && s !== 0) ? s.toExponential(2) : s.toFixed(4);
}

const QUERY_COLOR = 0x4f7fd9;
const HIT_COLOR = 0xd98f4f;

// The current query: { name, tags, id (stored or null), geometry promise, bytes/format for uploads }.
let current = null;
// Each search's number: an answer (or a step of its drawing) whose search is no longer the
// latest is dropped, so an upload still being analysed cannot draw over a later search.
let searchSeq = 0;
const stale = (seq) => seq !== searchSeq;

function makeCard(kind, caption) {
  const fig = document.createElement('figure');
  fig.className = `card ${kind}`;
  const view = document.createElement('div');
  view.className = 'view';
  const cap = document.createElement('figcaption');
  cap.append(...caption);
  fig.append(view, cap);
  return { fig, view };
}

async function fillView(view, geometryPromise, color) {
  note(view, 'loading…');
  try {
    const g = await geometryPromise;
    view.replaceChildren();
    attachView(view, g, color);
    view.dataset.rendered = '1';
  } catch (e) {
    note(view, `cannot display: ${e.message || e}`);
    view.dataset.rendered = 'error';
  }
}

function recordById(id) {
  return getJson(`/v1/shapes/${encodeURIComponent(id)}`);
}

async function renderResults(result, seq) {
  const q = current;
  const records = await Promise.all(result.hits.map((h) => recordById(h.id).catch(() => null)));
  if (stale(seq)) return;
  // The cards are built first and put in place at once: a later search's drawing cannot mix.
  for (const el of [...views.keys()]) if ($('grid').contains(el)) detachView(el);
  const grid = $('grid');
  grid.replaceChildren();
  const qcap = [];
  const b = document.createElement('b'); b.textContent = 'query: ';
  const nm = document.createElement('span'); nm.textContent = q.name;
  qcap.push(b, nm, ' ', tagsEl(q.tags));
  const qc = makeCard('query', qcap);
  qc.fig.dataset.testid = 'query-card';
  grid.append(qc.fig);
  fillView(qc.view, q.geometry(), QUERY_COLOR);
  result.hits.forEach((hit, i) => {
    const rec = records[i] || { id: hit.id, name: hit.name, tags: [] };
    const rank = document.createElement('span'); rank.className = 'rank'; rank.textContent = `#${hit.rank}`;
    const name = document.createElement('span'); name.textContent = hit.name;
    const score = document.createElement('span'); score.className = 'score'; score.title = 'dissimilarity (lower is closer)';
    score.textContent = fmtScore(hit.score);
    const c = makeCard('hit', [rank, name, score, document.createElement('br'), tagsEl(rec.tags)]);
    c.fig.dataset.testid = 'hit-card';
    c.fig.dataset.rank = hit.rank;
    c.fig.title = 'open next to the query';
    // Reachable from the keyboard: Tab to a hit, Enter or Space opens it.
    c.fig.tabIndex = 0;
    c.fig.setAttribute('role', 'button');
    c.fig.setAttribute('aria-label', `hit ${hit.rank}: ${hit.name}, open next to the query`);
    c.fig.addEventListener('keydown', (ev) => {
      if (ev.key === 'Enter' || ev.key === ' ') { ev.preventDefault(); openCompare(hit, rec, q); }
    });
    if (q.tags && q.tags.length && rec.tags && rec.tags.some((t) => q.tags.includes(t))) c.fig.classList.add('same-class');
    grid.append(c.fig);
    fillView(c.view, loadStoredGeometry(rec), HIT_COLOR);
    c.fig.addEventListener('click', (ev) => { if (ev.detail <= 1) openCompare(hit, rec, q); });
  });
  const t = result.timings || {};
  setStatus(`${result.hits.length} hits of ${result.candidates} candidates · stages: ${(result.stages || []).join(' → ') || 'scan'}` +
    ` · ${fmtMs(t.total_ms)} ranking${t.analysis && t.analysis.total_ms ? `, ${fmtMs(t.analysis.total_ms)} analysing the upload` : ''}` +
    ' · click a hit to open it next to the query; drag any view to orbit, Ctrl+wheel to zoom (one camera for all)');
}

const fmtMs = (ms) => (ms === undefined ? '?' : `${ms.toFixed(ms < 10 ? 1 : 0)} ms`);

// ---------------------------------------------------------------------------------------------
// Search.

// The most hits drawn (each is a download and a 3D view); the form says so too.
const MAX_HITS = 24;

function searchOptions() {
  const opts = { top_k: Math.max(1, Math.min(MAX_HITS, parseInt($('topk').value, 10) || 8)) };
  const tag = $('search-tag').value.trim();
  if (tag) opts.tags = [tag];
  const mode = document.querySelector('input[name=rerank-mode]:checked').value;
  if (mode === 'custom') {
    const stages = [];
    const n = (id) => parseInt($(id).value, 10);
    if ($('st-reciprocal').checked) stages.push({ stage: 'reciprocal', shortlist: n('st-reciprocal-n') });
    if ($('st-exact').checked) stages.push({ stage: 'exact', shortlist: n('st-exact-n'), spec: { dissimilarity: $('st-exact-d').value } });
    if ($('st-gw').checked) stages.push({ stage: 'spectral_gw', shortlist: n('st-gw-n') });
    opts.rerank = stages;
  }
  return opts;
}

async function searchStored(rec) {
  const seq = ++searchSeq;
  showError(null);
  hideCompare();
  current = { name: rec.name, tags: rec.tags, id: rec.id, geometry: () => loadStoredGeometry(rec) };
  setStatus(`searching for ${rec.name}…`);
  try {
    const result = await postJson('/v1/search', { id: rec.id, ...searchOptions() });
    if (stale(seq)) return;
    await renderResults(result, seq);
  } catch (e) {
    if (stale(seq)) return;
    showError(e);
    setStatus('search failed');
  }
}

// The server's upload limits (`GET /v1/index`): a file over `max_body_bytes` is refused here.
// Sent, it would be cut off while being sent, which the browser reports as a network error.
let uploadLimits = null;
// What a multipart upload adds to the file: its boundaries, part headers and JSON part.
const ENVELOPE_BYTES = 4096;

async function searchUpload(file) {
  const seq = ++searchSeq;
  showError(null);
  hideCompare();
  setStatus(`analysing ${file.name} (${(file.size / 1024).toFixed(0)} KiB)…`);
  try {
    const max = uploadLimits && uploadLimits.max_body_bytes;
    if (max && file.size + ENVELOPE_BYTES > max) {
      throw new ApiError({
        title: 'too large', code: 'limit.bytes',
        detail: `${file.name} has ${file.size} bytes; the server takes uploads up to ${max} bytes (its max_body_bytes): not sent`,
      });
    }
    const bytes = new Uint8Array(await file.arrayBuffer());
    if (stale(seq)) return;
    const format = formatOf(file.name, bytes);
    const align = $('align').checked;
    let parsed = null;
    const geometry = () => {
      if (!parsed) {
        parsed = readGeometry(bytes, format, align);
        // Read again next time if the reader failed (a stopped worker, say).
        parsed.catch(() => { parsed = null; });
      }
      return parsed.then((g) => g.clone());
    };
    current = { name: file.name, tags: [], id: null, geometry };
    let result;
    if ($('store').checked) {
      const fd = new FormData();
      fd.append('file', new Blob([bytes]), file.name);
      const tags = $('store-tags').value.split(',').map((t) => t.trim()).filter(Boolean);
      fd.append('metadata', new Blob([JSON.stringify({ name: file.name, tags })], { type: 'application/json' }));
      const ing = await (await api('POST', '/v1/shapes', fd)).json();
      // Stored: the list and the count change whatever the search does.
      refreshList();
      refreshIndexInfo();
      if (stale(seq)) return;
      current.id = ing.id;
      current.tags = ing.shape.tags;
      result = await postJson('/v1/search', { id: ing.id, ...searchOptions() });
    } else {
      const fd = new FormData();
      fd.append('file', new Blob([bytes]), file.name);
      fd.append('query', new Blob([JSON.stringify(searchOptions())], { type: 'application/json' }));
      result = await (await api('POST', '/v1/search', fd)).json();
    }
    if (stale(seq)) return;
    await renderResults(result, seq);
  } catch (e) {
    if (stale(seq)) return;
    showError(e);
    setStatus(`${file.name}: not searched`);
  }
}

// ---------------------------------------------------------------------------------------------
// Compare: query and one hit side by side, their distance distributions.

let compareHit = null;

function hideCompare() {
  $('compare').hidden = true;
  detachView($('cmp-query'));
  detachView($('cmp-hit'));
  compareHit = null;
}

// `query` is the query of the grid the hit was drawn in (a search started since may have
// replaced `current`).
async function openCompare(hit, rec, query) {
  compareHit = { hit, rec, query };
  $('compare').hidden = false;
  $('compare-title').textContent = `${query.name}  vs  #${hit.rank} ${hit.name}`;
  $('cmp-query-cap').textContent = `query: ${query.name}`;
  $('cmp-hit-cap').textContent = `#${hit.rank} ${hit.name} · score ${fmtScore(hit.score)}`;
  fillView($('cmp-query'), query.geometry(), QUERY_COLOR);
  fillView($('cmp-hit'), loadStoredGeometry(rec), HIT_COLOR);
  $('compare').scrollIntoView({ behavior: 'instant', block: 'start' });
  await drawPlot();
}

const signatureCache = new Map();
async function signature(id) {
  if (!signatureCache.has(id)) {
    const p = getJson(`/v1/shapes/${encodeURIComponent(id)}/signature`);
    signatureCache.set(id, p);
    p.catch(() => signatureCache.delete(id));
  }
  return signatureCache.get(id);
}

function distributionChannels(sig) {
  const out = new Map();
  for (const ch of (sig.signature && sig.signature.channels) || []) {
    if (ch.values && ch.values.distribution) out.set(ch.name, ch.values.distribution);
  }
  return out;
}

async function drawPlot() {
  // The hit and query of this drawing: the panel may be closed, or another hit opened, while
  // the signatures load (the drawing is then dropped).
  const cmp = compareHit;
  if (!cmp) return;
  const cur = cmp.query;
  const plot = $('plot');
  try {
    const [qs, hs] = await Promise.all([
      cur.id ? signature(cur.id) : Promise.resolve(null),
      signature(cmp.hit.id),
    ]);
    if (cmp !== compareHit) return;
    const hch = distributionChannels(hs);
    const qch = qs ? distributionChannels(qs) : new Map();
    const sel = $('channel');
    const names = [...hch.keys()];
    if ([...sel.options].map((o) => o.value).join('\n') !== names.join('\n')) {
      const keep = sel.value;
      sel.replaceChildren(...names.map((n) => { const o = document.createElement('option'); o.value = n; o.textContent = n; return o; }));
      if (names.includes(keep)) sel.value = keep;
    }
    const name = sel.value || names[0];
    if (!name) { plot.innerHTML = '<p class="note">this signature has no distance distributions</p>'; return; }
    const kind = document.querySelector('input[name=plot-kind]:checked').value;
    const series = [];
    if (qch.has(name)) series.push({ label: `query: ${cur.name}`, color: '#2a5fc9', dist: distributionFromSketch(qch.get(name)) });
    series.push({ label: `#${cmp.hit.rank} ${cmp.hit.name}`, color: '#d0701f', dist: distributionFromSketch(hch.get(name)) });
    plot.innerHTML = plotDistributions(series, { kind, channel: name });
    if (!qch.has(name)) {
      const p = document.createElement('p');
      p.className = 'note';
      p.textContent = 'The uploaded query is not stored, so only the hit’s distribution is drawn: tick “also store it” to compare both.';
      plot.append(p);
    }
  } catch (e) {
    if (cmp === compareHit) showError(e);
  }
}

// ---------------------------------------------------------------------------------------------
// Stored shapes: paged list, search, delete.

const cursors = [null]; // cursor of each page visited
let pageIdx = 0;
let nextCursor = null;

// Each listing has a number; an answer to an earlier one is dropped (a slow page 2 must not
// replace page 3, nor a listing before a delete the one after it).
let listSeq = 0;

/** Lists the current page: true when listed, false when the listing failed, null when a later
 * listing overtook it. */
async function refreshList() {
  const seq = ++listSeq;
  const tag = $('tag-filter').value.trim();
  const cursor = cursors[pageIdx];
  const qs = new URLSearchParams({ limit: String(PAGE) });
  if (cursor) qs.set('cursor', cursor);
  if (tag) qs.set('tag', tag);
  try {
    const page = await getJson(`/v1/shapes?${qs}`);
    if (seq !== listSeq) return null;
    nextCursor = page.next_cursor;
    const ul = $('shape-list');
    ul.replaceChildren(...page.items.map(shapeRow));
    if (!page.items.length) {
      const li = document.createElement('li');
      li.textContent = pageIdx === 0 ? 'no stored shapes yet: drop a mesh and tick “also store it”' : 'no more shapes';
      ul.append(li);
    }
    $('page').textContent = `page ${pageIdx + 1}`;
    $('prev').disabled = pageIdx === 0;
    $('next').disabled = !nextCursor;
    return true;
  } catch (e) {
    if (seq !== listSeq) return null;
    // The buttons were disabled while the page was asked for.
    $('prev').disabled = pageIdx === 0;
    $('next').disabled = !nextCursor;
    // A loading server: the index line says so, and lists again once it is ready.
    if (!(e.problem && e.problem.code === 'server.not_ready')) showError(e);
    return false;
  }
}

// Turning the page: the buttons stay disabled until the page has come (a second click on
// "next" before it, a double click, would skip a page with the cursor of the one before).
// A page that could not be listed leaves the page shown as it was.
async function turnPage(delta) {
  if (delta > 0) {
    if (!nextCursor) return;
    cursors[pageIdx + 1] = nextCursor;
  } else if (pageIdx === 0) {
    return;
  }
  const [idx, next] = [pageIdx, nextCursor];
  pageIdx += delta;
  nextCursor = null;
  $('prev').disabled = true;
  $('next').disabled = true;
  if ((await refreshList()) === false) {
    pageIdx = idx;
    nextCursor = next;
    $('prev').disabled = pageIdx === 0;
    $('next').disabled = !nextCursor;
  }
}

function shapeRow(rec) {
  const li = document.createElement('li');
  li.dataset.id = rec.id;
  const name = document.createElement('span');
  name.className = 'name';
  name.textContent = rec.name;
  name.title = `${rec.name} · ${rec.id} · ${rec.format}, ${rec.vertices} vertices, ${rec.faces} faces`;
  const meta = document.createElement('span');
  meta.className = 'meta';
  meta.textContent = `${rec.format} ${rec.vertices}v`;
  const search = document.createElement('button');
  search.textContent = 'search';
  search.dataset.testid = 'search-stored';
  search.addEventListener('click', () => searchStored(rec));
  const del = document.createElement('button');
  del.textContent = 'delete';
  del.className = 'danger';
  del.dataset.testid = 'delete';
  let disarm = null;
  del.addEventListener('click', async (ev) => {
    // The second click of a double click neither arms nor confirms: the confirmation is a click
    // of its own.
    if (ev.detail > 1) return;
    if (del.dataset.armed !== '1') {
      del.dataset.armed = '1';
      del.textContent = 'sure?';
      clearTimeout(disarm);
      disarm = setTimeout(() => { del.dataset.armed = ''; del.textContent = 'delete'; }, 4000);
      return;
    }
    clearTimeout(disarm);
    del.dataset.armed = '';
    del.disabled = true; // one DELETE, however often it is clicked meanwhile
    try {
      await api('DELETE', `/v1/shapes/${encodeURIComponent(rec.id)}`);
      // Gone from the list at once, whatever the listing below does.
      li.remove();
      showError(null);
      setStatus(`deleted ${rec.name}`);
      for (const k of [...geometryCache.keys()]) if (k.startsWith(`${rec.id}:`)) geometryCache.delete(k);
      signatureCache.delete(rec.id);
      await refreshList();
      refreshIndexInfo();
    } catch (e) {
      del.disabled = false;
      del.textContent = 'delete';
      showError(e);
    }
  });
  li.append(name, tagsEl(rec.tags), meta, search, del);
  return li;
}

// While the server loads its index (503 `server.not_ready`) the page says so and asks again
// after the answer's Retry-After, then lists the shapes once it is ready.
let retryTimer = null;

async function refreshIndexInfo() {
  try {
    const info = await getJson('/v1/index');
    uploadLimits = info.limits || null;
    $('index-info').textContent = `${info.shapes} stored shapes · calibration epoch ${info.calibration_epoch} · engine ${info.engine}`;
    if (retryTimer !== null) {
      retryTimer = null;
      showError(null);
      refreshList();
    }
  } catch (e) {
    const p = e.problem || {};
    if (p.status === 503 && p.code === 'server.not_ready') {
      const secs = Math.min(30, Math.max(1, e.retryAfter || 2));
      $('index-info').textContent = `the server is loading its index; asking again in ${secs} s`;
      clearTimeout(retryTimer);
      retryTimer = setTimeout(refreshIndexInfo, secs * 1000);
      return;
    }
    $('index-info').textContent = 'index unavailable';
    showError(e);
  }
}

// ---------------------------------------------------------------------------------------------
// Wiring.

$('file').addEventListener('change', () => {
  const f = $('file').files[0];
  if (f) searchUpload(f);
  $('file').value = '';
});
const drop = $('drop');
drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
drop.addEventListener('dragleave', () => drop.classList.remove('over'));
drop.addEventListener('drop', (e) => {
  e.preventDefault();
  drop.classList.remove('over');
  const f = e.dataTransfer.files[0];
  if (f) searchUpload(f);
});
$('prev').addEventListener('click', () => turnPage(-1));
$('next').addEventListener('click', () => turnPage(1));
let filterTimer;
$('tag-filter').addEventListener('input', () => {
  clearTimeout(filterTimer);
  // The pages of the old filter are gone: no turning until the new first page has come.
  $('prev').disabled = true;
  $('next').disabled = true;
  nextCursor = null;
  filterTimer = setTimeout(() => { cursors.length = 1; pageIdx = 0; refreshList(); }, 250);
});
$('compare-close').addEventListener('click', hideCompare);
$('channel').addEventListener('change', drawPlot);
for (const r of document.querySelectorAll('input[name=plot-kind]')) r.addEventListener('change', drawPlot);
$('align').addEventListener('change', () => {
  if (current && current.id) {
    const rec = { id: current.id, name: current.name, tags: current.tags };
    recordById(current.id).then(searchStored).catch(() => searchStored(rec));
  }
});

refreshIndexInfo();
refreshList();
// For tests and the curious: the renderer and a way to force a frame.
window.shapeseekViewer = { renderer, render: () => renderAll(), views };
