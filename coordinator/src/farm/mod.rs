//! The farm's state machine: jobs, units, workers and leases, in one place.
//!
//! Pure and synchronous: every operation takes the current time in milliseconds, so tests drive a
//! manual clock. The HTTP layer holds a [`Farm`] behind a mutex and calls these methods. Each
//! frame in progress keeps its film in a `FilmAssembly` behind its own lock, so that a result
//! folds without the farm's ([`Farm::begin_accept`], [`Fold::fold`], [`Farm::finish_accept`]);
//! the lock order is the farm's, then a frame's.
//!
//! Job: queued -> running -> paused <-> running -> completed | failed | cancelled.
//! Unit: pending -> leased(lease) -> received -> merged; an expired or released lease sends the
//! unit back to pending. A result is accepted only from the lease that holds the unit, so each
//! unit is merged exactly once.
//!
//! Merge: each frame in progress folds its results through a `FilmAssembly`
//! (`common/src/assembly.rs`), the same merge as `render_local`'s and restore's; the farm
//! records what it folded ([`FrameRun`] scheduling, the job's figures). A tile folds pass p before pass p+1
//! (results that arrive early wait in the assembly), and a unit's BDPT splats fold into the
//! film's radiance sums with the unit. The
//! film's radiance sums are exact integers, for which this order is not needed; its AOV means
//! (albedo, normal, depth) are bit-identical to a local render because of it (film.rs), and it
//! makes every progressive image a prefix of the final one (each pixel holds samples `[0, s)`).

mod changes;
mod denoise;
mod frame_run;
mod job;
mod lease;
mod residency;
#[cfg(test)]
pub(crate) mod tests;
mod workers;

pub use changes::Changes;
pub use denoise::{DENOISE_TAG, DenoiseOutcome, DenoisedLayer};
pub use frame_run::FrameRun;
use job::FrameStatus;
pub use job::{Checkpoint, CheckpointHead, CheckpointSource, FrameCheckpoint, FrameFilm, Job, JobRecord, JobSpec};
use lease::Lease;
pub use lease::{Fold, Folding};
pub use residency::{FrameRef, ResidencyPlan};
use workers::Worker;

use pathfarm_common::assembly::FilmAssembly;
use pathfarm_common::film::Film;
use pathfarm_common::frames::FrameSet;
use pathfarm_common::job::{Limits, RenderSettings};
use pathfarm_common::protocol::{FrameOrder, FrameState, JobId, JobState, LeaseId, Notify, NotifyEvent, WorkerId};
use std::collections::{BTreeMap, HashMap};

/// Tunables of the state machine.
#[derive(Clone, Debug)]
pub struct FarmConfig {
    /// A lease that is not renewed by a heartbeat for this long expires.
    pub lease_timeout_ms: u64,
    /// Workers are asked to heartbeat this often.
    pub heartbeat_ms: u64,
    /// A unit that failed this many times fails its job.
    pub max_unit_failures: u32,
    /// A worker that failed this many units of a job is blocklisted for it.
    pub blocklist_after: u32,
    pub limits: Limits,
    /// How often the service calls [`Farm::expire`]; a call later than this plus half the lease
    /// timeout after the last one means the coordinator stalled.
    pub expiry_tick_ms: u64,
    /// Workers offline (not seen) for longer than this, holding no lease, are forgotten.
    /// `None`: never.
    pub worker_prune_ms: Option<u64>,
    /// Memory for the films in memory (each `Film::bytes_for` its size): frames start, and
    /// films are read back from disk, only while they fit; a job whose films could never fit
    /// is refused. `None`: unbounded.
    pub film_budget_bytes: Option<u64>,
    /// Films in memory at most (frames in progress and being written); beyond it the least
    /// recently used ones wait on disk ([`Farm::residency_plan`]).
    pub max_resident_films: usize,
    /// A film read back from disk stays in memory at least this long before it may be written
    /// out again for another job's (no thrashing between jobs that take turns).
    pub min_resident_ms: u64,
    /// Frames of one frame-order job in progress at once, at most (the next frame starts when
    /// the frames in progress have no pending unit left and its film fits the budget).
    pub max_open_frames: usize,
    /// A job's final denoise step that no worker took for this long is given up: its frame is
    /// finished without the denoised layer (`farm/denoise.rs`).
    pub denoise_grace_ms: u64,
}

/// Default of `--film-memory-mb`: 16 GiB of films in memory.
pub const DEFAULT_FILM_BUDGET_BYTES: u64 = 16 << 30;
/// Default of `--max-resident-films`.
pub const DEFAULT_MAX_RESIDENT_FILMS: usize = 32;

impl Default for FarmConfig {
    fn default() -> Self {
        Self {
            lease_timeout_ms: 10_000,
            heartbeat_ms: 2_000,
            max_unit_failures: 3,
            blocklist_after: 2,
            limits: Limits::default(),
            film_budget_bytes: Some(DEFAULT_FILM_BUDGET_BYTES),
            max_resident_films: DEFAULT_MAX_RESIDENT_FILMS,
            min_resident_ms: 2_000,
            worker_prune_ms: Some(3_600_000),
            expiry_tick_ms: 250,
            max_open_frames: 2,
            denoise_grace_ms: 30_000,
        }
    }
}

/// Constant-time comparison; an empty token never matches (not even an empty one configured).
pub fn token_matches(given: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    !expected.is_empty() && given.len() == expected.len() && bool::from(given.as_bytes().ct_eq(expected.as_bytes()))
}

pub use pathfarm_common::frames::MAX_FRAMES;

/// Errors of farm operations; the API maps each to a status code.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FarmError {
    #[error("job {0} does not exist")]
    NoJob(JobId),
    #[error("worker {0} is not registered (register again)")]
    NoWorker(WorkerId),
    #[error("lease {0} is not held (expired, released, already delivered, or its job ended)")]
    LeaseLost(LeaseId),
    #[error("result does not match lease {lease}: {reason}")]
    ResultMismatch { lease: LeaseId, reason: String },
    #[error("job {id} is {state}; {action} is not possible")]
    BadState { id: JobId, state: &'static str, action: &'static str },
    #[error("invalid job: {0}")]
    InvalidJob(String),
    #[error("{0}")]
    OverBudget(String),
    /// The request's worker secret is missing or is not the secret of the worker the lease or
    /// the worker id belongs to.
    #[error("{0}")]
    WrongWorker(String),
    /// A denoised layer older than the one the farm holds.
    #[error("stale denoised layer: {0}")]
    Stale(String),
}

fn missing_secret() -> FarmError {
    FarmError::WrongWorker(format!(
        "missing {} header: send the worker_secret that POST /workers/register returned",
        pathfarm_common::protocol::WORKER_SECRET_HEADER
    ))
}

/// What merging a result did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MergeOutcome {
    /// Units folded into the film by this result (0 if it waits for an earlier pass).
    pub folded: u32,
    /// Passes that became complete.
    pub passes_completed: Vec<u32>,
    /// Frames (numbers) whose every unit is now merged.
    pub frames_completed: Vec<i32>,
    pub job_completed: bool,
}

/// Counters for `/metrics`.
#[derive(Clone, Debug, Default)]
pub struct Counters {
    pub units_leased: u64,
    pub units_merged: u64,
    pub units_failed: u64,
    pub leases_expired: u64,
    pub results_rejected: u64,
    pub samples_merged: u64,
}

/// All jobs, workers and leases.
#[derive(Debug)]
pub struct Farm {
    pub cfg: FarmConfig,
    jobs: BTreeMap<JobId, Job>,
    workers: BTreeMap<WorkerId, Worker>,
    leases: HashMap<LeaseId, Lease>,
    next_job: JobId,
    next_worker: WorkerId,
    next_lease: LeaseId,
    pub counters: Counters,
    /// When `expire` last ran (to notice that the coordinator stalled).
    last_expire_ms: Option<u64>,
    /// After a stall, nothing is expired, marked offline or pruned before this time.
    grace_until_ms: u64,
    /// When jobs were last restored (a coordinator restart): workers register again during the
    /// following `denoise_grace_ms`, so a denoise step is not given up for want of one before.
    restored_ms: Option<u64>,
    /// Webhook events of jobs that asked for them, oldest first; the server drains them
    /// (`take_notifications`).
    notifications: Vec<(JobId, NotifyEvent)>,
    /// What changed since the service last took it ([`Farm::take_changes`]).
    changes: Changes,
}

impl Farm {
    pub fn new(cfg: FarmConfig) -> Self {
        Self::with_epoch(cfg, 0)
    }

    /// A farm whose worker and lease ids carry `epoch` (the coordinator's start count) in their
    /// high bits, so ids handed out before a restart never match ids handed out after it.
    pub fn with_epoch(cfg: FarmConfig, epoch: u64) -> Self {
        Self {
            cfg,
            jobs: BTreeMap::new(),
            workers: BTreeMap::new(),
            leases: HashMap::new(),
            next_job: 1,
            next_worker: (epoch << 32) + 1,
            next_lease: (epoch << 40) + 1,
            notifications: Vec::new(),
            changes: Changes::default(),
            counters: Counters::default(),
            last_expire_ms: None,
            grace_until_ms: 0,
            restored_ms: None,
        }
    }

    /// Brings back a job from the store. `checkpoints`: the last checkpoint of each frame that
    /// had one; `done`: indices of the frames whose images were written (sequences; for a
    /// finished single-frame job, `[0]` when its final image is on disk, as its final marker
    /// says: then no film is held and its checkpoint is not needed). Units merged by a
    /// checkpoint stay merged, every other unit of the frame is pending again; frames without
    /// either start over. A job recorded completed whose frames are neither written nor complete
    /// in their checkpoints is queued again for the units they lack.
    pub fn restore(
        &mut self,
        rec: JobRecord,
        checkpoints: impl IntoIterator<Item = impl Into<FrameCheckpoint>>,
        done: &[usize],
        now_ms: u64,
    ) -> Result<(), String> {
        self.restored_ms = Some(now_ms);
        let spec = JobSpec {
            scene_id: rec.scene_id,
            name: Some(rec.name),
            priority: rec.priority,
            settings: rec.settings,
            requires: rec.requires,
            frames: rec.frames,
            order: rec.order,
        };
        let mut job = Job::new(rec.id, spec, rec.created_ms);
        job.finished_ms = rec.finished_ms;
        job.error = rec.error;
        job.notify = rec.notify;
        job.started_notified = rec.state != JobState::Queued;
        job.run_ms_before = rec.run_ms;
        let passes = job.plan.passes.len() as u32;
        let (units_per_frame, samples_per_frame) = (job.units_per_frame(), job.samples_per_frame());
        if job.sequence {
            for &i in done {
                if job.status.get(i).is_some_and(|s| s.state == FrameState::Pending) {
                    job.status[i] = FrameStatus { state: FrameState::Done, passes_done: passes };
                    job.unstarted -= 1;
                    job.frames_done += 1;
                    job.frames_merged += 1;
                    job.units_merged += units_per_frame;
                    job.samples_done += samples_per_frame;
                }
            }
        }
        if !job.sequence && rec.state.is_finished() && done.contains(&0) {
            job.image_on_disk = Some(None);
            if rec.state == JobState::Completed {
                job.status[0] = FrameStatus { state: FrameState::Done, passes_done: passes };
                job.unstarted = 0;
                (job.frames_done, job.frames_merged) = (1, 1);
                job.units_merged = units_per_frame;
                job.samples_done = job.samples_total;
            }
        }
        let tiles = job.plan.tiles.len();
        let checkpoints: Vec<FrameCheckpoint> =
            if job.image_on_disk.is_some() { Vec::new() } else { checkpoints.into_iter().map(Into::into).collect() };
        for cp in checkpoints {
            let (cp, film) = match cp {
                FrameCheckpoint::Loaded(c) => (c.head(), Some(c.film)),
                FrameCheckpoint::OnDisk(h) => (h, None),
            };
            let index = job
                .frame_index(cp.frame)
                .ok_or_else(|| format!("checkpoint of job {} is for frame {}, not in its frames", rec.id, cp.frame))?;
            if job.status[index].state != FrameState::Pending {
                continue; // written already: the checkpoint is stale
            }
            if cp.job_id != rec.id
                || cp.next_pass.len() != tiles
                || (cp.width, cp.height) != (job.settings.width, job.settings.height)
                || cp.next_pass.iter().any(|&p| p > passes)
            {
                return Err(format!("checkpoint of job {} frame {} does not match its settings", rec.id, cp.frame));
            }
            let on_disk = film.is_none();
            job.open_frame_with(index, FilmAssembly::without_film(&job.plan, cp.next_pass.clone()));
            let Some(run) = job.open.get_mut(&index) else { continue };
            run.restored = true;
            for (tile, &np) in cp.next_pass.iter().enumerate() {
                job.units_merged += u64::from(np);
                if job.settings.adaptive.is_none() {
                    job.samples_done += job.plan.tiles[tile].pixel_count() as u64
                        * u64::from(job.plan.passes.get(..np as usize).map_or(0, |p| p.iter().map(|p| p.spp()).sum()));
                }
            }
            // Adaptive: converged pixels hold fewer samples than the passes, and the masks are
            // a pure function of the merged sums (not stored): both come from the film, now or
            // when it is loaded (the assembly judges them when it gets the film).
            if let Some(film) = film {
                job.put_film(index, film);
            }
            let Some(run) = job.open.get_mut(&index) else { continue };
            run.checkpoint_dirty = false;
            let (passes_done, complete) = (run.passes_done, run.is_complete());
            job.status[index].passes_done = passes_done;
            // A complete frame whose film is on disk completes when it is loaded.
            if complete && !on_disk {
                job.frame_merged(index);
            }
        }
        // Frames without a checkpoint start when they are leased (their films are not held
        // before); a sequence preview that started holds every frame's film.
        let total = job.frames.len() as u32;
        // A single-frame job recorded completed without its final image on disk and whose
        // checkpoint does not hold every unit: the row is written when the job completes, the
        // checkpoint and the image after it (a kill in between left them behind).
        let single_unfinished =
            !job.sequence && job.image_on_disk.is_none() && !job.open.values().any(|r| r.is_complete());
        job.state = match rec.state {
            // A sequence recorded completed whose last frames were merged but not written (and
            // whose checkpoints were older) renders them again; so does a single frame whose
            // checkpoint is older than its completion.
            JobState::Completed if (job.sequence && job.frames_merged < total) || single_unfinished => {
                job.finished_ms = None;
                JobState::Queued
            }
            s if s.is_finished() => s,
            _ if job.frames_merged == total => JobState::Completed,
            JobState::Paused => JobState::Paused,
            JobState::Running => {
                job.started_ms = Some(now_ms);
                JobState::Running
            }
            _ => JobState::Queued,
        };
        if job.state.is_finished() && job.state != JobState::Completed && job.sequence {
            job.drop_open_frames();
        } else if !job.state.is_finished() && job.order == FrameOrder::SequencePreview && !job.open.is_empty() {
            job.start_frames();
        }
        if job.state.is_finished() && !job.sequence && !job.open.is_empty() {
            // Its final images may not be on disk: written once more, then its film is dropped.
            job.output_dirty = true;
        }
        if job.state == JobState::Completed && job.finished_ms.is_none() {
            job.finished_ms = Some(now_ms);
        }
        job.note_restored_denoise(rec.state);
        job.log(format!(
            "restored: {} of {} units merged, {} of {} frames written",
            job.units_merged,
            units_per_frame * u64::from(total),
            job.frames_done,
            total
        ));
        self.next_job = self.next_job.max(rec.id + 1);
        self.jobs.insert(rec.id, job);
        Ok(())
    }

    /// New jobs get ids above `id`: ids of deleted jobs, and of rows the store skipped (their
    /// rows are still there), are never given again.
    pub fn reserve_job_ids_through(&mut self, id: JobId) {
        self.next_job = self.next_job.max(id.saturating_add(1));
    }

    // ----------------------------------------------------------------- jobs

    /// Adds a job; settings are validated against the configured limits.
    pub fn submit(
        &mut self,
        scene_id: String,
        name: Option<String>,
        priority: i32,
        settings: RenderSettings,
        now_ms: u64,
    ) -> Result<JobId, FarmError> {
        self.submit_job(JobSpec { name, priority, ..JobSpec::new(scene_id, settings) }, now_ms)
    }

    /// Adds a job whose units go only to workers having every tag of `requires`.
    pub fn submit_requiring(
        &mut self,
        scene_id: String,
        name: Option<String>,
        priority: i32,
        settings: RenderSettings,
        requires: Vec<String>,
        now_ms: u64,
    ) -> Result<JobId, FarmError> {
        self.submit_job(JobSpec { name, priority, requires, ..JobSpec::new(scene_id, settings) }, now_ms)
    }

    /// Memory of the films every job holds now.
    pub fn film_bytes_held(&self) -> u64 {
        self.jobs.values().map(Job::film_bytes).sum()
    }

    /// The farm's own budgets for a job whose settings are valid (`RenderSettings::validate`
    /// is the one check of the settings): frames, frames x tiles x passes within `max_units`,
    /// and the films it needs at once within `--film-memory-mb` (a job that could never start
    /// is refused; one that fits waits until the films held leave room).
    fn check_budgets(&self, spec: &JobSpec) -> Result<(), FarmError> {
        let settings = &spec.settings;
        let frames = spec.frames.as_ref().map_or(1, FrameSet::len) as u64;
        if frames > MAX_FRAMES as u64 || frames == 0 {
            return Err(FarmError::InvalidJob(format!("a job has 1 to {MAX_FRAMES} frames, got {frames}")));
        }
        let units = settings.tile_count().saturating_mul(settings.pass_count()).saturating_mul(frames);
        if units > self.cfg.limits.max_units {
            return Err(FarmError::InvalidJob(format!(
                "units (frames x tiles x passes) must be at most {}, got {frames} x {} x {} = {units}: render fewer \
                 frames, larger tiles or fewer passes",
                self.cfg.limits.max_units,
                settings.tile_count(),
                settings.pass_count()
            )));
        }
        if let Some(budget) = self.cfg.film_budget_bytes {
            let film = Film::bytes_for(settings.width, settings.height);
            let films = if spec.order == FrameOrder::SequencePreview { frames } else { 1 };
            let need = film.saturating_mul(films);
            if need > budget {
                let mib = |b: u64| b.div_ceil(1 << 20);
                let bpp = pathfarm_common::film::PIXEL_BYTES;
                let what = if films > 1 {
                    format!(
                        "order sequence_preview holds every frame's film at once: {films} frames x {} MiB = {} MiB \
                         ({}x{} pixels, {bpp} bytes each; order \"frame\" needs one film at a time)",
                        mib(film),
                        mib(need),
                        settings.width,
                        settings.height
                    )
                } else {
                    format!(
                        "the job's film needs {} MiB ({}x{} pixels, {bpp} bytes each)",
                        mib(need),
                        settings.width,
                        settings.height
                    )
                };
                return Err(FarmError::OverBudget(format!(
                    "{what}, more than the coordinator's film budget of {} MiB (--film-memory-mb): lower the \
                     resolution",
                    mib(budget)
                )));
            }
        }
        Ok(())
    }

    /// Adds a job: settings, tags, frames x tiles x passes and the film budget are checked
    /// before anything is allocated. A frame-order job needs one film to fit the budget; a
    /// sequence-preview job needs every frame's. The job holds no film while queued: its frames
    /// start when leased, once their films fit beside the films held then.
    pub fn submit_job(&mut self, spec: JobSpec, now_ms: u64) -> Result<JobId, FarmError> {
        pathfarm_common::protocol::validate_tags(&spec.requires, "requires").map_err(FarmError::InvalidJob)?;
        spec.settings.validate(&self.cfg.limits).map_err(|e| FarmError::InvalidJob(e.to_string()))?;
        self.check_budgets(&spec)?;
        let id = self.next_job;
        self.next_job += 1;
        self.jobs.insert(id, Job::new(id, spec, now_ms));
        self.note_unservable();
        self.changes.record(id);
        self.changes.work_ready = true;
        Ok(id)
    }

    pub fn job(&self, id: JobId) -> Result<&Job, FarmError> {
        self.jobs.get(&id).ok_or(FarmError::NoJob(id))
    }

    pub fn job_mut(&mut self, id: JobId) -> Result<&mut Job, FarmError> {
        self.jobs.get_mut(&id).ok_or(FarmError::NoJob(id))
    }

    pub fn jobs(&self) -> impl Iterator<Item = &Job> {
        self.jobs.values()
    }

    /// Jobs with ids above `after`, in id order.
    pub fn jobs_after(&self, after: Option<JobId>) -> impl Iterator<Item = &Job> {
        use std::ops::Bound;
        let from = after.map_or(Bound::Unbounded, Bound::Excluded);
        self.jobs.range((from, Bound::Unbounded)).map(|(_, j)| j)
    }

    pub fn jobs_mut(&mut self) -> impl Iterator<Item = &mut Job> {
        self.jobs.values_mut()
    }

    /// Ends a job's leases; their results will be refused.
    fn drop_leases_of(&mut self, id: JobId) {
        let held: Vec<LeaseId> = self.leases.iter().filter(|(_, l)| l.job == id).map(|(k, _)| *k).collect();
        for lease_id in held {
            if let Some(l) = self.leases.remove(&lease_id) {
                if let Some(w) = self.workers.get_mut(&l.worker) {
                    w.leases.remove(&lease_id);
                }
                if let Some(job) = self.jobs.get_mut(&l.job) {
                    job.leased = job.leased.saturating_sub(1);
                    if l.denoise.is_none() {
                        job.requeue(l.frame, l.unit);
                    }
                }
            }
        }
    }

    fn finish(&mut self, id: JobId, state: JobState, error: Option<String>, now_ms: u64) {
        self.drop_leases_of(id);
        self.changes.record(id);
        self.changes.outputs = true;
        if let Some(job) = self.jobs.get_mut(&id) {
            job.stop_clock(now_ms);
            job.state = state;
            job.finished_ms = Some(now_ms);
            job.error = error;
            // A single-frame job cancelled before it started has no film and no image.
            job.output_dirty = job.sequence || !job.open.is_empty();
            for run in job.open.values_mut() {
                run.drop_received();
            }
            if job.sequence && state != JobState::Completed {
                job.drop_open_frames();
            }
            let event = match state {
                JobState::Completed => Some(NotifyEvent::Completed),
                JobState::Failed => Some(NotifyEvent::Failed),
                JobState::Cancelled => Some(NotifyEvent::Cancelled),
                _ => None,
            };
            if let Some(event) = event
                && job.notify.as_ref().is_some_and(|n| n.wants(event))
            {
                self.notifications.push((id, event));
            }
        }
    }

    /// The server wrote frame `index` of a sequence (`frames/NNNN/image.exr` and `preview.png`):
    /// its film is dropped. Returns the frame number, or `None` if it was not waiting.
    pub fn frame_written(&mut self, id: JobId, index: usize) -> Option<i32> {
        let job = self.jobs.get_mut(&id)?;
        job.finishing.remove(&index)?;
        job.status[index].state = FrameState::Done;
        job.frames_done += 1;
        let frame = job.frames.frames()[index];
        self.changes.frames.push((id, frame));
        self.changes.progress(id);
        self.changes.work_ready = true; // the next frame may start
        job.log(format!("frame {frame} written ({} of {} done)", job.frames_done, job.frames.len()));
        Some(frame)
    }

    /// The server wrote the images of a finished single-frame job (`preview_ev`: the EV of its
    /// preview): unless something changed since the job ended (`output_dirty`), its film is
    /// dropped and its images are served from the files. Returns the job's `finished_ms` when
    /// it was dropped (for the final marker, [`crate::service::outputs::FINAL_MARKER`]).
    pub fn final_image_written(&mut self, id: JobId, preview_ev: Option<f32>) -> Option<u64> {
        let job = self.jobs.get_mut(&id)?;
        if job.sequence || !job.state.is_finished() || job.output_dirty || job.leased > 0 {
            return None;
        }
        job.open.clear();
        job.image_on_disk = Some(preview_ev);
        job.finished_ms
    }

    /// Sets the webhook of a job (right after submitting it).
    pub fn set_notify(&mut self, id: JobId, notify: Option<Notify>) -> Result<(), FarmError> {
        self.job_mut(id)?.notify = notify;
        self.changes.record(id);
        Ok(())
    }

    /// What changed since the last call, for the service to apply (persist, wake, publish).
    pub fn take_changes(&mut self) -> Changes {
        std::mem::take(&mut self.changes)
    }

    /// The webhook events queued since the last call, oldest first.
    pub fn take_notifications(&mut self) -> Vec<(JobId, NotifyEvent)> {
        std::mem::take(&mut self.notifications)
    }

    /// Appends a line to a job's log (no-op for a job that is gone).
    pub fn log_job(&mut self, id: JobId, line: String) {
        if let Some(job) = self.jobs.get_mut(&id) {
            job.log(line);
            self.changes.progress(id);
        }
    }

    pub fn cancel(&mut self, id: JobId, now_ms: u64) -> Result<(), FarmError> {
        let job = self.job(id)?;
        if job.state.is_finished() {
            return Err(FarmError::BadState { id, state: job.state.as_str(), action: "cancel" });
        }
        self.finish(id, JobState::Cancelled, None, now_ms);
        if let Some(job) = self.jobs.get_mut(&id) {
            job.log("cancelled".into());
        }
        Ok(())
    }

    /// Stops handing out the job's units; units in flight still merge.
    pub fn pause(&mut self, id: JobId, now_ms: u64) -> Result<(), FarmError> {
        let job = self.job_mut(id)?;
        if !matches!(job.state, JobState::Queued | JobState::Running) {
            return Err(FarmError::BadState { id, state: job.state.as_str(), action: "pause" });
        }
        job.stop_clock(now_ms);
        job.state = JobState::Paused;
        job.log("paused".into());
        self.changes.record(id);
        Ok(())
    }

    pub fn resume(&mut self, id: JobId, _now_ms: u64) -> Result<(), FarmError> {
        let job = self.job_mut(id)?;
        if job.state != JobState::Paused {
            return Err(FarmError::BadState { id, state: job.state.as_str(), action: "resume" });
        }
        job.state = if job.units_merged > 0 || job.leased > 0 { JobState::Running } else { JobState::Queued };
        if job.state == JobState::Running {
            job.started_ms = Some(_now_ms);
        }
        job.log("resumed".into());
        self.changes.record(id);
        self.changes.work_ready = true;
        Ok(())
    }

    pub fn set_priority(&mut self, id: JobId, priority: i32) -> Result<(), FarmError> {
        self.job_mut(id)?.priority = priority;
        self.changes.record(id);
        self.changes.work_ready = true;
        Ok(())
    }

    /// Removes a finished job.
    pub fn delete(&mut self, id: JobId) -> Result<Job, FarmError> {
        let job = self.job(id)?;
        if !job.state.is_finished() {
            return Err(FarmError::BadState { id, state: job.state.as_str(), action: "delete (cancel it first)" });
        }
        self.changes.removed.insert(id);
        self.jobs.remove(&id).ok_or(FarmError::NoJob(id))
    }

    /// Takes back a job that was just submitted but could not be saved, whatever its state (its
    /// leases, if a worker was quick, are dropped: their results will be refused).
    pub fn withdraw(&mut self, id: JobId) {
        let leases: Vec<LeaseId> = self.leases.iter().filter(|(_, l)| l.job == id).map(|(&k, _)| k).collect();
        for lease in leases {
            self.take_lease(lease);
        }
        self.jobs.remove(&id);
    }
}
