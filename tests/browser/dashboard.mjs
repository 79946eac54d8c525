// Headless Chromium check of the pathfarm dashboard.
//
//   node tests/browser/dashboard.mjs URL JOBID [SCREENSHOT] [SEQUENCE_JOBID]
//
// With $PATHFARM_TOKEN set, the coordinator is expected to require that client token: the page
// must ask for it (a dialog), keep it in localStorage and follow the events with `?token=`.
// Opens URL (the dashboard), waits for job JOBID's row, opens its panel and prints READY; the
// caller then starts a worker. The job must reach `completed` through live updates (the page
// is never reloaded), and its preview image must load. Saves a full-page screenshot. With
// SEQUENCE_JOBID (a 3-frame job rendered after JOBID): its panel shows a frame strip of three
// frames, each written with a thumbnail, and choosing frame 2 shows frame 2's preview.
// Chromium: $PATHFARM_CHROMIUM or /usr/bin/chromium.
import { chromium } from 'playwright-core';

const [url, jobArg, shot = 'target/dashboard.png', seqArg] = process.argv.slice(2);
if (!url || !jobArg) {
  console.error('usage: node dashboard.mjs URL JOBID [SCREENSHOT]');
  process.exit(2);
}
const job = Number(jobArg);
const executablePath = process.env.PATHFARM_CHROMIUM || '/usr/bin/chromium';
const timeout = Number(process.env.PATHFARM_BROWSER_TIMEOUT_MS || 120000);

function fail(msg) {
  console.error('FAIL: ' + msg);
  process.exitCode = 1;
}

const browser = await chromium.launch({ executablePath, args: ['--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage'] });
const errors = [];
try {
  const page = await browser.newPage({ viewport: { width: 1360, height: 1000 }, deviceScaleFactor: 1 });
  page.on('pageerror', (e) => errors.push('page error: ' + e.message));
  // With a token, the first requests are refused (401) until the dialog is answered.
  let expect401 = Boolean(process.env.PATHFARM_TOKEN);
  page.on('console', (m) => {
    if (m.type() !== 'error') return;
    if (expect401 && m.text().includes('status of 401')) return;
    errors.push('console error: ' + m.text());
  });
  page.setDefaultTimeout(timeout);

  await page.goto(url, { waitUntil: 'domcontentloaded' });
  // A marker that survives only if the page is never reloaded.
  await page.evaluate(() => { window.__pathfarmMarker = 'no-reload'; });

  const token = process.env.PATHFARM_TOKEN;
  if (token) {
    await page.locator('#token-dialog[open]').waitFor();
    console.log('token asked');
    await page.fill('#token-input', token);
    await page.click('#token-ok');
  }

  const row = page.locator(`#jobs tbody tr[data-job-id="${job}"]`);
  await row.waitFor();
  expect401 = false;
  const firstState = await row.getAttribute('data-state');
  console.log(`job ${job} listed, state ${firstState}`);
  await page.locator('#conn.live').waitFor();
  await row.click();
  await page.locator('#job-panel:not([hidden])').waitFor();
  // Raise the queued job's priority from its panel; the panel shows it and the API has it.
  await page.click(`button[data-act="prio-up"][data-id="${job}"]`);
  await page.waitForFunction(() => {
    const p = document.querySelector('#job-actions .prio');
    return p && p.textContent.trim() === 'P1';
  });
  const prio = await page.evaluate(async ([id, t]) => {
    const r = await fetch(`/api/v1/jobs/${id}`, { headers: t ? { Authorization: 'Bearer ' + t } : {} });
    return (await r.json()).priority;
  }, [job, token]);
  if (prio !== 1) fail(`priority after the click is ${prio}, expected 1`);
  console.log('priority raised');
  console.log('READY');

  // Record every state the row shows until it completes.
  const seen = [firstState];
  const t0 = Date.now();
  for (;;) {
    const s = await page.locator(`#jobs tbody tr[data-job-id="${job}"]`).getAttribute('data-state');
    if (s && seen[seen.length - 1] !== s) {
      seen.push(s);
      console.log('state ' + s);
      // A picture of the job mid-render too (best effort).
      if (s === 'running') await page.screenshot({ path: shot.replace(/\.png$/, '-running.png') }).catch(() => {});
      // Only finished jobs can be deleted.
      if (s === 'running' && (await page.locator(`button[data-act="delete"][data-id="${job}"]`).count()) > 0) {
        fail('a running job offers delete');
      }
    }
    if (s === 'completed') break;
    if (s === 'failed' || s === 'cancelled') throw new Error(`job ended ${s}`);
    if (Date.now() - t0 > timeout) throw new Error(`job did not complete in ${timeout} ms (states: ${seen.join(' -> ')})`);
    await page.waitForTimeout(100);
  }
  if (seen[0] === 'completed') fail('the job was already completed when the page opened: live updates were not exercised');

  // The progress column reads 100%, the tile map is all green, the preview loaded.
  await page.waitForFunction((id) => {
    const r = document.querySelector(`#jobs tbody tr[data-job-id="${id}"] .pct`);
    return r && r.textContent.trim() === '100%';
  }, job);
  await page.waitForFunction(() => /^(\d+)\/\1 complete$/.test(document.querySelector('#tiles-cap').textContent));
  await page.waitForFunction(() => {
    const img = document.querySelector('#preview');
    return img && img.complete && img.naturalWidth > 0;
  });
  const size = await page.evaluate(() => [document.querySelector('#preview').naturalWidth, document.querySelector('#preview').naturalHeight]);
  console.log(`preview ${size[0]}x${size[1]}`);
  // The worker shows up in the workers table.
  await page.locator('#workers tbody tr').first().waitFor();
  // The convergence plot has measured at least one pass (the caption line is drawn).
  const conv = await page.evaluate(async ([id, t]) => {
    const r = await fetch(`/api/v1/jobs/${id}/convergence`, { headers: t ? { Authorization: 'Bearer ' + t } : {} });
    return (await r.json()).points.length;
  }, [job, token]);
  console.log(`convergence points ${conv}`);
  if (conv < 1) fail('no convergence points');
  await page.waitForTimeout(600); // let the last detail fetch draw
  if (token && (await page.evaluate(() => localStorage.getItem('pathfarm.token'))) !== token) fail('the token was not kept in localStorage');
  const marker = await page.evaluate(() => window.__pathfarmMarker);
  if (marker !== 'no-reload') fail('the page was reloaded');
  await page.evaluate(() => window.scrollTo(0, 0));
  await page.screenshot({ path: shot, fullPage: true });
  console.log(`screenshot ${shot}`);
  console.log(`states: ${seen.join(' -> ')}`);
  if (seqArg) {
    // The sequence's panel: a strip of three frames that become written, each with a thumbnail.
    const seq = Number(seqArg);
    await page.locator(`#jobs tbody tr[data-job-id="${seq}"]`).click();
    await page.locator('#frame-strip:not([hidden])').waitFor();
    await page.waitForFunction(() => {
      const frames = [...document.querySelectorAll('#frame-strip button.frame')];
      return frames.length === 3 && frames.every((f) => {
        const img = f.querySelector('img');
        return f.dataset.state === 'done' && img && img.complete && img.naturalWidth > 0;
      });
    });
    const labels = await page.evaluate(() => [...document.querySelectorAll('#frame-strip button.frame')].map((f) => f.dataset.frame).join(','));
    if (labels !== '1,2,3') fail(`frame strip shows frames ${labels}, expected 1,2,3`);
    console.log('frame strip: 3 frames written, thumbnails loaded');
    await page.click('#frame-strip button.frame[data-frame="2"]');
    await page.waitForFunction(() => /frame 2 · 48×32/.test(document.querySelector('#preview-cap').textContent));
    if ((await page.locator('#frame-strip button.frame.chosen').getAttribute('data-frame')) !== '2') fail('frame 2 is not marked chosen');
    console.log('frame 2 chosen, its preview shown');
    await page.screenshot({ path: shot.replace(/\.png$/, '-sequence.png'), fullPage: true });
    await page.locator(`#jobs tbody tr[data-job-id="${job}"]`).click();
    await page.locator('#frame-strip').waitFor({ state: 'hidden' });
  }
  // Delete the finished job from the page (confirming the dialog): the row goes, the API 404s.
  page.once('dialog', (d) => d.accept());
  await page.click(`button[data-act="delete"][data-id="${job}"]`);
  await page.locator(`#jobs tbody tr[data-job-id="${job}"]`).waitFor({ state: 'detached' });
  // Asked from node, not the page: a 404 in the page would be logged as a console error.
  const gone = (await fetch(new URL(`/api/v1/jobs/${job}`, url), { headers: token ? { Authorization: 'Bearer ' + token } : {} })).status;
  if (gone !== 404) fail(`deleted job answers ${gone}, expected 404`);
  console.log('deleted');
} catch (e) {
  fail(e.message);
  const page = browser.contexts()[0]?.pages()[0];
  if (page) await page.screenshot({ path: shot, fullPage: true }).catch(() => {});
} finally {
  await browser.close();
}
if (errors.length) fail(errors.join('\n'));
if (!process.exitCode) console.log('PASS');
