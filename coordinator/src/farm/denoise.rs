//! Denoise steps: a job with `denoise` gets each frame denoised (OIDN, on a worker that
//! registered the tag `denoise`) once its last pass merged, and, with `denoise_preview`, after
//! every completed pass too.
//!
//! A step is a lease like a unit's ([`Lease::denoise`] set): it expires, is renewed by
//! heartbeats and is released like one, and is handed out through the same long poll, before
//! render units, only to workers with the tag. The worker fetches the frame's resolved colour,
//! albedo and normal (`GET /leases/{id}/denoise-input`) and uploads the denoised colour
//! (`PUT /leases/{id}/denoised`); the farm keeps per frame the layer of the latest pass only,
//! so a late upload of an earlier pass never replaces a newer one.
//!
//! The final step holds its frame back (a single-frame job stays running, a sequence's frame is
//! not written) until the layer is stored, never longer: when no live worker can denoise, when
//! none took the step within [`super::FarmConfig::denoise_grace_ms`], or when it failed
//! `max_unit_failures` times, the frame goes on without the layer and the job's log says why.
//! Previews never hold anything back: one nobody takes is dropped. After a coordinator restart
//! the workers register again: for `denoise_grace_ms` after the restore, a step waits for a
//! denoise worker to come back instead of being given up at once (a frame whose film is read
//! back complete gets its final step then, as after any merge).
//!
//! Denoised layers live in memory until written: a frame whose final layer was stored but not
//! written before a restart goes on without it.

use super::lease::Lease;
use super::{Farm, FarmError, Job};
use pathfarm_common::job::{TileRect, UnitKey};
use pathfarm_common::protocol::{JobId, JobState, LeaseGrant, LeaseId, LeaseKind, WorkerId};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// The tag a worker registers when it can denoise.
pub const DENOISE_TAG: &str = "denoise";

/// A denoise step of a frame: of its film after `passes` merged passes; `last`: the final one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Step {
    pub(super) passes: u32,
    pub(super) last: bool,
}

/// A step waiting for a worker, since `since_ms`.
#[derive(Clone, Copy, Debug)]
struct Waiting {
    step: Step,
    since_ms: u64,
}

/// A denoised layer the farm holds: of the frame's film after `passes` passes.
#[derive(Clone, Debug)]
pub struct DenoisedLayer {
    pub passes: u32,
    pub rgb: Arc<Vec<[f32; 3]>>,
}

/// A job's denoise steps and layers, by frame index.
#[derive(Debug, Default)]
pub(super) struct JobDenoise {
    /// Per frame: the newest step waiting for a worker.
    waiting: BTreeMap<usize, Waiting>,
    /// Frames whose final step is owed (waiting or leased): they are held back.
    owed: BTreeSet<usize>,
    /// Per frame: failed attempts of its final step.
    failures: BTreeMap<usize, u32>,
    /// Per frame: the newest denoised layer.
    layers: BTreeMap<usize, DenoisedLayer>,
    /// Previews were skipped for want of a worker (logged once).
    previews_skipped: bool,
}

/// What storing a denoised layer did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DenoiseOutcome {
    pub job_id: JobId,
    /// The frame (number) the layer is of.
    pub frame: i32,
    /// The layer was its frame's final one.
    pub last: bool,
    pub job_completed: bool,
}

impl Step {
    /// Newer steps first: a final step over any preview, then more passes.
    fn rank(self) -> (bool, u32) {
        (self.last, self.passes)
    }
}

impl Job {
    /// The newest denoised layer of frame `index`, if one is stored.
    pub fn denoised(&self, index: usize) -> Option<DenoisedLayer> {
        self.denoise.layers.get(&index).cloned()
    }

    /// Frame `index` waits for its final denoise step (a sequence's frame is not written yet).
    pub fn denoise_owed(&self, index: usize) -> bool {
        self.denoise.owed.contains(&index)
    }

    /// Forgets frame `index`'s layer (a sequence's frame written with it).
    pub fn drop_denoised(&mut self, index: usize) {
        self.denoise.layers.remove(&index);
    }

    /// Queues `step` for frame `index` unless a newer one waits.
    fn queue_denoise(&mut self, index: usize, step: Step, now_ms: u64) {
        if step.last {
            self.denoise.owed.insert(index);
        }
        let newer = self.denoise.waiting.get(&index).is_some_and(|w| w.step.rank() >= step.rank());
        if !newer {
            self.denoise.waiting.insert(index, Waiting { step, since_ms: now_ms });
        }
    }

    /// A unit lease or a denoise lease comes back unfinished: its unit or step waits again.
    pub(super) fn give_back(&mut self, l: &Lease, now_ms: u64) {
        match l.denoise {
            Some(step) => {
                let stale = self.denoise.layers.get(&l.frame).is_some_and(|h| h.passes >= step.passes);
                if stale || (step.last && !self.denoise.owed.contains(&l.frame)) {
                    return; // a newer layer is stored, or the step was given up meanwhile
                }
                self.queue_denoise(l.frame, step, now_ms);
            }
            None => self.requeue(l.frame, l.unit),
        }
    }

    /// The frame goes on without its final layer: logged with `why`.
    fn give_up_denoise(&mut self, index: usize, why: &str) {
        self.denoise.waiting.remove(&index);
        if self.denoise.owed.remove(&index) {
            let frame = self.frames.frames()[index];
            let what = if self.sequence { format!("frame {frame}") } else { "the image".to_string() };
            self.log(format!("denoise: {what} is finished without the denoised layer: {why}"));
            self.output_dirty = true;
        }
    }

    /// After a restore: denoised layers live in memory until written, so frames merged before
    /// the restart and not written yet go on without theirs (a job that was not finished says so
    /// in its log).
    pub(super) fn note_restored_denoise(&mut self, recorded: JobState) {
        // A sequence's merged frames not written yet; a single frame merged (it counts as done).
        let unwritten = if self.sequence { self.frames_done } else { 0 };
        if self.settings.denoise && !recorded.is_finished() && self.frames_merged > unwritten {
            self.log(
                "denoise: frames merged before the coordinator restarted are finished without the denoised layer \
                 (denoised layers are held in memory until written)"
                    .into(),
            );
        }
    }

    /// Every frame is merged and no final step is owed.
    fn done_denoising(&self) -> bool {
        self.frames_merged as usize == self.frames.len() && self.denoise.owed.is_empty()
    }
}

impl Farm {
    /// A live worker that can take job `job`'s denoise steps: tag `denoise`, the job's
    /// `requires`, not blocklisted; or, within `denoise_grace_ms` of a restore (a coordinator
    /// restart: the workers have not registered again yet), one may still come. Then a final
    /// step waits for the grace like any other instead of being given up at once.
    fn denoiser_exists(&self, job: &Job, now_ms: u64) -> bool {
        let registering = self.restored_ms.is_some_and(|t| now_ms.saturating_sub(t) < self.cfg.denoise_grace_ms);
        registering
            || self.workers.iter().any(|(id, w)| {
                !w.offline
                    && w.tags.contains(DENOISE_TAG)
                    && job.requires.iter().all(|t| w.tags.contains(t))
                    && !job.blocklist.contains(id)
            })
    }

    /// After a merge: queues the denoise steps of job `id` for the passes its frame `index`
    /// completed (`last`: the frame is fully merged). Without a live worker that can denoise,
    /// the final step is given up at once and previews are skipped. Returns whether the job
    /// must wait for a final step before it completes.
    pub(super) fn denoise_after_merge(
        &mut self,
        id: JobId,
        index: usize,
        passes: &[u32],
        last: bool,
        now_ms: u64,
    ) -> bool {
        let Some(job) = self.jobs.get(&id) else { return false };
        if !job.settings.denoise {
            return false;
        }
        let capable = self.denoiser_exists(job, now_ms);
        let Some(job) = self.jobs.get_mut(&id) else { return false };
        let total = job.plan.passes.len() as u32;
        // A step may be queued: workers that can denoise are woken.
        self.changes.work_ready = true;
        if last {
            job.queue_denoise(index, Step { passes: total, last: true }, now_ms);
            if !capable {
                job.give_up_denoise(
                    index,
                    "no live worker can denoise (none registered the tag `denoise`: build workers with \
                     `--features pathfarm-worker/denoise`)",
                );
            }
        } else if job.settings.denoise_preview
            && let Some(&p) = passes.iter().max()
        {
            if capable {
                job.queue_denoise(index, Step { passes: p + 1, last: false }, now_ms);
            } else if !std::mem::replace(&mut job.denoise.previews_skipped, true) {
                job.log("denoise: no live worker can denoise: denoised previews are skipped".into());
            }
        }
        !job.denoise.owed.is_empty()
    }

    /// Hands a worker with the tag `denoise` the next denoise step, if any: highest priority
    /// first, final steps before previews, lower frames first.
    pub(super) fn lease_denoise(&mut self, worker: WorkerId, now_ms: u64) -> Option<LeaseGrant> {
        let w = self.workers.get(&worker)?;
        if !w.tags.contains(DENOISE_TAG) {
            return None;
        }
        let tags = &w.tags;
        let job_id = self
            .jobs
            .values()
            .filter(|j| j.accepts_work() && !j.denoise.waiting.is_empty() && !j.blocklist.contains(&worker))
            .filter(|j| j.requires.iter().all(|t| tags.contains(t)))
            .min_by_key(|j| (std::cmp::Reverse(j.priority), j.id))
            .map(|j| j.id)?;
        let lease_id = self.next_lease;
        self.next_lease += 1;
        let job = self.jobs.get_mut(&job_id)?;
        let (&index, _) = job.denoise.waiting.iter().min_by_key(|(i, w)| (!w.step.last, **i))?;
        let step = job.denoise.waiting.remove(&index)?.step;
        job.leased += 1;
        let frame = job.frames.frames()[index];
        let mut settings = job.settings.clone();
        settings.frame = frame;
        let pass = step.passes.saturating_sub(1);
        let grant = LeaseGrant {
            kind: LeaseKind::Denoise,
            lease_id,
            job_id,
            scene_id: job.scene_id.clone(),
            unit: UnitKey { frame, pass, tile: 0 },
            tile: TileRect { x0: 0, y0: 0, x1: settings.width, y1: settings.height },
            pass: job.plan.passes[pass as usize],
            settings,
            mask: None,
        };
        self.leases.insert(
            lease_id,
            Lease {
                job: job_id,
                frame: index,
                unit: 0,
                worker,
                deadline_ms: now_ms + self.cfg.lease_timeout_ms,
                denoise: Some(step),
            },
        );
        if let Some(w) = self.workers.get_mut(&worker) {
            w.leases.insert(lease_id);
        }
        self.changes.progress(job_id);
        self.changes.workers.insert(worker);
        tracing::debug!(
            job = job_id,
            frame,
            passes = step.passes,
            last = step.last,
            lease = lease_id,
            "denoise step leased"
        );
        Some(grant)
    }

    /// The job, frame index and image size of denoise lease `lease_id` (held).
    pub fn denoise_lease(&self, lease_id: LeaseId) -> Result<(JobId, i32, (u32, u32)), FarmError> {
        let l = self.leases.get(&lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
        if l.denoise.is_none() {
            return Err(FarmError::ResultMismatch {
                lease: lease_id,
                reason: "this is a render lease: PUT its result to /leases/{id}/result".into(),
            });
        }
        let job = self.jobs.get(&l.job).ok_or(FarmError::LeaseLost(lease_id))?;
        Ok((l.job, job.frames.frames()[l.frame], (job.settings.width, job.settings.height)))
    }

    /// A denoise step's failure (`failed`) or return: retried up to `max_unit_failures` times,
    /// then its frame goes on without the layer.
    pub(super) fn denoise_released(&mut self, l: Lease, failed: bool, reason: &str, now_ms: u64) {
        let max = self.cfg.max_unit_failures;
        let Some(job) = self.jobs.get_mut(&l.job) else { return };
        let Some(step) = l.denoise else { return };
        // The step waits again (or its frame goes on without it).
        self.changes.work_ready = true;
        self.changes.outputs = true;
        self.changes.progress(l.job);
        if !failed {
            job.give_back(&l, now_ms);
            return;
        }
        let frame = job.frames.frames()[l.frame];
        job.log(format!(
            "worker {} failed the denoise step of frame {frame} (pass {}): {reason}",
            l.worker, step.passes
        ));
        if !step.last {
            return; // a preview: the next pass brings another
        }
        let n = job.denoise.failures.entry(l.frame).or_insert(0);
        *n += 1;
        if *n >= max {
            let why = format!("its denoise step failed {max} times; last error: {reason}");
            job.give_up_denoise(l.frame, &why);
            self.complete_if_denoised(l.job, now_ms);
        } else {
            job.give_back(&l, now_ms);
        }
    }

    /// Stores the denoised layer `rgb` of denoise lease `lease_id` (its size was checked when
    /// decoded). A layer of fewer passes than the one stored is refused (`Stale`); the final
    /// one releases its frame, and the job completes when nothing else is owed.
    pub fn accept_denoised(
        &mut self,
        lease_id: LeaseId,
        rgb: Vec<[f32; 3]>,
        now_ms: u64,
    ) -> Result<DenoiseOutcome, FarmError> {
        let (_, _, (w, h)) = self.denoise_lease(lease_id)?;
        if rgb.len() != w as usize * h as usize {
            return Err(FarmError::ResultMismatch {
                lease: lease_id,
                reason: format!("{} pixels, the frame has {w} x {h}", rgb.len()),
            });
        }
        let l = self.take_lease(lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
        let step = l.denoise.ok_or(FarmError::LeaseLost(lease_id))?;
        if let Some(worker) = self.workers.get_mut(&l.worker) {
            worker.last_seen_ms = now_ms;
        }
        let job = self.jobs.get_mut(&l.job).ok_or(FarmError::LeaseLost(lease_id))?;
        let frame = job.frames.frames()[l.frame];
        if let Some(have) = job.denoise.layers.get(&l.frame)
            && have.passes >= step.passes
        {
            return Err(FarmError::Stale(format!(
                "the denoised layer of frame {frame} after pass {} is stored already; this one is of pass {}",
                have.passes, step.passes
            )));
        }
        job.denoise.layers.insert(l.frame, DenoisedLayer { passes: step.passes, rgb: Arc::new(rgb) });
        job.output_dirty = true;
        self.changes.outputs = true;
        self.changes.progress(l.job);
        let mut out = DenoiseOutcome { job_id: l.job, frame, last: step.last, job_completed: false };
        if step.last && job.denoise.owed.remove(&l.frame) {
            job.denoise.waiting.remove(&l.frame);
            if job.sequence {
                job.log(format!("frame {frame} denoised"));
            } else {
                job.log("denoised".into());
            }
            out.job_completed = self.complete_if_denoised(l.job, now_ms);
        }
        Ok(out)
    }

    /// Completes job `id` if it is running with every frame merged and no final step owed.
    fn complete_if_denoised(&mut self, id: JobId, now_ms: u64) -> bool {
        let Some(job) = self.jobs.get_mut(&id) else { return false };
        if job.state.is_finished() || !job.done_denoising() {
            return false;
        }
        job.log("completed".into());
        self.finish(id, JobState::Completed, None, now_ms);
        true
    }

    /// Gives up the steps nobody can take: with no live worker that can denoise, or waiting
    /// longer than `denoise_grace_ms`, a final step lets its frame go on without the layer and a
    /// preview is dropped. Runs with the lease expiry; returns the jobs it changed.
    pub fn expire_denoise(&mut self, now_ms: u64) -> Vec<JobId> {
        let grace = self.cfg.denoise_grace_ms;
        let ids: Vec<JobId> =
            self.jobs.values().filter(|j| j.accepts_work() && !j.denoise.waiting.is_empty()).map(|j| j.id).collect();
        let mut changed = Vec::new();
        for id in ids {
            let Some(job) = self.jobs.get(&id) else { continue };
            let capable = self.denoiser_exists(job, now_ms);
            let Some(job) = self.jobs.get_mut(&id) else { continue };
            let due: Vec<(usize, Step)> = job
                .denoise
                .waiting
                .iter()
                .filter(|(_, w)| !capable || now_ms.saturating_sub(w.since_ms) > grace)
                .map(|(&i, w)| (i, w.step))
                .collect();
            for (index, step) in &due {
                if step.last {
                    let why = if capable {
                        format!("no worker took its denoise step within {} s", grace / 1000)
                    } else {
                        "no live worker can denoise (the workers with the tag `denoise` are gone)".to_string()
                    };
                    job.give_up_denoise(*index, &why);
                } else {
                    job.denoise.waiting.remove(index);
                }
            }
            if !due.is_empty() {
                self.complete_if_denoised(id, now_ms);
                self.changes.outputs = true;
                self.changes.progress(id);
                changed.push(id);
            }
        }
        changed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::farm::{FarmConfig, JobSpec};
    use pathfarm_common::film::{SampleValue, TileAccum, add_sample};
    use pathfarm_common::frames::FrameSet;
    use pathfarm_common::job::{PassSchedule, RenderSettings};
    use pathfarm_common::protocol::{FrameOrder, UnitResultFrame};

    /// 20 x 12, 8 px tiles (6 tiles), passes [0, 1), [1, 3), [3, 7); `denoise` on.
    fn settings(preview: bool) -> RenderSettings {
        let mut s = RenderSettings::new(20, 12, 7);
        s.tile_size = 8;
        s.passes = PassSchedule::Doubling { first: 1, max: 4 };
        s.denoise = true;
        s.denoise_preview = preview;
        s
    }

    fn result(g: &LeaseGrant) -> UnitResultFrame {
        let mut accum = TileAccum::new(g.tile);
        for y in g.tile.y0..g.tile.y1 {
            for x in g.tile.x0..g.tile.x1 {
                for s in g.pass.samples() {
                    let v = SampleValue { radiance: [x as f32, y as f32, s as f32], ..Default::default() };
                    add_sample(accum.pixel_mut(x - g.tile.x0, y - g.tile.y0), &v);
                }
            }
        }
        UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None }
    }

    fn tagged(farm: &mut Farm, name: &str, tags: &[&str]) -> WorkerId {
        farm.register_tagged(name.into(), 1, String::new(), tags.iter().map(|t| t.to_string()).collect(), 0)
    }

    /// Renders every unit `w` is given (render grants only) at `now`.
    fn render_all(farm: &mut Farm, w: WorkerId, now: u64) {
        while let Some(g) = farm.lease(w, now).expect("lease") {
            assert_eq!(g.kind, LeaseKind::Render, "a worker without the tag got a denoise step");
            farm.accept(g.lease_id, result(&g), now).expect("accept");
        }
    }

    fn layer(farm: &Farm, lease: LeaseId, value: f32) -> Vec<[f32; 3]> {
        let (_, _, (w, h)) = farm.denoise_lease(lease).expect("denoise lease");
        vec![[value; 3]; w as usize * h as usize]
    }

    fn log_has(farm: &Farm, id: JobId, needle: &str) -> bool {
        farm.job(id).expect("job").log.iter().any(|l| l.contains(needle))
    }

    /// The final denoise step goes only to a worker with the tag `denoise`; the job stays
    /// running until its layer is stored, then completes with it. A render result sent on a
    /// denoise lease is refused.
    #[test]
    fn the_final_step_goes_to_a_capable_worker_and_holds_the_job() {
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, settings(false), 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        let denoiser = tagged(&mut farm, "d", &["cpu", DENOISE_TAG]);
        render_all(&mut farm, plain, 0);
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Running, "the job waits for its denoise step");
        assert!(job.denoise_owed(0) && job.denoised(0).is_none());
        assert!(log_has(&farm, id, "waiting for the denoise step"));
        assert_eq!(farm.lease(plain, 1).expect("lease"), None, "only a worker with the tag denoises");
        let g = farm.lease(denoiser, 1).expect("lease").expect("the denoise step");
        assert_eq!(g.kind, LeaseKind::Denoise);
        assert_eq!((g.unit.pass, g.tile), (2, TileRect { x0: 0, y0: 0, x1: 20, y1: 12 }));
        let e = farm.accept(g.lease_id, result(&g), 2).expect_err("a render result on a denoise lease");
        assert!(e.to_string().contains("denoise lease"), "{e}");
        let e = farm.accept_denoised(g.lease_id, vec![[0.0; 3]; 5], 2).expect_err("wrong size");
        assert!(e.to_string().contains("5 pixels"), "{e}");
        let out = farm.accept_denoised(g.lease_id, layer(&farm, g.lease_id, 0.5), 2).expect("stored");
        assert!(out.last && out.job_completed);
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        let d = job.denoised(0).expect("layer");
        assert_eq!((d.passes, d.rgb[0]), (3, [0.5; 3]));
        assert!(!job.denoise_owed(0));
        assert!(farm.leases.is_empty());
    }

    /// Without a live worker that can denoise the job completes at its last merge, without the
    /// layer, and its log says why.
    #[test]
    fn without_a_capable_worker_the_job_finishes_without_the_layer() {
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, settings(true), 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        render_all(&mut farm, plain, 0);
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        assert!(job.denoised(0).is_none() && !job.denoise_owed(0));
        assert!(log_has(&farm, id, "finished without the denoised layer: no live worker can denoise"));
        assert!(log_has(&farm, id, "denoised previews are skipped"));
    }

    /// A capable worker that never takes the step: after the configured grace the job completes
    /// without the layer, with a log line; a step that keeps failing is given up likewise.
    #[test]
    fn an_untaken_or_failing_step_is_given_up_after_the_grace_or_the_retries() {
        let grace = 5_000;
        let mut farm = Farm::new(FarmConfig { denoise_grace_ms: grace, ..FarmConfig::default() });
        let id = farm.submit("x".into(), None, 0, settings(false), 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        tagged(&mut farm, "idle denoiser", &[DENOISE_TAG]);
        render_all(&mut farm, plain, 100);
        assert!(farm.expire_denoise(100 + grace).is_empty(), "within the grace");
        assert_eq!(farm.job(id).expect("job").state, JobState::Running);
        assert_eq!(farm.expire_denoise(101 + grace), vec![id]);
        assert_eq!(farm.job(id).expect("job").state, JobState::Completed);
        assert!(log_has(&farm, id, "finished without the denoised layer: no worker took its denoise step within 5 s"));

        // Failing: retried (the step waits again) until max_unit_failures, then given up.
        let id = farm.submit("x".into(), None, 0, settings(false), 0).expect("submit");
        let d = tagged(&mut farm, "failing denoiser", &[DENOISE_TAG]);
        render_all(&mut farm, plain, 0);
        for attempt in 1..=farm.cfg.max_unit_failures {
            let g = farm.lease(d, 0).expect("lease").expect("the step again");
            assert_eq!(g.kind, LeaseKind::Denoise);
            farm.release(g.lease_id, true, "OIDN: out of memory", 0).expect("release");
            let done = attempt == farm.cfg.max_unit_failures;
            assert_eq!(farm.job(id).expect("job").state == JobState::Completed, done);
        }
        assert!(log_has(&farm, id, "its denoise step failed 3 times; last error: OIDN: out of memory"));
        assert!(farm.job(id).expect("job").denoised(0).is_none());
    }

    /// `denoise_preview`: after each completed pass a capable worker is handed the frame's
    /// denoise step before render units; a late layer of an earlier pass is refused and never
    /// replaces the newer one; an expired step waits again; the final layer completes the job.
    #[test]
    fn previews_follow_the_passes_and_stale_layers_are_refused() {
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, settings(true), 0).expect("submit");
        let d = tagged(&mut farm, "d", &["cpu", DENOISE_TAG]);
        let tiles = farm.job(id).expect("job").plan.tiles.len();
        let render_pass = |farm: &mut Farm| {
            for _ in 0..tiles {
                let g = farm.lease(d, 0).expect("lease").expect("a unit");
                assert_eq!(g.kind, LeaseKind::Render);
                farm.accept(g.lease_id, result(&g), 0).expect("accept");
            }
        };
        render_pass(&mut farm);
        // Pass 0 complete: the preview step comes before pass 1's units.
        let first = farm.lease(d, 0).expect("lease").expect("preview");
        assert_eq!((first.kind, first.unit.pass), (LeaseKind::Denoise, 0));
        render_pass(&mut farm);
        let second = farm.lease(d, 0).expect("lease").expect("preview");
        assert_eq!((second.kind, second.unit.pass), (LeaseKind::Denoise, 1));
        let out = farm.accept_denoised(second.lease_id, layer(&farm, second.lease_id, 2.0), 0).expect("stored");
        assert!(!out.last && !out.job_completed);
        let e = farm.accept_denoised(first.lease_id, layer(&farm, first.lease_id, 1.0), 0).expect_err("stale");
        assert!(matches!(e, FarmError::Stale(_)), "{e}");
        let kept = farm.job(id).expect("job").denoised(0).expect("layer");
        assert_eq!((kept.passes, kept.rgb[0]), (2, [2.0; 3]), "the newer layer stays");
        // The last pass: the final step; its lease expires and the step waits again.
        render_pass(&mut farm);
        assert_eq!(farm.job(id).expect("job").state, JobState::Running);
        let lost = farm.lease(d, 0).expect("lease").expect("final");
        assert_eq!((lost.kind, lost.unit.pass), (LeaseKind::Denoise, 2));
        assert_eq!(farm.expire(farm.cfg.lease_timeout_ms + 1), 1);
        let now = farm.cfg.lease_timeout_ms + 2;
        let last = farm.lease(d, now).expect("lease").expect("final again");
        assert_eq!((last.kind, last.unit.pass), (LeaseKind::Denoise, 2));
        let out = farm.accept_denoised(last.lease_id, layer(&farm, last.lease_id, 3.0), now).expect("stored");
        assert!(out.last && out.job_completed);
        assert_eq!(farm.job(id).expect("job").denoised(0).expect("layer").passes, 3);
    }

    /// A restart while the final step is owed: the layer lived in memory only, so the restored
    /// job completes without it and its log says why.
    #[test]
    fn a_restart_with_a_final_step_owed_says_the_layer_is_lost() {
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, settings(false), 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        tagged(&mut farm, "d", &[DENOISE_TAG]);
        render_all(&mut farm, plain, 0);
        assert_eq!(farm.job(id).expect("job").state, JobState::Running);
        let record = farm.job(id).expect("job").record(0);
        let checkpoints = farm.job_mut(id).expect("job").take_checkpoints(true, 4);
        let mut restarted = Farm::new(FarmConfig::default());
        restarted.restore(record, checkpoints, &[], 1).expect("restore");
        assert_eq!(restarted.job(id).expect("job").state, JobState::Completed);
        assert!(log_has(&restarted, id, "restarted are finished without the denoised layer"));
    }

    /// A restart while the final step is owed, as the service restores (checkpoint heads; the
    /// film read back by the residency loop before any worker registered again): the step waits
    /// for a denoise worker to register within the grace, and the job completes with its layer.
    /// Past the grace with none, the frame goes on without it.
    #[test]
    fn after_a_restart_the_final_step_waits_for_denoise_workers_to_register() {
        let cfg = FarmConfig { denoise_grace_ms: 30_000, ..FarmConfig::default() };
        let mut farm = Farm::new(cfg.clone());
        let id = farm.submit("x".into(), None, 0, settings(false), 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        tagged(&mut farm, "d", &[DENOISE_TAG]);
        render_all(&mut farm, plain, 0);
        assert!(farm.job(id).expect("job").denoise_owed(0));
        let record = farm.job(id).expect("job").record(0);
        let checkpoint = farm.job_mut(id).expect("job").take_checkpoints(true, 4).pop().expect("checkpoint");
        for (grace_left, registers) in [(true, true), (false, false)] {
            let t0 = 1_000_000;
            let mut restarted = Farm::new(cfg.clone());
            restarted.restore(record.clone(), [checkpoint.head()], &[], t0).expect("restore");
            // The residency loop reads the film back at once, before any worker registered.
            let plan = restarted.residency_plan(t0);
            assert_eq!(plan.load.len(), 1, "{plan:?}");
            let now = if grace_left { t0 + 10 } else { t0 + cfg.denoise_grace_ms + 1 };
            restarted.attach_film(plan.load[0], Ok(checkpoint.clone()), now).expect("attach");
            let job = restarted.job(id).expect("job");
            if !grace_left {
                assert_eq!(job.state, JobState::Completed, "no denoiser past the grace");
                assert!(log_has(&restarted, id, "no live worker can denoise"));
                continue;
            }
            assert!(job.denoise_owed(0) && job.state == JobState::Running, "the step waits for a worker");
            restarted.expire_denoise(now + 1_000);
            assert!(restarted.job(id).expect("job").denoise_owed(0), "not given up within the grace");
            if registers {
                let d = tagged(&mut restarted, "d again", &[DENOISE_TAG]);
                let g = restarted.lease(d, now + 2_000).expect("lease").expect("the final step");
                assert_eq!(g.kind, LeaseKind::Denoise);
                let out = restarted.accept_denoised(g.lease_id, layer(&restarted, g.lease_id, 2.0), now + 3_000);
                assert!(out.expect("stored").job_completed);
                assert!(restarted.job(id).expect("job").denoised(0).is_some());
            }
        }
    }

    /// A sequence: each frame's final step holds that frame back from being written (not the
    /// others), and its layer is kept for the frame writer.
    #[test]
    fn a_sequence_frame_waits_for_its_own_step() {
        let mut farm = Farm::new(FarmConfig { max_open_frames: 2, ..FarmConfig::default() });
        let spec = JobSpec {
            frames: Some(FrameSet::parse("10-11").expect("frames")),
            order: FrameOrder::Frame,
            ..JobSpec::new("x".into(), settings(false))
        };
        let id = farm.submit_job(spec, 0).expect("submit");
        let plain = tagged(&mut farm, "plain", &["cpu"]);
        let d = tagged(&mut farm, "d", &[DENOISE_TAG]);
        render_all(&mut farm, plain, 0);
        let job = farm.job(id).expect("job");
        assert_eq!(job.frames_to_write().len(), 2);
        assert!(job.denoise_owed(0) && job.denoise_owed(1));
        let g = farm.lease(d, 0).expect("lease").expect("frame 10's step");
        assert_eq!(g.unit.frame, 10);
        let out = farm.accept_denoised(g.lease_id, layer(&farm, g.lease_id, 1.0), 0).expect("stored");
        assert_eq!((out.frame, out.job_completed), (10, false));
        let job = farm.job(id).expect("job");
        assert!(!job.denoise_owed(0) && job.denoise_owed(1) && job.denoised(0).is_some());
        let g = farm.lease(d, 0).expect("lease").expect("frame 11's step");
        assert_eq!(g.unit.frame, 11);
        let out = farm.accept_denoised(g.lease_id, layer(&farm, g.lease_id, 1.0), 0).expect("stored");
        assert!(out.job_completed);
    }
}
