//! Leases: scheduling, expiry, release and the merge of results.
//!
//! A result is merged in three steps, so that the fold (a tile's sums added to the film) runs
//! without the farm lock: [`Farm::begin_accept`] (farm lock: check the result, end its lease,
//! the unit is received: in flight, not pending), [`Fold::fold`] (its frame's lock only: the
//! frame's `FilmAssembly` folds what is in order), [`Farm::finish_accept`] (farm lock: record
//! the units folded, complete passes, the frame, the job).

use super::frame_run::sample_count_mismatch;
use super::{Farm, FarmError, Job, MergeOutcome};
use parking_lot::Mutex;
use pathfarm_common::adaptive::AdaptiveSettings;
use pathfarm_common::assembly::{FilmAssembly, Folded};
use pathfarm_common::film::Film;
use pathfarm_common::film::SplatBuffer;
use pathfarm_common::job::{Plan, TileRect, UnitKey};
use pathfarm_common::protocol::{
    FrameOrder, FrameState, JobId, JobState, LeaseGrant, LeaseId, NotifyEvent, ResultView, TileSums, WorkerId,
};
use std::sync::Arc;

#[derive(Clone, Debug)]
pub(super) struct Lease {
    pub(super) job: JobId,
    /// Index of the unit's frame in the job's frame set.
    pub(super) frame: usize,
    pub(super) unit: usize,
    pub(super) worker: WorkerId,
    pub(super) deadline_ms: u64,
    /// A denoise step of frame `frame` (`unit` unused), not a unit (`farm/denoise.rs`).
    pub(super) denoise: Option<super::denoise::Step>,
}

/// A result taken from its lease ([`Farm::begin_accept`]), to be folded into its frame's
/// film outside the farm lock.
pub struct Fold<'a> {
    job: JobId,
    index: usize,
    key: UnitKey,
    asm: Arc<Mutex<FilmAssembly>>,
    plan: Arc<Plan>,
    adaptive: Option<(AdaptiveSettings, u32)>,
    rect: TileRect,
    sums: TileSums<'a>,
    splats: Option<SplatBuffer>,
}

/// What a [`Fold`] folded, for [`Farm::finish_accept`] to record.
#[derive(Debug)]
pub struct Folding {
    job: JobId,
    index: usize,
    /// The assembly folded into: recorded only while the frame still has it.
    asm: Arc<Mutex<FilmAssembly>>,
    folded: Vec<Folded>,
}

impl Fold<'_> {
    /// Folds the result under its frame's lock alone: the one merge (`FilmAssembly`, as
    /// `render_local`'s) folds every unit of the tile now in order (none while the film is on
    /// disk: the result waits in the assembly). A result in order is merged as its sums are
    /// read (packed sums straight from the body); one that must wait is decoded to wait.
    pub fn fold(self) -> Folding {
        let adaptive = self.adaptive.as_ref().map(|(a, spp)| (a, *spp));
        let folded = self.asm.lock().offer_sums(&self.plan, adaptive, self.key, self.rect, self.sums, self.splats);
        Folding { job: self.job, index: self.index, asm: self.asm, folded }
    }
}

impl Farm {
    /// Hands the worker the next unit: highest priority first; among equal priorities the job
    /// with the fewest units in flight (then the fewest served) - a fair share; inside a job,
    /// canonical (pass-major) order, returned units first.
    pub fn lease(&mut self, worker: WorkerId, now_ms: u64) -> Result<Option<LeaseGrant>, FarmError> {
        let w = self.workers.get_mut(&worker).ok_or(FarmError::NoWorker(worker))?;
        w.last_seen_ms = now_ms;
        let was_offline = std::mem::replace(&mut w.offline, false);
        if was_offline {
            self.note_unservable();
        }
        // A worker that can denoise takes the waiting denoise steps first: they hold frames back.
        if let Some(grant) = self.lease_denoise(worker, now_ms) {
            return Ok(Some(grant));
        }
        let tags = &self.workers[&worker].tags;
        // A job whose frames in progress have nothing pending may start its next frames (a
        // queued job its first), while it holds fewer than `max_open_frames` (frame order) and
        // the new films fit the film budget beside every film held.
        let (budget, max_open) =
            (self.cfg.film_budget_bytes.unwrap_or(u64::MAX), self.cfg.max_open_frames.max(1) as u64);
        let max_films = self.cfg.max_resident_films.max(1) as u64;
        let mut held: Option<(u64, u64)> = None;
        let farm = &*self;
        let mut may_start = |j: &Job| {
            j.unstarted > 0
                && (j.order == FrameOrder::SequencePreview || j.films_held() < max_open)
                && (j.order == FrameOrder::Frame || j.films_held() == 0)
                // A frame whose film is on disk is loaded before the next one starts.
                && j.open.values().all(|r| r.resident)
                && {
                    let (films, used) = *held.get_or_insert_with(|| farm.films_in_memory());
                    let n = j.films_to_start();
                    let need = n.saturating_mul(Film::bytes_for(j.settings.width, j.settings.height));
                    films + n <= max_films && used.saturating_add(need) <= budget
                }
        };
        let pick = self
            .jobs
            .values()
            .filter(|j| j.accepts_work() && !j.blocklist.contains(&worker))
            .filter(|j| j.requires.iter().all(|t| tags.contains(t)))
            .filter(|j| j.has_pending() || may_start(j))
            .min_by_key(|j| (std::cmp::Reverse(j.priority), j.leased, j.served, j.id))
            .map(|j| j.id);
        let Some(job_id) = pick else { return Ok(None) };
        let lease_id = self.next_lease;
        self.next_lease += 1;
        let Some(job) = self.jobs.get_mut(&job_id) else { return Ok(None) };
        if !job.has_pending() {
            job.start_frames();
        }
        let Some((frame, unit)) = job.take_unit(lease_id) else { return Ok(None) };
        if let Some(run) = job.open.get_mut(&frame) {
            run.last_used = now_ms;
        }
        job.leased += 1;
        job.served += 1;
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            job.started_ms = Some(now_ms);
            self.changes.record(job_id);
        }
        if !job.started_notified {
            job.started_notified = true;
            if job.notify.as_ref().is_some_and(|n| n.wants(NotifyEvent::Started)) {
                self.notifications.push((job_id, NotifyEvent::Started));
            }
        }
        let key = job.unit_key(frame, unit);
        let mut settings = job.settings.clone();
        settings.frame = key.frame;
        let mask = job
            .open
            .get(&frame)
            // Adaptive jobs only: under the frame lock (lock order farm, then frame), which waits
            // for a fold of this frame in progress.
            .filter(|_| job.settings.adaptive.is_some())
            .and_then(|run| run.asm.lock().mask(key.tile as usize).cloned())
            .filter(|m| !m.none());
        let grant = LeaseGrant {
            kind: Default::default(),
            mask,
            lease_id,
            job_id,
            scene_id: job.scene_id.clone(),
            settings,
            unit: key,
            tile: job.plan.tiles[key.tile as usize],
            pass: job.plan.passes[key.pass as usize],
        };
        self.leases.insert(
            lease_id,
            Lease { job: job_id, frame, unit, worker, deadline_ms: now_ms + self.cfg.lease_timeout_ms, denoise: None },
        );
        if let Some(w) = self.workers.get_mut(&worker) {
            w.leases.insert(lease_id);
        }
        self.counters.units_leased += 1;
        self.changes.progress(job_id);
        self.changes.workers.insert(worker);
        Ok(Some(grant))
    }

    pub(super) fn take_lease(&mut self, lease_id: LeaseId) -> Option<Lease> {
        let l = self.leases.remove(&lease_id)?;
        if let Some(w) = self.workers.get_mut(&l.worker) {
            w.leases.remove(&lease_id);
        }
        if let Some(job) = self.jobs.get_mut(&l.job) {
            job.leased = job.leased.saturating_sub(1);
        }
        Some(l)
    }

    /// Sends units of expired leases back to pending and marks silent workers offline.
    /// Returns the number of leases that expired.
    ///
    /// `expire` runs every `expiry_tick_ms`. When it runs late by more than half the lease
    /// timeout, the coordinator stalled (paused, swapped, starved): workers' heartbeats and
    /// results could not be heard meanwhile, so every lease gets one more lease timeout from
    /// now before it can expire, and no worker is marked offline or pruned until then.
    pub fn expire(&mut self, now_ms: u64) -> usize {
        let timeout = self.cfg.lease_timeout_ms;
        if let Some(last) = self.last_expire_ms
            && now_ms.saturating_sub(last) > self.cfg.expiry_tick_ms + timeout / 2
        {
            let grace = now_ms + timeout;
            tracing::warn!(
                stalled_ms = now_ms.saturating_sub(last),
                leases = self.leases.len(),
                grace_ms = timeout,
                "the coordinator stalled: every lease gets one lease timeout of grace"
            );
            for l in self.leases.values_mut() {
                l.deadline_ms = l.deadline_ms.max(grace);
            }
            self.grace_until_ms = grace;
        }
        self.last_expire_ms = Some(now_ms);
        let expired: Vec<LeaseId> =
            self.leases.iter().filter(|(_, l)| l.deadline_ms < now_ms).map(|(id, _)| *id).collect();
        for &id in &expired {
            if let Some(l) = self.take_lease(id) {
                self.changes.work_ready = true;
                self.changes.progress(l.job);
                self.changes.workers.insert(l.worker);
                if let Some(job) = self.jobs.get_mut(&l.job) {
                    job.give_back(&l, now_ms);
                    let key = job.unit_key(l.frame, l.unit);
                    if l.denoise.is_some() {
                        job.log(format!(
                            "lease {id} of worker {} expired: the denoise step of frame {} waits again",
                            l.worker, key.frame
                        ));
                    } else {
                        job.log(format!(
                            "lease {id} of worker {} expired: unit frame {} pass {} tile {} is pending again",
                            l.worker, key.frame, key.pass, key.tile
                        ));
                    }
                }
                self.counters.leases_expired += 1;
            }
        }
        if now_ms >= self.grace_until_ms {
            for (&id, w) in self.workers.iter_mut() {
                if now_ms.saturating_sub(w.last_seen_ms) > self.cfg.lease_timeout_ms && !w.offline {
                    w.offline = true;
                    self.changes.workers.insert(id);
                }
            }
        }
        self.note_unservable();
        expired.len()
    }

    /// A worker gives a unit back: on shutdown (`failed = false`) or because rendering failed.
    pub fn release(&mut self, lease_id: LeaseId, failed: bool, reason: &str, now_ms: u64) -> Result<(), FarmError> {
        let l = self.take_lease(lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
        self.changes.work_ready = true;
        self.changes.progress(l.job);
        self.changes.workers.insert(l.worker);
        if l.denoise.is_some() {
            self.denoise_released(l, failed, reason, now_ms);
            return Ok(());
        }
        let (max_failures, blocklist_after) = (self.cfg.max_unit_failures, self.cfg.blocklist_after);
        let Some(job) = self.jobs.get_mut(&l.job) else { return Ok(()) };
        job.requeue(l.frame, l.unit);
        if !failed {
            return Ok(());
        }
        self.counters.units_failed += 1;
        let key = job.unit_key(l.frame, l.unit);
        let unit_name = if job.sequence {
            format!("unit frame {} pass {} tile {}", key.frame, key.pass, key.tile)
        } else {
            format!("unit pass {} tile {}", key.pass, key.tile)
        };
        job.log(format!("worker {} failed {unit_name}: {reason}", l.worker));
        let unit_failures = job.unit_failures.entry((l.frame, l.unit)).or_insert(0);
        *unit_failures += 1;
        let unit_failures = *unit_failures;
        let worker_failures = job.worker_failures.entry(l.worker).or_insert(0);
        *worker_failures += 1;
        if *worker_failures >= blocklist_after && job.blocklist.insert(l.worker) {
            job.log(format!("worker {} is blocklisted for this job after {blocklist_after} failures", l.worker));
        }
        // Fail the job when a unit keeps failing, or when every live worker is blocklisted for
        // it (nobody is left to try: waiting would leave it queued forever).
        let workers = &self.workers;
        let everyone_blocklisted = workers.iter().all(|(id, w)| w.offline || job.blocklist.contains(id));
        let failure = if unit_failures >= max_failures {
            Some(format!("{unit_name} failed {unit_failures} times; last error: {reason}"))
        } else if everyone_blocklisted {
            Some(format!("every worker is blocklisted for this job after repeated failures; last error: {reason}"))
        } else {
            None
        };
        if let Some(msg) = failure {
            let id = job.id;
            job.log(format!("job failed: {msg}"));
            self.finish(id, JobState::Failed, Some(msg), now_ms);
        }
        Ok(())
    }

    /// Accepts a unit's result from the worker holding its lease and merges it: the three
    /// steps of [`Farm::begin_accept`], [`Fold::fold`] and [`Farm::finish_accept`] at once.
    pub fn accept<'a>(
        &mut self,
        lease_id: LeaseId,
        frame: impl Into<ResultView<'a>>,
        now_ms: u64,
    ) -> Result<MergeOutcome, FarmError> {
        let fold = self.begin_accept(lease_id, frame, now_ms)?;
        Ok(self.finish_accept(fold.fold(), now_ms))
    }

    /// Takes a unit's result from the worker holding its lease: checks it, ends the lease and
    /// marks the unit received (in flight: neither pending nor merged). The returned [`Fold`]
    /// folds it under its frame's lock alone, with the farm lock released meanwhile; then
    /// [`Farm::finish_accept`] records what it folded.
    pub fn begin_accept<'a>(
        &mut self,
        lease_id: LeaseId,
        frame: impl Into<ResultView<'a>>,
        now_ms: u64,
    ) -> Result<Fold<'a>, FarmError> {
        let frame = frame.into();
        let l = self.leases.get(&lease_id).ok_or(FarmError::LeaseLost(lease_id))?.clone();
        if l.denoise.is_some() {
            return Err(FarmError::ResultMismatch {
                lease: lease_id,
                reason: "this is a denoise lease: PUT its denoised layer to /leases/{id}/denoised".into(),
            });
        }
        let job = self.jobs.get(&l.job).ok_or(FarmError::LeaseLost(lease_id))?;
        if !job.open.contains_key(&l.frame) {
            return Err(FarmError::LeaseLost(lease_id));
        }
        let key = job.unit_key(l.frame, l.unit);
        let rect = job.plan.tiles[key.tile as usize];
        let checked = if frame.lease_id != lease_id {
            Err(format!("frame is for lease {}", frame.lease_id))
        } else if frame.job_id != l.job || frame.unit != key {
            Err(format!(
                "frame is for job {} unit {:?}, lease holds job {} unit {key:?}",
                frame.job_id, frame.unit, l.job
            ))
        } else if frame.rect != rect || frame.sums.len() != rect.pixel_count() {
            Err(format!("tile {:?} of {} pixels, expected {rect:?}", frame.rect, frame.sums.len()))
        } else if frame
            .splats
            .as_ref()
            .is_some_and(|s| (s.width, s.height) != (job.settings.width, job.settings.height))
        {
            Err("splat buffer size differs from the image".into())
        } else {
            // Adaptive jobs only: the mask is read under the frame lock (a fold of the frame in
            // progress finishes first). It is the tile's mask its pass was leased with: the
            // tile's next fold is this unit's.
            let run = job.open.get(&l.frame);
            let asm = run.filter(|_| job.settings.adaptive.is_some()).map(|r| r.asm.lock());
            let mask = asm.as_ref().and_then(|a| a.mask(key.tile as usize));
            sample_count_mismatch(&frame.sums, rect, job.plan.passes[key.pass as usize].spp(), mask)
        };
        let rendered = match checked {
            Ok(samples) => samples,
            Err(reason) => {
                // The worker holds the lease but sent something else: give the unit to someone else.
                self.counters.results_rejected += 1;
                self.take_lease(lease_id);
                self.changes.work_ready = true;
                self.changes.progress(l.job);
                if let Some(job) = self.jobs.get_mut(&l.job) {
                    job.requeue(l.frame, l.unit);
                    job.log(format!("refused a result of worker {}: {reason}", l.worker));
                }
                return Err(FarmError::ResultMismatch { lease: lease_id, reason });
            }
        };
        self.take_lease(lease_id);
        self.changes.progress(l.job);
        self.changes.workers.insert(l.worker);
        if let Some(w) = self.workers.get_mut(&l.worker) {
            w.units_done += 1;
            w.samples_done += rendered;
            w.last_seen_ms = now_ms;
        }
        let Some(job) = self.jobs.get_mut(&l.job) else { return Err(FarmError::LeaseLost(lease_id)) };
        let adaptive = job.settings.adaptive.map(|a| (a, job.settings.spp));
        let Some(run) = job.open.get_mut(&l.frame) else { return Err(FarmError::LeaseLost(lease_id)) };
        run.receive(l.unit);
        Ok(Fold {
            job: l.job,
            index: l.frame,
            key,
            asm: run.asm.clone(),
            plan: job.plan.clone(),
            adaptive,
            rect,
            sums: frame.sums,
            splats: frame.splats,
        })
    }

    /// Records what a [`Fold`] folded (in any order with the other folds of its frame), then
    /// completes passes, the frame and the job as they become complete.
    pub fn finish_accept(&mut self, folding: Folding, now_ms: u64) -> MergeOutcome {
        let run = self.jobs.get(&folding.job).and_then(|j| j.open.get(&folding.index));
        if !run.is_some_and(|r| Arc::ptr_eq(&r.asm, &folding.asm)) {
            return MergeOutcome::default(); // the frame ended meanwhile (its job did)
        }
        self.settle(folding.job, folding.index, &folding.folded, now_ms)
    }

    /// Records the units frame `index`'s assembly folded (`folded`, in the order folded: none
    /// while the frame's film is on disk, they wait until it is loaded), then completes passes,
    /// the frame and the job as they become complete.
    pub(super) fn settle(&mut self, job_id: JobId, index: usize, folded: &[Folded], now_ms: u64) -> MergeOutcome {
        let mut out = MergeOutcome::default();
        let Some(job) = self.jobs.get_mut(&job_id) else { return out };
        let Some(run) = job.open.get_mut(&index) else { return out };
        let passes_before = run.passes_done;
        run.last_used = now_ms;
        for f in folded {
            job.record_folded(index, f);
            self.counters.units_merged += 1;
            self.counters.samples_merged += f.samples;
            out.folded += 1;
            if f.judged.is_some() {
                // Adaptive: the tile's next pass may now be pending.
                self.changes.work_ready = true;
            }
        }
        let Some(run) = job.open.get(&index) else { return out };
        // Passes complete in order, because every tile folds its passes in order.
        out.passes_completed = (passes_before..run.passes_done).collect();
        if !out.passes_completed.is_empty() {
            self.changes.outputs = true;
            if !job.sequence {
                job.output_dirty = true;
            }
        }
        if out.folded > 0 {
            self.changes.progress(job_id);
        }
        job.status[index].passes_done = run.passes_done;
        let frame_complete = run.is_complete() && job.status[index].state == FrameState::Rendering;
        if frame_complete {
            let frame = job.frames.frames()[index];
            job.frame_merged(index);
            out.frames_completed.push(frame);
            self.changes.outputs = true;
            self.changes.work_ready = true;
            if job.sequence {
                job.log(format!("frame {frame} merged"));
            }
        }
        let (id, all_merged) = (job.id, job.frames_merged as usize == job.frames.len() && !job.state.is_finished());
        // Denoise steps (`farm/denoise.rs`): a frame's final one holds the job open.
        let owed = (frame_complete || !out.passes_completed.is_empty())
            && self.denoise_after_merge(id, index, &out.passes_completed, frame_complete, now_ms);
        if all_merged && !owed {
            self.log_job(id, "completed".into());
            self.finish(id, JobState::Completed, None, now_ms);
            out.job_completed = true;
        } else if all_merged && frame_complete {
            self.log_job(id, "every frame merged; waiting for the denoise step".into());
        }
        out
    }

    /// The tile and image size a result for `lease_id` must have, if the lease is held.
    pub fn lease_shape(&self, lease_id: LeaseId) -> Option<(pathfarm_common::job::TileRect, (u32, u32))> {
        let l = self.leases.get(&lease_id)?;
        let job = self.jobs.get(&l.job)?;
        let key = job.unit_key(l.frame, l.unit);
        Some((job.plan.tiles[key.tile as usize], (job.settings.width, job.settings.height)))
    }

    /// Leases held right now.
    pub fn leases_held(&self) -> usize {
        self.leases.len()
    }
}
