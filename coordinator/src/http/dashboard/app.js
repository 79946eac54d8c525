// pathfarm dashboard: reads the REST API, follows /api/v1/events (server-sent events).
// No framework, no build step. Kept in the coordinator binary with include_str!.
'use strict';

const API = '/api/v1';
const $ = (s) => document.querySelector(s);
const st = {
  token: localStorage.getItem('pathfarm.token') || '',
  jobs: new Map(), // id -> {info, at: ms when received}
  workers: [],
  workersAt: Date.now(),
  selected: null,
  es: null,
  tiles: null,
  conv: null,
  lastPasses: -1,
  previewUrl: null,
  previewBusy: false,
  previewAgain: false,
  frames: null, // the selected sequence's frames (first STRIP_MAX)
  layer: 'denoised', // which layer the preview shows of a job with `denoise`: 'denoised' or 'noisy'
  frame: null, // the frame whose preview is shown
  thumbs: new Map(), // 'job/frame' -> blob URL of a written frame's preview
  thumbsBusy: false,
};
// Frames shown in a sequence's strip.
const STRIP_MAX = 240;
const isSequence = (j) => Boolean(j && j.info.frames && j.info.frames.sequence);

// ------------------------------------------------------------------ helpers
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' })[c]);
function authHeaders() { return st.token ? { Authorization: 'Bearer ' + st.token } : {}; }
async function api(path, opts = {}) {
  const r = await fetch(API + path, { ...opts, headers: { ...authHeaders(), ...(opts.headers || {}) } });
  if (r.status === 401) { askToken(); throw new Error('unauthorized'); }
  if (!r.ok) {
    let msg = r.status + ' ' + r.statusText;
    try { msg = (await r.json()).error.message; } catch (_) { /* not JSON */ }
    throw new Error(msg);
  }
  return r;
}
function fmtRate(x) {
  if (!x) return '–';
  if (x >= 1e9) return (x / 1e9).toFixed(2) + ' G';
  if (x >= 1e6) return (x / 1e6).toFixed(2) + ' M';
  if (x >= 1e3) return (x / 1e3).toFixed(1) + ' k';
  return x.toFixed(0);
}
function fmtDur(s) {
  if (s == null || !isFinite(s)) return '–';
  s = Math.max(0, s);
  if (s < 10) return s.toFixed(1) + ' s';
  if (s < 60) return Math.round(s) + ' s';
  const m = Math.floor(s / 60), h = Math.floor(m / 60);
  if (h > 0) return h + ' h ' + (m % 60) + ' m';
  return m + ' m ' + Math.round(s % 60) + ' s';
}
function ago(ms) { return fmtDur((Date.now() - ms) / 1000) + ' ago'; }
// Running jobs' clocks advance between events.
function live(j) {
  const info = j.info;
  const dt = info.state === 'running' ? (Date.now() - j.at) / 1000 : 0;
  const eta = info.eta_secs == null ? null : (info.state === 'running' ? Math.max(0, info.eta_secs - dt) : info.eta_secs);
  return { elapsed: info.elapsed_secs + dt, eta };
}

// ------------------------------------------------------------------ token
function askToken() {
  const d = $('#token-dialog');
  if (d.open) return;
  $('#token-btn').hidden = false;
  $('#token-input').value = st.token;
  d.showModal();
}
$('#token-dialog').addEventListener('close', () => {
  if ($('#token-dialog').returnValue !== 'ok') return;
  st.token = $('#token-input').value.trim();
  localStorage.setItem('pathfarm.token', st.token);
  connect();
});
$('#token-btn').addEventListener('click', askToken);

// ------------------------------------------------------------------ jobs table
// The table row gets the common actions; the job panel (`panel`) adds the priority controls.
function actionButtons(info, panel = false) {
  const b = [];
  const id = info.id;
  if (info.state === 'running' || info.state === 'queued') b.push(`<button data-act="pause" data-id="${id}">pause</button>`);
  if (info.state === 'paused') b.push(`<button data-act="resume" data-id="${id}">resume</button>`);
  const finished = ['completed', 'failed', 'cancelled'].includes(info.state);
  if (!finished) b.push(`<button data-act="cancel" data-id="${id}">cancel</button>`);
  b.push(`<button data-act="exr" data-id="${id}" title="download the multi-layer EXR">EXR</button>`);
  b.push(`<button data-act="png" data-id="${id}" title="download the PNG preview">PNG</button>`);
  if (finished) {
    b.push(`<button data-act="delete" data-id="${id}" title="delete the job and its files">delete</button>`);
  } else if (panel) {
    b.push(`<span class="prio" title="priority: higher runs first">P${info.priority}</span>`);
    b.push(`<button data-act="prio-up" data-id="${id}" title="raise the priority">▲</button>`);
    b.push(`<button data-act="prio-down" data-id="${id}" title="lower the priority">▼</button>`);
  }
  return b.join('');
}

// Cells of a job row, as HTML strings (only changed cells are rewritten, so buttons under
// the pointer survive the updates).
function jobCells(j) {
  const i = j.info, s = i.settings, t = live(j);
  const pct = Math.round(i.progress * 1000) / 10;
  const done = i.state === 'completed';
  return [
    String(i.id),
    esc(i.name),
    `<span class="badge state ${i.state}">${i.state}</span>`,
    esc(s.integrator.type),
    `${s.width} × ${s.height}`,
    `${i.spp_done} / ${s.spp}`,
    `<span class="bar ${done ? 'done' : ''}"><i style="width:${pct}%"></i></span><span class="pct">${pct.toFixed(pct < 100 ? 1 : 0)}%</span>`,
    fmtRate(i.samples_per_sec),
    fmtDur(t.eta),
    fmtDur(t.elapsed),
    actionButtons(i),
  ];
}
const JOB_CELL_CLASS = ['num', '', '', '', '', 'num', '', 'num', 'num eta', 'num elapsed', 'actions'];

function renderJobs() {
  const jobs = [...st.jobs.values()].sort((a, b) => b.info.id - a.info.id);
  $('#jobs-empty').hidden = jobs.length > 0;
  $('#jobs-count').textContent = jobs.length ? jobs.length + (jobs.length === 1 ? ' job' : ' jobs') : '';
  const body = $('#jobs tbody');
  const old = new Map([...body.rows].map((r) => [Number(r.dataset.jobId), r]));
  jobs.forEach((j, k) => {
    const id = j.info.id;
    let row = old.get(id);
    old.delete(id);
    if (!row) {
      row = document.createElement('tr');
      row.dataset.jobId = id;
      row._cells = JOB_CELL_CLASS.map((c) => { const td = row.insertCell(); td.className = c; return null; });
    }
    row.dataset.state = j.info.state;
    row.classList.toggle('selected', st.selected === id);
    jobCells(j).forEach((html, c) => {
      if (row._cells[c] !== html) { row.cells[c].innerHTML = html; row._cells[c] = html; }
    });
    if (body.rows[k] !== row) body.insertBefore(row, body.rows[k] || null);
  });
  for (const r of old.values()) r.remove();
  renderSummary();
}

function renderSummary() {
  const counts = {};
  for (const j of st.jobs.values()) counts[j.info.state] = (counts[j.info.state] || 0) + 1;
  const busy = st.workers.filter((w) => w.state === 'busy').length;
  const up = st.workers.filter((w) => w.state !== 'offline').length;
  const parts = [];
  if (counts.running) parts.push(counts.running + ' running');
  if (counts.queued) parts.push(counts.queued + ' queued');
  parts.push(`${busy}/${up} workers busy`);
  $('#summary').textContent = parts.join(' · ');
}

async function download(id, kind) {
  const file = kind === 'exr' ? 'image.exr' : 'preview.png';
  // A sequence has no single image: the chosen frame's.
  const seq = isSequence(st.jobs.get(id)) && st.selected === id && st.frame != null;
  const r = await api(seq ? `/jobs/${id}/frames/${st.frame}/${file}` : `/jobs/${id}/${file}`);
  const url = URL.createObjectURL(await r.blob());
  const a = document.createElement('a');
  const j = st.jobs.get(id);
  a.href = url;
  a.download = `${(j ? j.info.name : 'job') + '-' + id}.${kind}`;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

document.addEventListener('click', async (e) => {
  const btn = e.target.closest('button[data-act]');
  if (btn) {
    e.stopPropagation();
    const id = Number(btn.dataset.id), act = btn.dataset.act;
    try {
      if (act === 'exr' || act === 'png') await download(id, act);
      else if (act === 'prio-up' || act === 'prio-down') {
        const cur = st.jobs.get(id)?.info.priority ?? 0;
        const priority = cur + (act === 'prio-up' ? 1 : -1);
        const r = await api(`/jobs/${id}/priority`, {
          method: 'PUT', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ priority }),
        });
        upsertJob(await r.json());
      } else if (act === 'delete') {
        if (!confirm(`Delete job ${id} and its images?`)) return;
        await api(`/jobs/${id}`, { method: 'DELETE' });
        st.jobs.delete(id);
        if (st.selected === id) select(null);
        renderJobs();
      } else {
        const r = await api(`/jobs/${id}/${act}`, { method: 'POST' });
        upsertJob(await r.json());
      }
    } catch (err) { alert(`${act} job ${id}: ${err.message}`); }
    return;
  }
  const frame = e.target.closest('#frame-strip button.frame');
  if (frame) {
    st.frame = Number(frame.dataset.frame);
    renderStrip();
    refreshPreview();
    return;
  }
  const row = e.target.closest('#jobs tbody tr');
  if (row) select(Number(row.dataset.jobId));
});
$('#job-close').addEventListener('click', () => select(null));
for (const radio of document.querySelectorAll('#layer-toggle input')) {
  radio.addEventListener('change', () => { st.layer = radio.value; refreshPreview(); });
}

function upsertJob(info) {
  st.jobs.set(info.id, { info, at: Date.now() });
  renderJobs();
  if (st.selected === info.id) renderPanel(true);
}

// ------------------------------------------------------------------ job panel
function select(id) {
  st.selected = id;
  st.tiles = null; st.conv = null; st.lastPasses = -1;
  st.frames = null; st.frame = null;
  $('#frame-strip').hidden = true;
  history.replaceState(null, '', id == null ? location.pathname : '#job=' + id);
  $('#preview').removeAttribute('src');
  $('#job-log').textContent = '…';
  $('#preview-cap').textContent = 'preview';
  const job = st.jobs.get(id);
  $('#layer-toggle').hidden = !(job && job.info.settings.denoise);
  renderJobs();
  renderPanel(false);
  drawConvergence();
  if (id != null) { fetchDetailsNow(); refreshPreview(); $('#job-panel').scrollIntoView({ behavior: 'smooth', block: 'nearest' }); }
}

let panelTimer = null;
function renderPanel(fetchDetails) {
  const panel = $('#job-panel');
  const j = st.jobs.get(st.selected);
  if (!j) { panel.hidden = true; return; }
  panel.hidden = false;
  const i = j.info, s = i.settings;
  $('#job-title').textContent = `#${i.id} ${i.name}`;
  $('#job-state').className = 'badge ' + i.state;
  $('#job-state').textContent = i.state;
  $('#job-meta').textContent = `${s.width}×${s.height} · ${s.integrator.type} · ${i.spp_done}/${s.spp} spp · pass ${i.passes_done}/${i.passes_total} · ${i.units_merged}/${i.units_total} units${isSequence(j) ? ` · frames ${i.frames.spec}: ${i.frames.done}/${i.frames.total} written` : ''}`;
  const acts = actionButtons(i, true);
  if ($('#job-actions').dataset.html !== acts) { $('#job-actions').innerHTML = acts; $('#job-actions').dataset.html = acts; }
  $('#job-error').hidden = !i.error;
  $('#job-error').textContent = i.error || '';
  // A job waiting for workers with its required tags says so.
  $('#job-waiting').hidden = !i.waiting;
  $('#job-waiting').textContent = i.waiting ? `waiting: ${i.waiting}` : '';
  const req = (i.requires || []).length ? { requires: i.requires } : {};
  $('#job-settings').textContent = JSON.stringify({ scene_id: i.scene_id, priority: i.priority, ...req, ...s }, null, 2);
  drawTiles();
  if (fetchDetails && !panelTimer) {
    // At most ~4 detail fetches a second, whatever the event rate.
    panelTimer = setTimeout(() => { panelTimer = null; fetchDetailsNow(); }, 250);
  }
}

async function fetchDetailsNow() {
  const id = st.selected;
  if (id == null) return;
  try {
    const [tiles, log] = await Promise.all([
      api(`/jobs/${id}/tiles`).then((r) => r.json()),
      api(`/jobs/${id}/log`).then((r) => r.json()),
    ]);
    if (st.selected !== id) return;
    st.tiles = tiles;
    drawTiles();
    const pre = $('#job-log');
    const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
    pre.textContent = log.length ? log.join('\n') : '(no log lines yet)';
    if (atEnd) pre.scrollTop = pre.scrollHeight;
    const j = st.jobs.get(id);
    if (isSequence(j)) await fetchFrames(id);
    if (j && j.info.passes_done !== st.lastPasses) {
      st.lastPasses = j.info.passes_done;
      st.conv = await api(`/jobs/${id}/convergence`).then((r) => r.json());
      drawConvergence();
    }
  } catch (err) { console.warn('job details', err); }
}

// ------------------------------------------------------------------ frame strip (sequences)
async function fetchFrames(id) {
  const frames = await api(`/jobs/${id}/frames?limit=${STRIP_MAX}`).then((r) => r.json());
  if (st.selected !== id) return;
  const before = st.frames && st.frames.find((f) => f.frame === st.frame);
  st.frames = frames;
  if (st.frame == null || !frames.some((f) => f.frame === st.frame)) {
    // The first frame in progress, else the last one written.
    const cur = frames.find((f) => f.state === 'rendering' || f.state === 'writing');
    const done = frames.filter((f) => f.state === 'done');
    st.frame = (cur || done[done.length - 1] || frames[0] || { frame: null }).frame;
  }
  const now = frames.find((f) => f.frame === st.frame);
  renderStrip();
  if (now && (!before || before.passes_done !== now.passes_done || before.state !== now.state)) refreshPreview();
  loadThumbs(id);
}

function renderStrip() {
  const strip = $('#frame-strip');
  const j = st.jobs.get(st.selected);
  if (!isSequence(j) || !st.frames) { strip.hidden = true; return; }
  strip.hidden = false;
  const total = j.info.frames.total, passes = Math.max(1, j.info.passes_total);
  const html = st.frames.map((f) => {
    const thumb = st.thumbs.get(`${st.selected}/${f.frame}`);
    const pct = Math.round((100 * f.passes_done) / passes);
    const chosen = f.frame === st.frame ? ' chosen' : '';
    const face = thumb ? `<img src="${thumb}" alt="frame ${f.frame}">` : `<span class="ph">${f.state === 'pending' ? '' : pct + '%'}</span>`;
    return `<button type="button" class="frame ${f.state}${chosen}" data-frame="${f.frame}" data-state="${f.state}" title="frame ${f.frame}: ${f.state}, ${f.passes_done}/${passes} passes">${face}<span class="fn">${f.frame}</span></button>`;
  }).join('') + (total > st.frames.length ? `<span class="muted">first ${st.frames.length} of ${total} frames</span>` : '');
  if (strip.dataset.html !== html) { strip.innerHTML = html; strip.dataset.html = html; }
}

// Thumbnails of written frames, one request at a time (a written frame never changes).
async function loadThumbs(id) {
  if (st.thumbsBusy) return;
  st.thumbsBusy = true;
  try {
    for (;;) {
      if (st.selected !== id || !st.frames) break;
      const f = st.frames.find((x) => x.state === 'done' && !st.thumbs.has(`${id}/${x.frame}`));
      if (!f) break;
      const r = await api(`/jobs/${id}/frames/${f.frame}/preview.png`);
      st.thumbs.set(`${id}/${f.frame}`, URL.createObjectURL(await r.blob()));
      renderStrip();
    }
  } catch (err) { console.warn('thumbnails', err); }
  st.thumbsBusy = false;
}

async function refreshPreview() {
  const id = st.selected;
  if (id == null) return;
  const job = st.jobs.get(id);
  // A queued job has no image yet (its film exists from its first lease on): nothing to ask for.
  if (job && job.info.state === 'queued') return;
  const seq = isSequence(job);
  const frame = st.frame;
  if (seq && (frame == null || (st.frames || []).some((f) => f.frame === frame && f.state === 'pending'))) return;
  if (st.previewBusy) { st.previewAgain = true; return; }
  st.previewBusy = true;
  try {
    // Without `?layer` the preview shows the denoised layer when there is one, else the noisy.
    const layer = st.layer === 'noisy' ? '?layer=noisy' : '';
    const path = (seq ? `/jobs/${id}/frames/${frame}/preview.png` : `/jobs/${id}/preview.png`) + layer;
    const r = await api(path, { cache: 'no-store' });
    const shown = r.headers.get('x-pathfarm-preview-layer');
    const url = URL.createObjectURL(await r.blob());
    if (st.selected === id) {
      const img = $('#preview');
      img.onload = () => {
        const which = seq ? `frame ${frame} · ` : '';
        const layer = shown ? ` · ${shown}` : '';
        $('#preview-cap').textContent = `preview · ${which}${img.naturalWidth}×${img.naturalHeight}${layer} · updated ${new Date().toLocaleTimeString()}`;
      };
      img.src = url;
      if (st.previewUrl) URL.revokeObjectURL(st.previewUrl);
      st.previewUrl = url;
    } else URL.revokeObjectURL(url);
  } catch (err) { console.warn('preview', err); }
  st.previewBusy = false;
  if (st.previewAgain) { st.previewAgain = false; refreshPreview(); }
}

function drawTiles() {
  const c = $('#tiles');
  const j = st.jobs.get(st.selected);
  const t = st.tiles;
  const ctx = c.getContext('2d');
  if (!j) return;
  const W = j.info.settings.width, H = j.info.settings.height;
  // Fit the image aspect into a 360-wide canvas.
  const cw = 360, ch = Math.max(60, Math.min(300, Math.round(cw * H / W)));
  if (c.height !== ch) c.height = ch;
  const s = Math.min(cw / W, ch / H), ox = (cw - W * s) / 2, oy = (ch - H * s) / 2;
  ctx.clearRect(0, 0, cw, ch);
  ctx.fillStyle = '#fafbfc'; ctx.fillRect(0, 0, cw, ch);
  if (!t) return;
  const leased = new Set(st.workers.filter((w) => w.current && w.current[0] === j.info.id).map((w) => w.current[1].tile));
  let full = 0;
  t.tiles.forEach((r, k) => {
    const f = t.passes_total ? t.passes_merged[k] / t.passes_total : 0;
    if (f >= 1) full++;
    const x = ox + r.x0 * s, y = oy + r.y0 * s, w = (r.x1 - r.x0) * s, h = (r.y1 - r.y0) * s;
    ctx.fillStyle = f >= 1 ? '#2f9e6a' : f <= 0 ? '#2a3040' : `hsl(32, 80%, ${62 - 22 * f}%)`;
    ctx.fillRect(x + 0.5, y + 0.5, w - 1, h - 1);
    if (w > 26 && h > 14) {
      ctx.fillStyle = f >= 1 || f <= 0 ? 'rgba(255,255,255,.85)' : '#3a2206';
      ctx.font = '10px system-ui, sans-serif';
      ctx.fillText(`${t.passes_merged[k]}/${t.passes_total}`, x + 4, y + 12);
    }
    if (leased.has(k)) {
      ctx.strokeStyle = '#3b7bd6'; ctx.lineWidth = 2;
      ctx.strokeRect(x + 1.5, y + 1.5, w - 3, h - 3);
    }
  });
  $('#tiles-cap').textContent = `${full}/${t.tiles.length} complete`;
}

function drawConvergence() {
  const c = $('#conv');
  const ctx = c.getContext('2d');
  const W = c.width, H = c.height;
  ctx.clearRect(0, 0, W, H);
  ctx.fillStyle = '#fafbfc'; ctx.fillRect(0, 0, W, H);
  const pts = ((st.conv && st.conv.points) || []).filter((p) => p.rmse > 0 && p.mean_spp > 0);
  ctx.font = '11px system-ui, sans-serif';
  if (pts.length === 0) {
    ctx.fillStyle = '#6b7385';
    ctx.fillText('waiting for the first completed pass…', 16, H / 2);
    return;
  }
  const L = 48, R = 12, T = 12, B = 30;
  const xs = pts.map((p) => Math.log10(p.mean_spp)), ys = pts.map((p) => Math.log10(p.rmse));
  let x0 = Math.floor(Math.min(...xs)), x1 = Math.ceil(Math.max(...xs));
  if (x1 <= x0) x1 = x0 + 1;
  const yr = [Math.min(...ys), Math.max(...ys)];
  let y0 = Math.floor(yr[0] - 0.05), y1 = Math.ceil(yr[1] + 0.05);
  if (y1 <= y0) y1 = y0 + 1;
  const px = (v) => L + (v - x0) / (x1 - x0) * (W - L - R);
  const py = (v) => T + (y1 - v) / (y1 - y0) * (H - T - B);
  // Grid and axes (decades).
  ctx.strokeStyle = '#e4e7ee'; ctx.fillStyle = '#6b7385'; ctx.lineWidth = 1;
  for (let d = x0; d <= x1; d++) {
    ctx.beginPath(); ctx.moveTo(px(d), T); ctx.lineTo(px(d), H - B); ctx.stroke();
    ctx.textAlign = d === x1 ? 'right' : d === x0 ? 'left' : 'center';
    ctx.fillText(String(10 ** d), px(d), H - B + 14);
    ctx.textAlign = 'left';
  }
  for (let d = y0; d <= y1; d++) {
    ctx.beginPath(); ctx.moveTo(L, py(d)); ctx.lineTo(W - R, py(d)); ctx.stroke();
    ctx.fillText('1e' + d, 8, py(d) + 4);
  }
  ctx.fillText('samples per pixel', W / 2 - 40, H - 4);
  // Reference: 1/sqrt(n) through the first point.
  ctx.setLineDash([4, 4]); ctx.strokeStyle = '#9aa3b5';
  ctx.beginPath();
  ctx.moveTo(px(xs[0]), py(ys[0]));
  ctx.lineTo(px(x1), py(ys[0] - 0.5 * (x1 - xs[0])));
  ctx.stroke();
  ctx.setLineDash([]);
  ctx.fillText('1/√n', px(x1) - 30, Math.max(T + 10, py(ys[0] - 0.5 * (x1 - xs[0])) - 6));
  // Measured.
  ctx.strokeStyle = '#e8912e'; ctx.fillStyle = '#e8912e'; ctx.lineWidth = 2;
  ctx.beginPath();
  pts.forEach((p, k) => { const X = px(xs[k]), Y = py(ys[k]); if (k) ctx.lineTo(X, Y); else ctx.moveTo(X, Y); });
  ctx.stroke();
  pts.forEach((p, k) => { ctx.beginPath(); ctx.arc(px(xs[k]), py(ys[k]), 3, 0, 7); ctx.fill(); });
  const last = pts[pts.length - 1];
  ctx.fillStyle = '#1d2330';
  ctx.fillText(`rmse ${last.rmse.toExponential(2)} · relative ${(last.relative * 100).toFixed(2)}%`, L + 6, T + 10);
}

// ------------------------------------------------------------------ workers
function renderWorkers() {
  const ws = [...st.workers].sort((a, b) => a.id - b.id);
  $('#workers-empty').hidden = ws.length > 0;
  const up = ws.filter((w) => w.state !== 'offline').length;
  $('#workers-count').textContent = ws.length ? `${up} online, ${ws.length} registered` : '';
  const blocked = (wid) => [...st.jobs.values()].filter((j) => (j.info.blocklist || []).includes(wid)).map((j) => '#' + j.info.id);
  $('#workers tbody').innerHTML = ws.map((w) => {
    const cur = w.current ? `job ${w.current[0]} · pass ${w.current[1].pass} · tile ${w.current[1].tile}` : '–';
    const bl = blocked(w.id);
    return `<tr data-worker-id="${w.id}">
      <td class="num">${w.id}</td><td>${esc(w.name)}</td><td class="num">${w.threads}</td>
      <td>${(w.tags || []).length ? esc(w.tags.join(' ')) : '–'}</td>
      <td><span class="badge ${w.state}">${w.state}</span></td>
      <td>${cur}</td><td class="num">${w.units_done}</td><td class="num">${fmtRate(w.samples_per_sec)}</td>
      <td>${w.last_seen_ms ? ago(w.last_seen_ms) : '–'}</td>
      <td>${bl.length ? `<span class="badge failed">${bl.join(' ')}</span>` : '–'}</td>
    </tr>`;
  }).join('');
  renderSummary();
}

// ------------------------------------------------------------------ live updates
// The list routes are paged (ids ascending, at most 1000 per page): ask until a short page.
async function fetchList(path) {
  const out = [];
  for (;;) {
    const after = out.length ? `&after=${out[out.length - 1].id}` : '';
    const page = await api(`${path}?limit=1000${after}`).then((r) => r.json());
    out.push(...page);
    if (page.length < 1000) return out;
  }
}

async function fetchAll() {
  const [jobs, workers] = await Promise.all([fetchList('/jobs'), fetchList('/workers')]);
  applySnapshot({ jobs, workers });
}

function applySnapshot(s) {
  st.jobs = new Map(s.jobs.map((info) => [info.id, { info, at: Date.now() }]));
  st.workers = s.workers;
  renderJobs();
  renderWorkers();
  const m = /job=(\d+)/.exec(location.hash);
  if (st.selected == null && m && st.jobs.has(Number(m[1]))) select(Number(m[1]));
  else if (st.selected != null) { renderPanel(true); refreshPreview(); }
}

function setConn(cls, text) { const c = $('#conn'); c.className = 'conn ' + cls; c.textContent = text; }

function connect() {
  if (st.es) st.es.close();
  const url = API + '/events' + (st.token ? '?token=' + encodeURIComponent(st.token) : '');
  const es = new EventSource(url);
  st.es = es;
  const on = (name, f) => es.addEventListener(name, (e) => { try { f(JSON.parse(e.data)); } catch (err) { console.warn(name, err); } });
  es.onopen = () => setConn('live', 'live');
  es.onerror = () => {
    setConn('down', 'reconnecting');
    // A refused token closes the stream for good: find out why.
    if (es.readyState === EventSource.CLOSED) {
      fetchAll()
        .then(() => setTimeout(connect, 2000))
        .catch((err) => { if (err.message !== 'unauthorized') setTimeout(connect, 5000); });
    }
  };
  on('snapshot', applySnapshot);
  on('job', upsertJob);
  on('job_deleted', (d) => { st.jobs.delete(d.id); if (st.selected === d.id) select(null); renderJobs(); });
  on('workers', (ws) => { st.workers = ws; st.workersAt = Date.now(); renderWorkers(); if (st.selected != null) drawTiles(); });
  on('image', (d) => { if (d.id === st.selected) { refreshPreview(); renderPanel(true); } });
  on('frame', (d) => { if (d.id === st.selected) fetchFrames(d.id).catch(() => {}); });
  on('resync', () => fetchAll().catch(() => {}));
}

// Clocks of running jobs, "last seen" of workers.
function tick() {
  for (const row of document.querySelectorAll('#jobs tbody tr')) {
    const j = st.jobs.get(Number(row.dataset.jobId));
    if (!j || j.info.state !== 'running') continue;
    const t = live(j);
    for (const [c, v] of [[8, fmtDur(t.eta)], [9, fmtDur(t.elapsed)]]) {
      if (row._cells[c] !== v) { row.cells[c].textContent = v; row._cells[c] = v; }
    }
  }
  if (st.workers.length) renderWorkers();
}
setInterval(tick, 1000);
window.addEventListener('resize', drawConvergence);
drawConvergence();
connect();
