//! The farm's state machine: jobs, units, workers and leases, in one place.
//!
//! Pure and synchronous: every operation takes the current time in milliseconds, so tests drive a
//! manual clock. The HTTP layer holds a [`Farm`] behind a mutex and calls these methods.
//!
//! Job: queued -> running -> paused <-> running -> completed | failed | cancelled.
//! Unit: pending -> leased(lease) -> received -> merged; an expired or released lease sends the
//! unit back to pending. A result is accepted only from the lease that holds the unit, so each
//! unit is merged exactly once.
//!
//! Merge order: a tile folds pass p before pass p+1 (results that arrive early wait in
//! `waiting`), and a unit's BDPT splats fold into the film's radiance sums with the unit. The
//! film's radiance sums are exact integers, for which this order is not needed; its AOV means
//! (albedo, normal, depth) are bit-identical to a local render because of it (film.rs), and it
//! makes every progressive image a prefix of the final one (each pixel holds samples `[0, s)`).

use pathfarm_common::adaptive::{self, AdaptiveSettings, BlockMask};
use pathfarm_common::film::{Film, SplatBuffer, TileAccum};
use pathfarm_common::frames::FrameSet;
use pathfarm_common::job::{Limits, Plan, RenderSettings, TileRect, UnitKey};
use pathfarm_common::protocol::{
    FrameInfo, FrameOrder, FrameState, FramesSummary, JobId, JobInfo, JobState, LeaseGrant, LeaseId, Notify,
    NotifyEvent, UnitResultFrame, WorkerId, WorkerInfo, WorkerState,
};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

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
    /// Memory for the films of all jobs the farm holds (each `Film::bytes_for` its size); a job
    /// that does not fit is refused. `None`: unbounded.
    pub film_budget_bytes: Option<u64>,
    /// Frames of one frame-order job in progress at once, at most (the next frame starts when
    /// the frames in progress have no pending unit left and its film fits the budget).
    pub max_open_frames: usize,
}

impl Default for FarmConfig {
    fn default() -> Self {
        Self {
            lease_timeout_ms: 10_000,
            heartbeat_ms: 2_000,
            max_unit_failures: 3,
            blocklist_after: 2,
            limits: Limits::default(),
            film_budget_bytes: None,
            worker_prune_ms: Some(3_600_000),
            expiry_tick_ms: 250,
            max_open_frames: 2,
        }
    }
}

/// Why a tile's sums do not hold exactly `spp` samples per pixel (each sample adds weight 1 and
/// at most one hit), or `None`. A result claiming 1,000 samples for a 1-sample pass was merged.
/// With adaptive sampling, pixels in the converged blocks of `mask` must hold no sample.
fn sample_count_mismatch(accum: &TileAccum, spp: u32, mask: Option<&BlockMask>) -> Option<String> {
    let w = accum.rect.width();
    accum.sums.iter().enumerate().find_map(|(i, p)| {
        let (lx, ly) = (i as u32 % w, i as u32 / w);
        let expected = adaptive::expected_samples(mask, lx, ly, spp);
        (p.weight != expected || p.hits > expected).then(|| {
            let (x, y) = (accum.rect.x0 + lx, accum.rect.y0 + ly);
            let why = if expected == spp {
                format!("the pass has {spp} samples per pixel")
            } else {
                "its block has converged (adaptive sampling): it gets no samples".to_string()
            };
            format!("pixel ({x}, {y}) holds {:.3} samples and {:.3} hits; {why}", p.weight(), f64::from(p.hits))
        })
    })
}

/// Samples a tile's converged pixels will not get: per pixel in a converged block of `mask`,
/// the job's spp less the samples it holds (they stop changing once their block converged).
fn skipped_samples(
    mask: Option<&BlockMask>,
    sums: &[pathfarm_common::film::PixelSums],
    rect: TileRect,
    spp: u32,
) -> u64 {
    let Some(mask) = mask else { return 0 };
    let w = rect.width();
    sums.iter()
        .enumerate()
        .filter(|(i, _)| mask.pixel_converged(*i as u32 % w, *i as u32 / w))
        .map(|(_, p)| u64::from(spp.saturating_sub(p.weight)))
        .sum()
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
}

fn missing_secret() -> FarmError {
    FarmError::WrongWorker(format!(
        "missing {} header: send the worker_secret that POST /workers/register returned",
        pathfarm_common::protocol::WORKER_SECRET_HEADER
    ))
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum UnitState {
    Pending,
    Leased(LeaseId),
    /// Result held in `waiting` until the tile's earlier passes are merged.
    Received,
    Merged,
    /// Adaptive sampling: the tile's previous pass is not merged yet, so the blocks this unit
    /// samples are not known; it becomes pending when that pass merges.
    Blocked,
}

#[derive(Clone, Debug)]
struct Lease {
    job: JobId,
    /// Index of the unit's frame in the job's frame set.
    frame: usize,
    unit: usize,
    worker: WorkerId,
    deadline_ms: u64,
}

/// One frame whose film exists: its units (pass-major: `pass * tiles + tile`), merge state and
/// film. Frames not started have none of this; finished ones are written and dropped.
#[derive(Debug)]
pub struct FrameRun {
    units: Vec<UnitState>,
    /// Pending units before `cursor` are in `requeued`; at or after it, units are scanned.
    cursor: usize,
    pending: usize,
    requeued: BTreeSet<usize>,
    /// Per tile: the next pass to fold.
    next_pass: Vec<u32>,
    waiting: HashMap<usize, (TileAccum, Option<SplatBuffer>)>,
    /// Tiles merged, per pass.
    pass_merged: Vec<u32>,
    /// Adaptive sampling: per tile, the converged blocks after its last merged pass (`None`
    /// before the first, and for jobs without `adaptive`). A pure function of the film, so
    /// checkpoints do not hold it: restore computes it again.
    masks: Vec<Option<BlockMask>>,
    pub film: Film,
    pub passes_done: u32,
    units_merged: u64,
    /// Merged units since the last checkpoint snapshot.
    checkpoint_dirty: bool,
}

impl FrameRun {
    /// A frame with nothing merged. `adaptive`: only the first pass is pending; each tile's
    /// later passes wait for its previous one ([`UnitState::Blocked`]).
    fn new(plan: &Plan, width: u32, height: u32, adaptive: bool) -> Self {
        let units = plan.unit_count();
        let tiles = plan.tiles.len();
        let pending = if adaptive { tiles.min(units) } else { units };
        let mut states = vec![UnitState::Pending; units];
        states[pending..].fill(UnitState::Blocked);
        FrameRun {
            units: states,
            cursor: 0,
            pending,
            requeued: BTreeSet::new(),
            next_pass: vec![0; tiles],
            waiting: HashMap::new(),
            pass_merged: vec![0; plan.passes.len()],
            masks: vec![None; tiles],
            film: Film::new(width, height),
            passes_done: 0,
            units_merged: 0,
            checkpoint_dirty: true,
        }
    }

    /// The first pending unit in canonical order, without taking it.
    fn peek_pending(&mut self) -> Option<usize> {
        while self.cursor < self.units.len() && self.units[self.cursor] != UnitState::Pending {
            self.cursor += 1;
        }
        let scanned = (self.cursor < self.units.len()).then_some(self.cursor);
        match (self.requeued.first().copied(), scanned) {
            (Some(r), Some(s)) => Some(r.min(s)),
            (r, s) => r.or(s),
        }
    }

    /// The first pending unit in canonical order (returned units come first: they are earlier).
    fn take_pending(&mut self) -> Option<usize> {
        let i = self.peek_pending()?;
        if self.requeued.first() == Some(&i) {
            self.requeued.pop_first();
        } else {
            self.cursor = i + 1;
        }
        self.pending -= 1;
        Some(i)
    }

    fn requeue(&mut self, index: usize) {
        if self.units[index] != UnitState::Pending {
            self.units[index] = UnitState::Pending;
            self.pending += 1;
            if index < self.cursor {
                self.requeued.insert(index);
            }
        }
    }

    fn is_complete(&self) -> bool {
        self.units_merged == self.units.len() as u64
    }

    /// Adaptive sampling, once `tile` has merged its passes before `next_pass[tile]`: its
    /// converged blocks from the film's merged sums (exactly as `render_local` decides), then
    /// either its next pass becomes pending with the mask, or, when every block has converged,
    /// its remaining passes count as merged with nothing (the tile leaves the schedule).
    fn decide(&mut self, plan: &Plan, a: &AdaptiveSettings, spp: u32, tile: usize) -> Decision {
        let (tiles, passes) = (plan.tiles.len(), plan.passes.len());
        let np = self.next_pass[tile] as usize;
        let mut out = Decision::default();
        if np == 0 {
            return out;
        }
        let rect = plan.tiles[tile];
        let sums = self.film.tile(rect).sums;
        let mask = adaptive::converged_blocks(&sums, rect, a, plan.passes[np - 1].s1);
        let before = skipped_samples(self.masks[tile].as_ref(), &sums, rect, spp);
        out.samples_skipped = skipped_samples(Some(&mask), &sums, rect, spp).saturating_sub(before);
        let all = mask.all_converged();
        self.masks[tile] = Some(mask);
        if np >= passes {
            return out;
        }
        if all {
            for q in np..passes {
                let i = q * tiles + tile;
                if self.units[i] == UnitState::Pending {
                    self.pending -= 1;
                    self.requeued.remove(&i);
                }
                self.units[i] = UnitState::Merged;
                self.units_merged += 1;
                self.pass_merged[q] += 1;
                out.units_skipped += 1;
            }
            self.next_pass[tile] = passes as u32;
        } else if self.units[np * tiles + tile] == UnitState::Blocked {
            self.requeue(np * tiles + tile);
        }
        out
    }
}

/// What an adaptive decision for a tile changed.
#[derive(Clone, Copy, Debug, Default)]
struct Decision {
    /// Units (the tile's remaining passes) counted as merged because every block converged.
    units_skipped: u64,
    /// Samples that newly converged pixels will not get (taken off the job's total).
    samples_skipped: u64,
}

/// Per frame of the job, what is kept for every frame (8 bytes), started or not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FrameStatus {
    state: FrameState,
    passes_done: u32,
}

/// A job and its frames' units.
///
/// A job renders a frame set (one frame unless `frames` was given). Units are (frame, pass,
/// tile); only frames in progress hold a [`FrameRun`] (film and unit states), so memory grows
/// with the frames in progress, not with the frames in the job. A single-frame job (`sequence`
/// false) keeps its film after completion and writes `jobs/ID/image.exr`; a sequence's frame,
/// once every unit is merged, moves to `finishing` until the server has written
/// `jobs/ID/frames/NNNN/{image.exr,preview.png}` ([`Farm::frame_written`]), then its film is
/// dropped.
#[derive(Debug)]
pub struct Job {
    pub id: JobId,
    pub name: String,
    pub scene_id: String,
    pub priority: i32,
    pub settings: RenderSettings,
    /// The frames to render, in order.
    pub frames: FrameSet,
    /// `frames` was given: every frame is written under `frames/NNNN/`.
    pub sequence: bool,
    pub order: FrameOrder,
    /// Tags a worker must have (all of them) to be leased this job's units.
    pub requires: Vec<String>,
    /// Webhook called when the job reaches some states.
    pub notify: Option<Notify>,
    /// The `started` event was queued (once per job and coordinator run).
    started_notified: bool,
    /// Set while units are pending that no live worker may take (its tags lack some of
    /// `requires`): the reason, shown in the job's info and logged once.
    unservable: Option<String>,
    pub plan: Plan,
    pub state: JobState,
    status: Vec<FrameStatus>,
    /// Frames in progress, by index in `frames`.
    open: BTreeMap<usize, FrameRun>,
    /// Frames fully merged whose images are not written yet (sequences only).
    finishing: BTreeMap<usize, Arc<Film>>,
    /// Frames at or after this index may be pending; before it, none is.
    next_unopened: usize,
    /// Frames pending (not started).
    unstarted: usize,
    /// Frames fully merged (writing or done).
    frames_merged: u32,
    frames_done: u32,
    pub units_merged: u64,
    pub samples_done: u64,
    samples_total: u64,
    leased: u32,
    /// Units handed out so far (fair share among equal priorities).
    served: u64,
    unit_failures: HashMap<(usize, usize), u32>,
    worker_failures: HashMap<WorkerId, u32>,
    pub blocklist: BTreeSet<WorkerId>,
    pub created_ms: u64,
    started_ms: Option<u64>,
    /// Time spent running before the last pause.
    run_ms_before: u64,
    pub finished_ms: Option<u64>,
    pub error: Option<String>,
    /// Human-readable events (retries, failures, blocklists), newest last.
    pub log: Vec<String>,
    /// Output should be written (a pass completed, a frame finished or the job ended).
    pub output_dirty: bool,
}

/// Frames listed in a job's info (the rest: `GET /jobs/{id}/frames`).
const INFO_FRAMES: usize = 64;

impl Job {
    fn unit_key(&self, frame: usize, index: usize) -> UnitKey {
        let tiles = self.plan.tiles.len();
        UnitKey { frame: self.frames.frames()[frame], pass: (index / tiles) as u32, tile: (index % tiles) as u32 }
    }

    fn units_per_frame(&self) -> u64 {
        self.plan.unit_count() as u64
    }

    fn samples_per_frame(&self) -> u64 {
        u64::from(self.settings.width) * u64::from(self.settings.height) * u64::from(self.settings.spp)
    }

    fn has_pending(&self) -> bool {
        self.open.values().any(|f| f.pending > 0)
    }

    /// The next frame that may be started (frame order: only when no frame in progress has
    /// pending units left).
    fn frame_to_open(&mut self) -> Option<usize> {
        while self.next_unopened < self.status.len() && self.status[self.next_unopened].state != FrameState::Pending {
            self.next_unopened += 1;
        }
        (self.next_unopened < self.status.len()).then_some(self.next_unopened)
    }

    /// Pending work, started or not (for "is anything waiting for a worker").
    fn has_work(&self) -> bool {
        self.has_pending() || self.unstarted > 0
    }

    /// Films this job holds (frames in progress and frames being written).
    pub fn films_held(&self) -> u64 {
        (self.open.len() + self.finishing.len()) as u64
    }

    fn open_frame(&mut self, index: usize) {
        let run =
            FrameRun::new(&self.plan, self.settings.width, self.settings.height, self.settings.adaptive.is_some());
        self.open.insert(index, run);
        self.status[index].state = FrameState::Rendering;
        self.unstarted -= 1;
    }

    /// At submission (and restoration): a frame-order job starts its first frame (its film was
    /// admitted with the job) unless one is in progress; sequence preview starts every frame.
    fn open_initial_frames(&mut self) {
        match self.order {
            FrameOrder::SequencePreview => {
                while let Some(i) = self.frame_to_open() {
                    self.open_frame(i);
                }
            }
            FrameOrder::Frame => {
                if self.open.is_empty()
                    && let Some(i) = self.frame_to_open()
                {
                    self.open_frame(i);
                }
            }
        }
    }

    /// Every unit of frame `index` is merged: a sequence's frame waits to be written, a
    /// single-frame job keeps its film as the job's image.
    fn frame_merged(&mut self, index: usize) {
        self.frames_merged += 1;
        self.status[index].passes_done = self.plan.passes.len() as u32;
        if self.sequence {
            if let Some(run) = self.open.remove(&index) {
                self.finishing.insert(index, Arc::new(run.film));
            }
            self.status[index].state = FrameState::Writing;
            self.output_dirty = true;
        } else {
            self.status[index].state = FrameState::Done;
            self.frames_done += 1;
        }
    }

    /// A cancelled or failed sequence gives up its frames in progress (their films).
    fn drop_open_frames(&mut self) {
        let dropped = std::mem::take(&mut self.open);
        for (i, _) in dropped {
            self.status[i] = FrameStatus { state: FrameState::Pending, passes_done: 0 };
            self.unstarted += 1;
        }
        self.next_unopened = 0;
    }

    /// A page of the frame list: frames with index above `after`, at most `limit`.
    pub fn frames_page(&self, after: Option<u32>, limit: usize) -> Vec<FrameInfo> {
        let from = after.map_or(0, |a| a as usize + 1);
        (from..self.status.len()).take(limit).filter_map(|i| self.frame_info(i)).collect()
    }

    /// The next unit to hand out: frame order takes the first frame in progress with pending
    /// units; sequence preview takes the lowest (pass, frame) over every frame.
    fn take_unit(&mut self) -> Option<(usize, usize)> {
        let tiles = self.plan.tiles.len().max(1);
        let frame = match self.order {
            FrameOrder::Frame => self.open.iter().find(|(_, f)| f.pending > 0).map(|(&i, _)| i),
            FrameOrder::SequencePreview => self
                .open
                .iter_mut()
                .filter(|(_, f)| f.pending > 0)
                .filter_map(|(&i, f)| f.peek_pending().map(|u| (u / tiles, i)))
                .min()
                .map(|(_, i)| i),
        }?;
        let unit = self.open.get_mut(&frame)?.take_pending()?;
        Some((frame, unit))
    }

    fn requeue(&mut self, frame: usize, unit: usize) {
        if let Some(f) = self.open.get_mut(&frame) {
            f.requeue(unit);
        }
    }

    fn accepts_work(&self) -> bool {
        matches!(self.state, JobState::Queued | JobState::Running)
    }

    fn running_ms(&self, now_ms: u64) -> u64 {
        let current = match (self.state, self.started_ms) {
            (JobState::Running, Some(s)) => now_ms.saturating_sub(s),
            _ => 0,
        };
        self.run_ms_before + current
    }

    fn stop_clock(&mut self, now_ms: u64) {
        if let (JobState::Running, Some(s)) = (self.state, self.started_ms) {
            self.run_ms_before += now_ms.saturating_sub(s);
        }
        self.started_ms = None;
    }

    fn log(&mut self, line: String) {
        tracing::info!(job = self.id, "{line}");
        if self.log.len() < 10_000 {
            self.log.push(line);
        }
    }

    /// The film shown as "the job's image": a single-frame job's film; for a sequence, `None`
    /// (each frame has its own: [`Job::frame_film`]).
    pub fn film(&self) -> Option<&Film> {
        if self.sequence { None } else { self.open.values().next().map(|f| &f.film) }
    }

    /// Mutable access to a single-frame job's film (tests).
    #[cfg(test)]
    pub fn film_mut(&mut self) -> Option<&mut Film> {
        if self.sequence { None } else { self.open.values_mut().next().map(|f| &mut f.film) }
    }

    /// The film of frame number `frame` while it is held (rendering or being written).
    pub fn frame_film(&self, frame: i32) -> Option<FrameFilm<'_>> {
        let index = self.frame_index(frame)?;
        if let Some(run) = self.open.get(&index) {
            return Some(FrameFilm::Open(&run.film));
        }
        self.finishing.get(&index).map(|f| FrameFilm::Finishing(f.clone()))
    }

    /// Position of frame number `frame` in the frame set.
    pub fn frame_index(&self, frame: i32) -> Option<usize> {
        self.frames.frames().iter().position(|&f| f == frame)
    }

    /// Frame `index` of the set.
    pub fn frame_info(&self, index: usize) -> Option<FrameInfo> {
        let s = self.status.get(index)?;
        Some(FrameInfo {
            index: index as u32,
            frame: self.frames.frames()[index],
            state: s.state,
            passes_done: s.passes_done,
        })
    }

    /// Frames fully merged whose images are to be written: (index, frame number, film).
    pub fn frames_to_write(&self) -> Vec<(usize, i32, Arc<Film>)> {
        self.finishing.iter().map(|(&i, f)| (i, self.frames.frames()[i], f.clone())).collect()
    }

    /// Per tile, the passes merged (the tile progress map) of the first frame in progress
    /// (every pass when the job has none in progress and is completed).
    pub fn tile_passes(&self) -> Vec<u32> {
        match self.open.values().next() {
            Some(f) => f.next_pass.clone(),
            None if self.state == JobState::Completed => vec![self.plan.passes.len() as u32; self.plan.tiles.len()],
            None => vec![0; self.plan.tiles.len()],
        }
    }

    /// Passes merged for every tile of every frame.
    pub fn passes_done(&self) -> u32 {
        self.status.iter().map(|s| s.passes_done).min().unwrap_or(0)
    }

    pub fn frames_summary(&self) -> FramesSummary {
        FramesSummary {
            sequence: self.sequence,
            spec: self.frames.spec().to_string(),
            order: self.order,
            total: self.frames.len() as u32,
            done: self.frames_done,
            in_progress: self.films_held() as u32,
            current: self
                .open
                .keys()
                .chain(self.finishing.keys())
                .take(INFO_FRAMES)
                .filter_map(|&i| self.frame_info(i))
                .collect(),
        }
    }

    pub fn info(&self, now_ms: u64) -> JobInfo {
        let elapsed_ms = self.running_ms(now_ms);
        let secs = elapsed_ms as f64 / 1000.0;
        let rate = if secs > 0.0 { self.samples_done as f64 / secs } else { 0.0 };
        let left = self.samples_total.saturating_sub(self.samples_done) as f64;
        let eta = match self.state {
            JobState::Completed => Some(0.0),
            _ if rate > 0.0 && !self.state.is_finished() => Some(left / rate),
            _ => None,
        };
        let passes_done = self.passes_done();
        let spp_done = match passes_done {
            0 => 0,
            p => self.plan.passes.get(p as usize - 1).map_or(self.settings.spp, |p| p.s1),
        };
        let mut frames = self.frames_summary();
        frames.current.sort_by_key(|f| f.index);
        JobInfo {
            id: self.id,
            name: self.name.clone(),
            scene_id: self.scene_id.clone(),
            state: self.state,
            priority: self.priority,
            settings: self.settings.clone(),
            tiles: self.plan.tiles.len() as u32,
            passes_total: self.plan.passes.len() as u32,
            passes_done,
            units_total: self.units_per_frame() * self.frames.len() as u64,
            units_merged: self.units_merged,
            spp_done,
            samples_done: self.samples_done,
            samples_total: self.samples_total,
            progress: if self.samples_total > 0 { self.samples_done as f64 / self.samples_total as f64 } else { 1.0 },
            samples_per_sec: rate,
            eta_secs: eta,
            elapsed_secs: secs,
            created_ms: self.created_ms,
            finished_ms: self.finished_ms,
            error: self.error.clone(),
            blocklist: self.blocklist.iter().copied().collect(),
            requires: self.requires.clone(),
            waiting: self.unservable.clone(),
            frames,
        }
    }
}

/// A frame's film as the API reads it: borrowed while rendering, shared while being written.
pub enum FrameFilm<'a> {
    Open(&'a Film),
    Finishing(Arc<Film>),
}

impl std::ops::Deref for FrameFilm<'_> {
    type Target = Film;
    fn deref(&self) -> &Film {
        match self {
            FrameFilm::Open(f) => f,
            FrameFilm::Finishing(f) => f,
        }
    }
}

/// What a job is made of (the submit request and the store's row share it).
#[derive(Clone, Debug)]
pub struct JobSpec {
    pub scene_id: String,
    pub name: Option<String>,
    pub priority: i32,
    pub settings: RenderSettings,
    pub requires: Vec<String>,
    /// `None`: the one frame `settings.frame`, written as the job's image.
    pub frames: Option<FrameSet>,
    pub order: FrameOrder,
}

impl JobSpec {
    pub fn new(scene_id: String, settings: RenderSettings) -> Self {
        Self {
            scene_id,
            name: None,
            priority: 0,
            settings,
            requires: Vec::new(),
            frames: None,
            order: FrameOrder::Frame,
        }
    }
}

impl Job {
    fn new(id: JobId, spec: JobSpec, now_ms: u64) -> Self {
        let plan = spec.settings.plan();
        let sequence = spec.frames.is_some();
        let frames = spec.frames.unwrap_or_else(|| FrameSet::single(spec.settings.frame));
        let frame_count = frames.len();
        let samples_total = u64::from(spec.settings.width)
            * u64::from(spec.settings.height)
            * u64::from(spec.settings.spp)
            * frames.len() as u64;
        Job {
            id,
            name: spec.name.unwrap_or_else(|| format!("job {id}")),
            scene_id: spec.scene_id,
            priority: spec.priority,
            status: vec![FrameStatus { state: FrameState::Pending, passes_done: 0 }; frames.len()],
            frames,
            sequence,
            order: spec.order,
            open: BTreeMap::new(),
            finishing: BTreeMap::new(),
            next_unopened: 0,
            unstarted: frame_count,
            frames_merged: 0,
            frames_done: 0,
            plan,
            settings: spec.settings,
            requires: spec.requires,
            notify: None,
            started_notified: false,
            unservable: None,
            state: JobState::Queued,
            units_merged: 0,
            samples_done: 0,
            samples_total,
            leased: 0,
            served: 0,
            unit_failures: HashMap::new(),
            worker_failures: HashMap::new(),
            blocklist: BTreeSet::new(),
            created_ms: now_ms,
            started_ms: None,
            run_ms_before: 0,
            finished_ms: None,
            error: None,
            log: Vec::new(),
            output_dirty: false,
        }
    }

    /// For at most `limit` frames in progress that merged units since the last call: the film
    /// and merged set, for a checkpoint (`all`: every frame in progress). Each is a copy of a
    /// film: the caller takes one at a time to bound the memory.
    pub fn take_checkpoints(&mut self, all: bool, limit: usize) -> Vec<Checkpoint> {
        let (id, frames) = (self.id, self.frames.frames());
        self.open
            .iter_mut()
            .filter(|(_, f)| all || f.checkpoint_dirty)
            .take(limit)
            .map(|(&i, f)| {
                f.checkpoint_dirty = false;
                Checkpoint { job_id: id, frame: frames[i], next_pass: f.next_pass.clone(), film: f.film.clone() }
            })
            .collect()
    }

    /// What the store keeps of a job besides its checkpoints.
    pub fn record(&self, now_ms: u64) -> JobRecord {
        JobRecord {
            id: self.id,
            name: self.name.clone(),
            scene_id: self.scene_id.clone(),
            priority: self.priority,
            settings: self.settings.clone(),
            requires: self.requires.clone(),
            notify: self.notify.clone(),
            frames: self.sequence.then(|| self.frames.clone()),
            order: self.order,
            state: self.state,
            created_ms: self.created_ms,
            finished_ms: self.finished_ms,
            error: self.error.clone(),
            run_ms: self.running_ms(now_ms),
        }
    }
}

/// A job's durable fields (one SQLite row).
#[derive(Clone, Debug, PartialEq)]
pub struct JobRecord {
    pub id: JobId,
    pub name: String,
    pub scene_id: String,
    pub priority: i32,
    pub settings: RenderSettings,
    pub requires: Vec<String>,
    pub notify: Option<Notify>,
    pub frames: Option<FrameSet>,
    pub order: FrameOrder,
    pub state: JobState,
    pub created_ms: u64,
    pub finished_ms: Option<u64>,
    pub error: Option<String>,
    pub run_ms: u64,
}

/// A frame's merged sums and which units they hold. Because each tile folds its passes in
/// order, the merged set is one number per tile: the passes folded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Checkpoint {
    pub job_id: JobId,
    /// The frame number.
    pub frame: i32,
    pub next_pass: Vec<u32>,
    pub film: Film,
}

#[derive(Debug)]
struct Worker {
    /// Issued at registration; every lease, heartbeat, result and release of this worker must
    /// carry it. Empty: nothing authenticates as this worker (farms built in tests).
    secret: String,
    name: String,
    threads: u32,
    /// What it offers (registration); jobs' `requires` must be a subset.
    tags: BTreeSet<String>,
    leases: BTreeSet<LeaseId>,
    last_seen_ms: u64,
    registered_ms: u64,
    units_done: u64,
    samples_done: u64,
    offline: bool,
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
    /// Webhook events of jobs that asked for them, oldest first; the server drains them
    /// (`take_notifications`).
    notifications: Vec<(JobId, NotifyEvent)>,
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
            counters: Counters::default(),
            last_expire_ms: None,
            grace_until_ms: 0,
        }
    }

    /// Brings back a job from the store. `checkpoints`: the last checkpoint of each frame that
    /// had one; `done`: indices of the frames whose images were written (sequences). Units
    /// merged by a checkpoint stay merged, every other unit of the frame is pending again;
    /// frames without either start over.
    pub fn restore(
        &mut self,
        rec: JobRecord,
        checkpoints: Vec<Checkpoint>,
        done: &[usize],
        now_ms: u64,
    ) -> Result<(), String> {
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
        let tiles = job.plan.tiles.len();
        for cp in checkpoints {
            let index = job
                .frame_index(cp.frame)
                .ok_or_else(|| format!("checkpoint of job {} is for frame {}, not in its frames", rec.id, cp.frame))?;
            if job.status[index].state != FrameState::Pending {
                continue; // written already: the checkpoint is stale
            }
            if cp.job_id != rec.id
                || cp.next_pass.len() != tiles
                || (cp.film.width, cp.film.height) != (job.settings.width, job.settings.height)
                || cp.next_pass.iter().any(|&p| p > passes)
            {
                return Err(format!("checkpoint of job {} frame {} does not match its settings", rec.id, cp.frame));
            }
            job.open_frame(index);
            let Some(run) = job.open.get_mut(&index) else { continue };
            for (tile, &np) in cp.next_pass.iter().enumerate() {
                for pass in 0..np as usize {
                    let i = pass * tiles + tile;
                    if run.units[i] == UnitState::Pending {
                        run.pending -= 1;
                    }
                    run.units[i] = UnitState::Merged;
                    run.units_merged += 1;
                    run.pass_merged[pass] += 1;
                    job.units_merged += 1;
                }
                if job.settings.adaptive.is_none() {
                    job.samples_done += job.plan.tiles[tile].pixel_count() as u64
                        * u64::from(job.plan.passes.get(..np as usize).map_or(0, |p| p.iter().map(|p| p.spp()).sum()));
                } else {
                    // Converged pixels hold fewer samples than the passes: count what they hold.
                    job.samples_done +=
                        cp.film.tile(job.plan.tiles[tile]).sums.iter().map(|p| u64::from(p.weight)).sum::<u64>();
                }
            }
            run.next_pass = cp.next_pass;
            run.film = cp.film;
            // Adaptive: the masks are a pure function of the merged sums, so they are computed
            // again (not stored); each tile's next pass becomes pending, or the tile leaves.
            if let Some(a) = job.settings.adaptive {
                for tile in 0..tiles {
                    let d = run.decide(&job.plan, &a, job.settings.spp, tile);
                    job.units_merged += d.units_skipped;
                    job.samples_total = job.samples_total.saturating_sub(d.samples_skipped);
                }
            }
            while (run.passes_done as usize) < job.plan.passes.len()
                && run.pass_merged[run.passes_done as usize] == tiles as u32
            {
                run.passes_done += 1;
            }
            run.checkpoint_dirty = false;
            job.status[index].passes_done = run.passes_done;
            if run.is_complete() {
                job.frame_merged(index);
            }
        }
        // A single-frame job always has its film (empty without a checkpoint, as before frames).
        if !job.sequence && job.open.is_empty() && job.frames_merged == 0 {
            job.open_frame(0);
        }
        let total = job.frames.len() as u32;
        job.state = match rec.state {
            // A sequence recorded completed whose last frames were merged but not written (and
            // whose checkpoints were older) renders them again.
            JobState::Completed if job.sequence && job.frames_merged < total => {
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
        } else if !job.state.is_finished() {
            job.open_initial_frames();
        }
        if job.state == JobState::Completed && job.finished_ms.is_none() {
            job.finished_ms = Some(now_ms);
        }
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
        self.jobs.values().map(|j| j.films_held() * Film::bytes_for(j.settings.width, j.settings.height)).sum()
    }

    /// The farm's own budgets for a job whose settings are valid (`RenderSettings::validate`
    /// is the one check of the settings): frames, frames x tiles x passes within `max_units`,
    /// and the films within `--film-memory-mb`.
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
            let used = self.film_bytes_held();
            if used.saturating_add(need) > budget {
                let mib = |b: u64| b.div_ceil(1 << 20);
                let what = if films > 1 {
                    format!(
                        "order sequence_preview holds every frame's film at once: {films} frames x {} MiB = {} MiB \
                         ({}x{} pixels, 256 bytes each; order \"frame\" needs one film at a time)",
                        mib(film),
                        mib(need),
                        settings.width,
                        settings.height
                    )
                } else {
                    format!(
                        "the job's film needs {} MiB ({}x{} pixels, 256 bytes each)",
                        mib(need),
                        settings.width,
                        settings.height
                    )
                };
                return Err(FarmError::OverBudget(format!(
                    "{what}; {} MiB of the coordinator's film budget of {} MiB (--film-memory-mb) are held by {} jobs: \
                     delete finished jobs or lower the resolution",
                    mib(used),
                    mib(budget),
                    self.jobs.len()
                )));
            }
        }
        Ok(())
    }

    /// Adds a job: settings, tags, frames x tiles x passes and the film budget are checked
    /// before anything is allocated. A frame-order job needs one film to fit the budget (more
    /// frames start only while their films fit); a sequence-preview job needs every frame's.
    pub fn submit_job(&mut self, spec: JobSpec, now_ms: u64) -> Result<JobId, FarmError> {
        pathfarm_common::protocol::validate_tags(&spec.requires, "requires").map_err(FarmError::InvalidJob)?;
        spec.settings.validate(&self.cfg.limits).map_err(|e| FarmError::InvalidJob(e.to_string()))?;
        self.check_budgets(&spec)?;
        let id = self.next_job;
        self.next_job += 1;
        let mut job = Job::new(id, spec, now_ms);
        job.open_initial_frames();
        self.jobs.insert(id, job);
        self.note_unservable();
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
                    job.requeue(l.frame, l.unit);
                }
            }
        }
    }

    fn finish(&mut self, id: JobId, state: JobState, error: Option<String>, now_ms: u64) {
        self.drop_leases_of(id);
        if let Some(job) = self.jobs.get_mut(&id) {
            job.stop_clock(now_ms);
            job.state = state;
            job.finished_ms = Some(now_ms);
            job.error = error;
            job.output_dirty = true;
            for run in job.open.values_mut() {
                run.waiting.clear();
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
        job.log(format!("frame {frame} written ({} of {} done)", job.frames_done, job.frames.len()));
        Some(frame)
    }

    /// Sets the webhook of a job (right after submitting it).
    pub fn set_notify(&mut self, id: JobId, notify: Option<Notify>) -> Result<(), FarmError> {
        self.job_mut(id)?.notify = notify;
        Ok(())
    }

    /// The webhook events queued since the last call, oldest first.
    pub fn take_notifications(&mut self) -> Vec<(JobId, NotifyEvent)> {
        std::mem::take(&mut self.notifications)
    }

    /// Appends a line to a job's log (no-op for a job that is gone).
    pub fn log_job(&mut self, id: JobId, line: String) {
        if let Some(job) = self.jobs.get_mut(&id) {
            job.log(line);
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
        Ok(())
    }

    pub fn set_priority(&mut self, id: JobId, priority: i32) -> Result<(), FarmError> {
        self.job_mut(id)?.priority = priority;
        Ok(())
    }

    /// Removes a finished job.
    pub fn delete(&mut self, id: JobId) -> Result<Job, FarmError> {
        let job = self.job(id)?;
        if !job.state.is_finished() {
            return Err(FarmError::BadState { id, state: job.state.as_str(), action: "delete (cancel it first)" });
        }
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

    // ----------------------------------------------------------------- workers

    /// Registers a worker that no request can authenticate as (see [`Farm::register_with_secret`]).
    pub fn register(&mut self, name: String, threads: u32, now_ms: u64) -> WorkerId {
        self.register_with_secret(name, threads, String::new(), now_ms)
    }

    /// Registers a worker whose requests must carry `secret` (an empty one never matches).
    pub fn register_with_secret(&mut self, name: String, threads: u32, secret: String, now_ms: u64) -> WorkerId {
        self.register_tagged(name, threads, secret, Vec::new(), now_ms)
    }

    /// Registers a worker offering `tags` (validated by the caller).
    pub fn register_tagged(
        &mut self,
        name: String,
        threads: u32,
        secret: String,
        tags: Vec<String>,
        now_ms: u64,
    ) -> WorkerId {
        let id = self.next_worker;
        self.next_worker += 1;
        tracing::info!(worker = id, %name, threads, ?tags, "worker registered");
        self.workers.insert(
            id,
            Worker {
                secret,
                name,
                threads,
                tags: tags.into_iter().collect(),
                leases: BTreeSet::new(),
                last_seen_ms: now_ms,
                registered_ms: now_ms,
                units_done: 0,
                samples_done: 0,
                offline: false,
            },
        );
        self.note_unservable();
        id
    }

    /// Marks the jobs with pending units whose `requires` no live (not offline) worker meets,
    /// logging once when a job becomes unservable, and clears the mark of the others. Runs
    /// when jobs or workers come and go (submit, registration, `expire`, pruning).
    pub fn note_unservable(&mut self) {
        let workers = &self.workers;
        for job in self.jobs.values_mut() {
            let stuck = !job.requires.is_empty()
                && job.accepts_work()
                && job.has_work()
                && !workers.values().any(|w| !w.offline && job.requires.iter().all(|t| w.tags.contains(t)));
            match (stuck, job.unservable.is_some()) {
                (true, false) => {
                    let why = format!("no live worker has tags [{}]", job.requires.join(", "));
                    job.log(format!("waiting: {why}"));
                    job.unservable = Some(why);
                }
                (false, true) => {
                    job.unservable = None;
                    if job.accepts_work() && job.has_work() {
                        job.log("a live worker has the required tags now".into());
                    }
                }
                _ => {}
            }
        }
    }

    /// Checks that `secret` is worker `worker`'s own: `NoWorker` if it is not registered,
    /// `WrongWorker` if the secret is missing or another's (compared in constant time).
    pub fn check_worker(&self, worker: WorkerId, secret: Option<&str>) -> Result<(), FarmError> {
        let w = self.workers.get(&worker).ok_or(FarmError::NoWorker(worker))?;
        match secret {
            Some(s) if crate::farm::token_matches(s, &w.secret) => Ok(()),
            Some(_) => Err(FarmError::WrongWorker(format!(
                "the worker secret is not worker {worker}'s: a worker may only act for itself"
            ))),
            None => Err(missing_secret()),
        }
    }

    /// Checks that lease `lease_id` is held and that `secret` belongs to the worker holding it:
    /// `LeaseLost` if it is not held, `WrongWorker` if the secret is missing or another's.
    pub fn check_lease(&self, lease_id: LeaseId, secret: Option<&str>) -> Result<(), FarmError> {
        let secret = secret.ok_or_else(missing_secret)?;
        let l = self.leases.get(&lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
        match self.workers.get(&l.worker) {
            Some(w) if crate::farm::token_matches(secret, &w.secret) => Ok(()),
            _ => Err(FarmError::WrongWorker(format!(
                "lease {lease_id} is held by another worker: only the worker it was granted to may deliver, \
                 release or renew it"
            ))),
        }
    }

    /// Marks the worker alive and extends its leases.
    pub fn heartbeat(&mut self, worker: WorkerId, now_ms: u64) -> Result<(), FarmError> {
        let w = self.workers.get_mut(&worker).ok_or(FarmError::NoWorker(worker))?;
        w.last_seen_ms = now_ms;
        w.offline = false;
        let deadline = now_ms + self.cfg.lease_timeout_ms;
        for id in &w.leases {
            if let Some(l) = self.leases.get_mut(id) {
                l.deadline_ms = deadline;
            }
        }
        Ok(())
    }

    /// Forgets workers that have not been seen for longer than `worker_prune_ms` and hold no
    /// lease; returns their ids (the store deletes their rows). A pruned worker that comes back
    /// gets 404 and registers again.
    pub fn prune_workers(&mut self, now_ms: u64) -> Vec<WorkerId> {
        let Some(after) = self.cfg.worker_prune_ms else { return Vec::new() };
        if now_ms < self.grace_until_ms {
            return Vec::new();
        }
        let gone: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.leases.is_empty() && now_ms.saturating_sub(w.last_seen_ms) > after)
            .map(|(id, _)| *id)
            .collect();
        for id in &gone {
            if let Some(w) = self.workers.remove(id) {
                tracing::info!(worker = id, name = %w.name, last_seen_ms = w.last_seen_ms, "offline worker pruned");
            }
        }
        if !gone.is_empty() {
            self.note_unservable();
        }
        gone
    }

    pub fn workers(&self, now_ms: u64) -> Vec<WorkerInfo> {
        self.workers
            .iter()
            .map(|(&id, w)| {
                let current = w
                    .leases
                    .iter()
                    .next()
                    .and_then(|l| self.leases.get(l))
                    .and_then(|l| self.jobs.get(&l.job).map(|j| (l.job, j.unit_key(l.frame, l.unit))));
                let secs = now_ms.saturating_sub(w.registered_ms) as f64 / 1000.0;
                WorkerInfo {
                    id,
                    name: w.name.clone(),
                    threads: w.threads,
                    state: if w.offline {
                        WorkerState::Offline
                    } else if w.leases.is_empty() {
                        WorkerState::Idle
                    } else {
                        WorkerState::Busy
                    },
                    current,
                    units_done: w.units_done,
                    samples_done: w.samples_done,
                    samples_per_sec: if secs > 0.0 { w.samples_done as f64 / secs } else { 0.0 },
                    last_seen_ms: w.last_seen_ms,
                    tags: w.tags.iter().cloned().collect(),
                }
            })
            .collect()
    }

    // ----------------------------------------------------------------- leases

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
        let tags = &self.workers[&worker].tags;
        // A frame-order sequence whose frames in progress have nothing pending may start its
        // next frame, while the frames it holds are under the cap and the new film fits.
        let (budget, max_open) = (self.cfg.film_budget_bytes, self.cfg.max_open_frames.max(1) as u64);
        let mut held: Option<u64> = None;
        let jobs = &self.jobs;
        let mut may_start = |j: &Job| {
            j.order == FrameOrder::Frame
                && j.unstarted > 0
                && j.films_held() < max_open
                && budget.is_none_or(|b| {
                    let used = *held.get_or_insert_with(|| {
                        jobs.values()
                            .map(|j| j.films_held() * Film::bytes_for(j.settings.width, j.settings.height))
                            .sum()
                    });
                    used.saturating_add(Film::bytes_for(j.settings.width, j.settings.height)) <= b
                })
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
        if !job.has_pending()
            && let Some(next) = job.frame_to_open()
        {
            job.open_frame(next);
            job.log(format!("frame {} started", job.frames.frames()[next]));
        }
        let Some((frame, unit)) = job.take_unit() else { return Ok(None) };
        if let Some(run) = job.open.get_mut(&frame) {
            run.units[unit] = UnitState::Leased(lease_id);
        }
        job.leased += 1;
        job.served += 1;
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            job.started_ms = Some(now_ms);
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
        let mask = job.open.get(&frame).and_then(|run| run.masks[key.tile as usize].clone()).filter(|m| !m.none());
        let grant = LeaseGrant {
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
            Lease { job: job_id, frame, unit, worker, deadline_ms: now_ms + self.cfg.lease_timeout_ms },
        );
        if let Some(w) = self.workers.get_mut(&worker) {
            w.leases.insert(lease_id);
        }
        self.counters.units_leased += 1;
        Ok(Some(grant))
    }

    fn take_lease(&mut self, lease_id: LeaseId) -> Option<Lease> {
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
                if let Some(job) = self.jobs.get_mut(&l.job) {
                    job.requeue(l.frame, l.unit);
                    let key = job.unit_key(l.frame, l.unit);
                    job.log(format!(
                        "lease {id} of worker {} expired: unit frame {} pass {} tile {} is pending again",
                        l.worker, key.frame, key.pass, key.tile
                    ));
                }
                self.counters.leases_expired += 1;
            }
        }
        if now_ms >= self.grace_until_ms {
            for w in self.workers.values_mut() {
                if now_ms.saturating_sub(w.last_seen_ms) > self.cfg.lease_timeout_ms {
                    w.offline = true;
                }
            }
        }
        self.note_unservable();
        expired.len()
    }

    /// A worker gives a unit back: on shutdown (`failed = false`) or because rendering failed.
    pub fn release(&mut self, lease_id: LeaseId, failed: bool, reason: &str, now_ms: u64) -> Result<(), FarmError> {
        let l = self.take_lease(lease_id).ok_or(FarmError::LeaseLost(lease_id))?;
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

    /// Accepts a unit's result from the worker holding its lease and merges it.
    pub fn accept(
        &mut self,
        lease_id: LeaseId,
        frame: UnitResultFrame,
        now_ms: u64,
    ) -> Result<MergeOutcome, FarmError> {
        let l = self.leases.get(&lease_id).ok_or(FarmError::LeaseLost(lease_id))?.clone();
        let job = self.jobs.get(&l.job).ok_or(FarmError::LeaseLost(lease_id))?;
        if !job.open.contains_key(&l.frame) {
            return Err(FarmError::LeaseLost(lease_id));
        }
        let key = job.unit_key(l.frame, l.unit);
        let rect = job.plan.tiles[key.tile as usize];
        let mismatch = if frame.lease_id != lease_id {
            Some(format!("frame is for lease {}", frame.lease_id))
        } else if frame.job_id != l.job || frame.unit != key {
            Some(format!(
                "frame is for job {} unit {:?}, lease holds job {} unit {key:?}",
                frame.job_id, frame.unit, l.job
            ))
        } else if frame.accum.rect != rect {
            Some(format!("tile {:?}, expected {rect:?}", frame.accum.rect))
        } else if frame
            .splats
            .as_ref()
            .is_some_and(|s| (s.width, s.height) != (job.settings.width, job.settings.height))
        {
            Some("splat buffer size differs from the image".into())
        } else {
            let mask = job.open.get(&l.frame).and_then(|run| run.masks[key.tile as usize].as_ref());
            sample_count_mismatch(&frame.accum, job.plan.passes[key.pass as usize].spp(), mask)
        };
        if let Some(reason) = mismatch {
            // The worker holds the lease but sent something else: give the unit to someone else.
            self.counters.results_rejected += 1;
            self.take_lease(lease_id);
            if let Some(job) = self.jobs.get_mut(&l.job) {
                job.requeue(l.frame, l.unit);
                job.log(format!("refused a result of worker {}: {reason}", l.worker));
            }
            return Err(FarmError::ResultMismatch { lease: lease_id, reason });
        }
        // Samples the unit holds (converged pixels of an adaptive tile hold none).
        let unit_samples = |accum: &TileAccum| accum.sums.iter().map(|p| u64::from(p.weight)).sum::<u64>();
        let rendered = unit_samples(&frame.accum);
        self.take_lease(lease_id);
        if let Some(w) = self.workers.get_mut(&l.worker) {
            w.units_done += 1;
            w.samples_done += rendered;
            w.last_seen_ms = now_ms;
        }
        let Some(job) = self.jobs.get_mut(&l.job) else { return Err(FarmError::LeaseLost(lease_id)) };
        let Some(run) = job.open.get_mut(&l.frame) else { return Err(FarmError::LeaseLost(lease_id)) };
        run.units[l.unit] = UnitState::Received;
        run.waiting.insert(l.unit, (frame.accum, frame.splats));
        run.checkpoint_dirty = true;
        let mut out = MergeOutcome::default();
        let tile = key.tile as usize;
        let tiles = job.plan.tiles.len();
        loop {
            let next = run.next_pass[tile];
            if next as usize >= job.plan.passes.len() {
                break;
            }
            let index = next as usize * tiles + tile;
            let Some((accum, splats)) = run.waiting.remove(&index) else { break };
            run.film.add_tile(&accum);
            if let Some(s) = splats {
                run.film.add_splats(&s);
            }
            run.units[index] = UnitState::Merged;
            run.next_pass[tile] += 1;
            run.units_merged += 1;
            job.units_merged += 1;
            let samples = unit_samples(&accum);
            job.samples_done += samples;
            self.counters.units_merged += 1;
            self.counters.samples_merged += samples;
            out.folded += 1;
            run.pass_merged[next as usize] += 1;
            if let Some(a) = &job.settings.adaptive {
                let d = run.decide(&job.plan, a, job.settings.spp, tile);
                job.units_merged += d.units_skipped;
                job.samples_total = job.samples_total.saturating_sub(d.samples_skipped);
            }
        }
        // Passes complete in order, because every tile folds its passes in order.
        while (run.passes_done as usize) < job.plan.passes.len()
            && run.pass_merged[run.passes_done as usize] == tiles as u32
        {
            let p = run.passes_done;
            run.passes_done += 1;
            if !job.sequence {
                job.output_dirty = true;
            }
            out.passes_completed.push(p);
        }
        job.status[l.frame].passes_done = run.passes_done;
        if run.is_complete() {
            job.frame_merged(l.frame);
            out.frames_completed.push(key.frame);
            if job.sequence {
                job.log(format!("frame {} merged", key.frame));
            }
        }
        if job.frames_merged as usize == job.frames.len() {
            let id = job.id;
            if job.settings.denoise {
                // The farm does not schedule the denoise step yet (issue 14, second part).
                job.log(
                    "denoise was asked for, but this coordinator does not schedule denoise steps yet: finished \
                     without the denoised layer (render locally with `pathfarm-worker render --denoise`)"
                        .into(),
                );
            }
            job.log("completed".into());
            self.finish(id, JobState::Completed, None, now_ms);
            out.job_completed = true;
        }
        Ok(out)
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

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_common::film::SampleValue;
    use pathfarm_common::job::PassSchedule;

    fn settings() -> RenderSettings {
        let mut s = RenderSettings::new(20, 12, 7);
        s.tile_size = 8;
        s.passes = PassSchedule::Doubling { first: 1, max: 4 };
        s
    }

    /// A fake render: every sample of every pixel adds (x, y, pass) so the result depends on the unit.
    fn fake_result(g: &LeaseGrant) -> UnitResultFrame {
        let mut accum = TileAccum::new(g.tile);
        for y in g.tile.y0..g.tile.y1 {
            for x in g.tile.x0..g.tile.x1 {
                for s in g.pass.samples() {
                    let v = SampleValue { radiance: [x as f32, y as f32, s as f32], ..Default::default() };
                    pathfarm_common::film::add_sample(accum.pixel_mut(x - g.tile.x0, y - g.tile.y0), &v);
                }
            }
        }
        UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None }
    }

    fn reference_film(s: &RenderSettings) -> Film {
        let plan = s.plan();
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        for _ in 0..plan.unit_count() {
            let g = farm.lease(w, 0).expect("lease").expect("work");
            farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
        }
        assert_eq!(farm.job(id).expect("job").state, JobState::Completed);
        farm.job(id).expect("job").film().expect("film").clone()
    }

    fn sequence(frames: &str, order: FrameOrder) -> JobSpec {
        JobSpec {
            frames: Some(FrameSet::parse(frames).expect("frames")),
            order,
            ..JobSpec::new("x".into(), settings())
        }
    }

    /// Frame order: a frame's units go out before the next frame's, the next frame starts only
    /// when the frames in progress have nothing pending, at most `max_open_frames` are held at
    /// once; grants carry the unit's frame; every frame's film equals a single-frame job's;
    /// a written frame's film is dropped.
    #[test]
    fn frame_order_bounds_the_frames_in_progress() {
        let s = settings();
        let reference = reference_film(&s);
        let per_frame = s.plan().unit_count();
        let mut farm = Farm::new(FarmConfig { max_open_frames: 2, ..FarmConfig::default() });
        let id = farm.submit_job(sequence("10-14", FrameOrder::Frame), 0).expect("submit");
        assert_eq!(farm.job(id).expect("job").films_held(), 1, "the first frame starts with the job");
        let w = farm.register("w".into(), 1, 0);
        let mut grants = Vec::new();
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            assert_eq!(g.settings.frame, g.unit.frame);
            grants.push(g);
        }
        // Two frames in progress, nothing returned: the third does not start.
        assert_eq!(grants.len(), 2 * per_frame);
        assert!(grants[..per_frame].iter().all(|g| g.unit.frame == 10));
        assert!(grants[per_frame..].iter().all(|g| g.unit.frame == 11));
        let info = farm.job(id).expect("job").info(0);
        assert_eq!((info.frames.total, info.frames.in_progress, info.frames.done), (5, 2, 0));
        assert_eq!(info.units_total, 5 * per_frame as u64);
        // Frame 10 merges: it waits to be written (still holding its film) and nothing starts.
        for g in &grants[..per_frame] {
            let out = farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
            assert!(!out.job_completed);
        }
        assert_eq!(farm.lease(w, 0).expect("lease"), None, "two films are held");
        let to_write = farm.job(id).expect("job").frames_to_write();
        assert_eq!(to_write.len(), 1);
        assert_eq!((to_write[0].1, &*to_write[0].2), (10, &reference));
        assert_eq!(farm.job(id).expect("job").frame_info(0).map(|f| f.state), Some(FrameState::Writing));
        assert_eq!(farm.frame_written(id, to_write[0].0), Some(10));
        assert_eq!(farm.frame_written(id, to_write[0].0), None, "once");
        assert_eq!(farm.job(id).expect("job").frame_info(0).map(|f| f.state), Some(FrameState::Done));
        // Room again: frame 12 starts.
        let g = farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(g.unit.frame, 12);
        grants = grants[per_frame..].to_vec();
        grants.push(g);
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            grants.push(g);
        }
        // Deliver everything, writing frames as they finish; the job completes with the last.
        let mut completed = false;
        while !completed {
            for g in std::mem::take(&mut grants) {
                completed |= farm.accept(g.lease_id, fake_result(&g), 0).expect("accept").job_completed;
            }
            for (i, frame, film) in farm.job(id).expect("job").frames_to_write() {
                assert_eq!(*film, reference, "frame {frame}");
                farm.frame_written(id, i);
            }
            while let Some(g) = farm.lease(w, 0).expect("lease") {
                assert!(farm.job(id).expect("job").films_held() <= 2);
                grants.push(g);
            }
        }
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        assert_eq!(job.films_held(), 0);
        assert_eq!(
            job.frames_page(None, 10).iter().map(|f| (f.frame, f.state)).collect::<Vec<_>>(),
            (10..15).map(|f| (f, FrameState::Done)).collect::<Vec<_>>()
        );
        assert_eq!(job.frames_page(Some(2), 10).first().map(|f| f.frame), Some(13));
        assert_eq!(job.info(0).passes_done, s.plan().passes.len() as u32);
    }

    /// Sequence preview: every frame's first pass is handed out before any frame's second.
    #[test]
    fn sequence_preview_hands_out_passes_across_frames() {
        let s = settings();
        let (tiles, passes) = (s.plan().tiles.len(), s.plan().passes.len());
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit_job(sequence("1-3", FrameOrder::SequencePreview), 0).expect("submit");
        assert_eq!(farm.job(id).expect("job").films_held(), 3);
        let w = farm.register("w".into(), 1, 0);
        let mut keys = Vec::new();
        let mut first = None;
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            keys.push(g.unit);
            // A result comes back now and then, out of order: requeues keep the order too.
            if keys.len() == 5 {
                first = Some(g);
            }
        }
        assert_eq!(keys.len(), 3 * tiles * passes);
        let order: Vec<(u32, i32)> = keys.iter().map(|k| (k.pass, k.frame)).collect();
        let mut sorted = order.clone();
        sorted.sort();
        assert_eq!(order, sorted, "pass-major, then frame");
        // An expired unit of pass 0 goes out before anything else pending.
        let g = first.expect("fifth grant");
        farm.release(g.lease_id, false, "shutdown", 0).expect("release");
        assert_eq!(farm.lease(w, 0).expect("lease").map(|g| g.unit), Some(g.unit));
        let _ = id;
    }

    /// Budgets and limits are checked before anything is allocated, with messages that say why.
    #[test]
    fn sequences_are_checked_against_budgets() {
        let s = settings();
        let film = Film::bytes_for(s.width, s.height);
        let units = s.plan().unit_count() as u64;
        let mut farm = Farm::new(FarmConfig { film_budget_bytes: Some(film * 2), ..FarmConfig::default() });
        // Frame order needs one film at a time: 100 frames fit a two-film budget.
        let id = farm.submit_job(sequence("1-100", FrameOrder::Frame), 0).expect("frame order fits");
        match farm.submit_job(sequence("1-3", FrameOrder::SequencePreview), 0) {
            Err(FarmError::OverBudget(m)) => {
                assert!(m.contains("sequence_preview holds every frame's film at once: 3 frames"), "{m}")
            }
            r => panic!("admitted: {r:?}"),
        }
        // The sequence holds one film; a second frame starts only while it fits.
        let w = farm.register("w".into(), 1, 0);
        let mut n = 0;
        while farm.lease(w, 0).expect("lease").is_some() {
            n += 1;
        }
        assert_eq!(n as u64, 2 * units, "two frames fit the budget");
        let mut small = Farm::new(FarmConfig {
            limits: Limits { max_units: units * 10, ..Limits::default() },
            ..FarmConfig::default()
        });
        small.submit_job(sequence("1-10", FrameOrder::Frame), 0).expect("10 frames fit");
        match small.submit_job(sequence("1-11", FrameOrder::Frame), 0) {
            Err(FarmError::InvalidJob(m)) => {
                assert!(m.contains("units (frames x tiles x passes)") && m.contains("11 x"), "{m}")
            }
            r => panic!("admitted: {r:?}"),
        }
        let _ = id;
    }

    /// A restored sequence keeps its written frames and resumes its frame in progress from its
    /// checkpoint; the result equals an uninterrupted render.
    #[test]
    fn a_restored_sequence_resumes_its_frames() {
        let s = settings();
        let reference = reference_film(&s);
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit_job(sequence("1-3", FrameOrder::Frame), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let per_frame = s.plan().unit_count();
        // Frame 1 completes and is written; frame 2 merges a few units.
        for _ in 0..per_frame + 5 {
            let g = farm.lease(w, 0).expect("lease").expect("work");
            farm.accept(g.lease_id, fake_result(&g), 0).expect("accept");
        }
        for (i, _, _) in farm.job(id).expect("job").frames_to_write() {
            farm.frame_written(id, i);
        }
        let cps = farm.job_mut(id).expect("job").take_checkpoints(true, usize::MAX);
        assert_eq!(cps.iter().map(|c| c.frame).collect::<Vec<_>>(), vec![2]);
        assert!(farm.job_mut(id).expect("job").take_checkpoints(false, 1).is_empty(), "nothing merged since");
        let rec = farm.job(id).expect("job").record(0);
        let mut again = Farm::new(FarmConfig::default());
        again.restore(rec, cps, &[0], 0).expect("restore");
        let job = again.job(id).expect("job");
        assert_eq!(job.units_merged, per_frame as u64 + 5);
        assert_eq!(job.frame_info(0).map(|f| f.state), Some(FrameState::Done));
        assert_eq!(job.frame_info(1).map(|f| f.state), Some(FrameState::Rendering));
        let w = again.register("w".into(), 1, 0);
        let mut done = false;
        while !done {
            let Some(g) = again.lease(w, 0).expect("lease") else {
                for (i, frame, film) in again.job(id).expect("job").frames_to_write() {
                    assert_eq!(*film, reference, "frame {frame}");
                    again.frame_written(id, i);
                }
                continue;
            };
            assert_ne!(g.unit.frame, 1, "frame 1 is written");
            done = again.accept(g.lease_id, fake_result(&g), 0).expect("accept").job_completed;
        }
        assert_eq!(again.job(id).expect("job").units_merged, 3 * per_frame as u64);
        // A checkpoint of another job, or of a frame not in the set, is refused.
        let mut bad = farm.job_mut(id).expect("job").take_checkpoints(true, 1);
        bad[0].frame = 9;
        let rec = farm.job(id).expect("job").record(0);
        assert!(Farm::new(FarmConfig::default()).restore(rec, bad, &[], 0).is_err());
    }

    /// Webhook events are queued once, only for the events a job asked for, in order.
    #[test]
    fn notifications_are_queued_for_the_events_asked_for() {
        let mut farm = Farm::new(FarmConfig::default());
        let hooked = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let url = "https://example.com/h".to_string();
        let events = vec![NotifyEvent::Started, NotifyEvent::Completed, NotifyEvent::Cancelled];
        farm.set_notify(hooked, Some(Notify { url, events })).expect("notify");
        let quiet = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let first = farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(first.job_id, hooked);
        farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(farm.take_notifications(), vec![(hooked, NotifyEvent::Started)]);
        assert!(farm.take_notifications().is_empty(), "drained");
        farm.pause(hooked, 1).expect("pause");
        farm.resume(hooked, 2).expect("resume");
        while farm.lease(w, 3).expect("lease").is_some() {}
        farm.cancel(quiet, 4).expect("cancel");
        farm.cancel(hooked, 4).expect("cancel");
        // Started is not sent again after a resume; the job without notify sends nothing.
        assert_eq!(farm.take_notifications(), vec![(hooked, NotifyEvent::Cancelled)]);
        farm.log_job(hooked, "notified cancelled: 200".into());
        assert_eq!(farm.job(hooked).expect("job").log.last().map(String::as_str), Some("notified cancelled: 200"));
    }

    #[test]
    fn out_of_order_results_merge_to_the_same_film() {
        let s = settings();
        let reference = reference_film(&s);
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let mut grants = Vec::new();
        while let Some(g) = farm.lease(w, 0).expect("lease") {
            grants.push(g);
        }
        assert_eq!(grants.len(), s.plan().unit_count());
        // Deliver in reverse: everything waits until pass 0 of each tile arrives.
        grants.reverse();
        let mut completed = Vec::new();
        for g in &grants {
            let out = farm.accept(g.lease_id, fake_result(g), 0).expect("accept");
            completed.extend(out.passes_completed);
        }
        assert_eq!(completed, (0..s.plan().passes.len() as u32).collect::<Vec<_>>());
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        assert_eq!(job.film(), Some(&reference));
    }

    /// A result claiming more samples than its pass (1,000 for 1: R = 1000 was merged) or
    /// fewer is refused and its unit handed out again; the honest result then merges.
    #[test]
    fn results_with_the_wrong_sample_count_are_refused() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig::default());
        farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let g = farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(g.pass.spp(), 1);
        let mut inflated = fake_result(&g);
        let v = SampleValue { radiance: [1.0; 3], ..Default::default() };
        for _ in 0..999 {
            pathfarm_common::film::add_sample(inflated.accum.pixel_mut(0, 0), &v);
        }
        match farm.accept(g.lease_id, inflated, 0) {
            Err(FarmError::ResultMismatch { reason, .. }) => {
                assert!(reason.contains("1000.000 samples") && reason.contains("1 samples per pixel"), "{reason}")
            }
            r => panic!("accepted: {r:?}"),
        }
        let mut empty = fake_result(&g);
        empty.accum = TileAccum::new(g.tile);
        let g = farm.lease(w, 0).expect("lease").expect("requeued");
        empty.lease_id = g.lease_id;
        assert!(matches!(farm.accept(g.lease_id, empty, 0), Err(FarmError::ResultMismatch { .. })));
        let g = farm.lease(w, 0).expect("lease").expect("requeued again");
        farm.accept(g.lease_id, fake_result(&g), 0).expect("the honest result merges");
    }

    #[test]
    fn duplicate_and_expired_results_are_refused() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, ..FarmConfig::default() });
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.accept(g.lease_id, fake_result(&g), 10).expect("first");
        assert_eq!(farm.accept(g.lease_id, fake_result(&g), 10), Err(FarmError::LeaseLost(g.lease_id)));
        // A lease renewed by heartbeats survives; an abandoned one expires.
        let g2 = farm.lease(w, 20).expect("lease").expect("work");
        farm.heartbeat(w, 90).expect("hb");
        assert_eq!(farm.expire(150), 0);
        assert_eq!(farm.expire(191), 1);
        assert_eq!(farm.accept(g2.lease_id, fake_result(&g2), 200), Err(FarmError::LeaseLost(g2.lease_id)));
        // The unit is handed out again, first, and merges once.
        let w2 = farm.register("w2".into(), 1, 200);
        let g3 = farm.lease(w2, 200).expect("lease").expect("work");
        assert_eq!((g3.unit, g3.tile), (g2.unit, g2.tile));
        farm.accept(g3.lease_id, fake_result(&g3), 200).expect("accept");
        assert_eq!(farm.job(id).expect("job").units_merged, 2);
    }

    #[test]
    fn leases_and_workers_are_bound_to_their_secret() {
        let mut farm = Farm::new(FarmConfig::default());
        farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let a = farm.register_with_secret("a".into(), 1, "secret-a".into(), 0);
        let b = farm.register_with_secret("b".into(), 1, "secret-b".into(), 0);
        let nobody = farm.register("n".into(), 1, 0);
        let g = farm.lease(a, 0).expect("lease").expect("work");
        assert_eq!(farm.check_lease(g.lease_id, Some("secret-a")), Ok(()));
        for bad in [Some("secret-b"), Some(""), Some("secret-"), None] {
            assert!(matches!(farm.check_lease(g.lease_id, bad), Err(FarmError::WrongWorker(_))), "{bad:?}");
            assert!(matches!(farm.check_worker(a, bad), Err(FarmError::WrongWorker(_))), "{bad:?}");
        }
        assert_eq!(farm.check_worker(a, Some("secret-a")), Ok(()));
        assert_eq!(farm.check_worker(b, Some("secret-b")), Ok(()));
        assert!(matches!(farm.check_worker(nobody, Some("")), Err(FarmError::WrongWorker(_))));
        assert_eq!(farm.check_worker(999, Some("secret-a")), Err(FarmError::NoWorker(999)));
        assert_eq!(farm.check_lease(g.lease_id + 100, Some("secret-a")), Err(FarmError::LeaseLost(g.lease_id + 100)));
    }

    /// A job requiring `gpu` is not leased to a cpu-only worker (which still gets untagged
    /// work); while no live worker has the tag the job stays queued and says why; a worker with
    /// the tag gets it.
    #[test]
    fn required_tags_decide_which_worker_gets_a_job() {
        let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 100, ..FarmConfig::default() });
        let tags = |t: &[&str]| t.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let cpu = farm.register_tagged("cpu".into(), 1, String::new(), tags(&["cpu", "avx2"]), 0);
        let id = farm.submit_requiring("x".into(), None, 5, settings(), tags(&["gpu"]), 0).expect("submit");
        assert_eq!(farm.lease(cpu, 0).expect("lease"), None, "a cpu-only worker got a gpu unit");
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Queued);
        let info = job.info(0);
        assert_eq!(info.requires, tags(&["gpu"]));
        assert_eq!(info.waiting.as_deref(), Some("no live worker has tags [gpu]"));
        assert!(job.log.iter().any(|l| l.contains("no live worker has tags [gpu]")), "{:?}", job.log);
        // Untagged work still goes to the cpu worker, after the higher-priority gpu job.
        let plain = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        assert_eq!(farm.lease(cpu, 0).expect("lease").map(|g| g.job_id), Some(plain));
        let gpu = farm.register_tagged("gpu".into(), 1, String::new(), tags(&["cpu", "gpu"]), 0);
        assert_eq!(farm.job(id).expect("job").info(0).waiting, None);
        assert_eq!(farm.lease(gpu, 0).expect("lease").map(|g| g.job_id), Some(id));
        assert_eq!(farm.job(id).expect("job").state, JobState::Running);
        assert_eq!(farm.workers(0).iter().find(|w| w.id == gpu).map(|w| w.tags.clone()), Some(tags(&["cpu", "gpu"])));
        // The gpu worker goes silent: the job says so again.
        farm.heartbeat(cpu, 150).expect("hb");
        farm.expire(150);
        assert_eq!(farm.job(id).expect("job").info(150).waiting.as_deref(), Some("no live worker has tags [gpu]"));
        assert!(matches!(
            farm.submit_requiring("x".into(), None, 0, settings(), tags(&["GPU"]), 0),
            Err(FarmError::InvalidJob(_))
        ));
    }

    #[test]
    fn offline_workers_are_pruned() {
        let mut farm =
            Farm::new(FarmConfig { lease_timeout_ms: 100, worker_prune_ms: Some(1000), ..Default::default() });
        farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let quiet = farm.register("quiet".into(), 1, 0);
        let busy = farm.register("busy".into(), 1, 0);
        let alive = farm.register("alive".into(), 1, 0);
        farm.lease(busy, 0).expect("lease").expect("work");
        farm.heartbeat(alive, 900).expect("hb");
        assert_eq!(farm.prune_workers(1000), Vec::<WorkerId>::new());
        // The busy worker's lease expires (it is then silent too): pruned with the quiet one.
        farm.expire(1001);
        assert_eq!(farm.prune_workers(1001), vec![quiet, busy]);
        assert_eq!(farm.workers(1001).iter().map(|w| w.id).collect::<Vec<_>>(), vec![alive]);
        assert_eq!(farm.heartbeat(quiet, 1002), Err(FarmError::NoWorker(quiet)));
        let mut never = Farm::new(FarmConfig { worker_prune_ms: None, ..Default::default() });
        never.register("w".into(), 1, 0);
        assert!(never.prune_workers(u64::MAX).is_empty());
    }

    /// A coordinator stall longer than the lease timeout does not expire live workers' leases:
    /// the expiry after it gives every lease one more lease timeout.
    #[test]
    fn leases_get_a_grace_period_after_a_stall() {
        let mut farm = Farm::new(FarmConfig { lease_timeout_ms: 1000, ..FarmConfig::default() });
        let id = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let g = farm.lease(w, 0).expect("lease").expect("work");
        let g2 = farm.lease(w, 0).expect("lease").expect("work");
        for t in (250..=750).step_by(250) {
            assert_eq!(farm.expire(t), 0);
        }
        // Stalled from 750 to 5000: nothing expires, the worker is not offline.
        assert_eq!(farm.expire(5000), 0);
        assert!(farm.workers(5000).iter().all(|i| i.state != WorkerState::Offline));
        // The worker's result, sent during the stall, is heard and merged.
        farm.accept(g.lease_id, fake_result(&g), 5100).expect("merged after the stall");
        assert_eq!(farm.job(id).expect("job").units_merged, 1);
        // The grace is one lease timeout: a lease nobody renews expires after it.
        for t in (5250..=6000).step_by(250) {
            assert_eq!(farm.expire(t), 0, "{t}");
        }
        assert_eq!(farm.expire(6001), 1);
        assert_eq!(farm.accept(g2.lease_id, fake_result(&g2), 6002), Err(FarmError::LeaseLost(g2.lease_id)));
        // Without a stall, leases expire on time.
        let h = farm.lease(w, 6002).expect("lease").expect("work");
        let mut t = 6002;
        while t <= 7002 {
            t += 250;
            farm.expire(t);
        }
        assert_eq!(farm.accept(h.lease_id, fake_result(&h), t), Err(FarmError::LeaseLost(h.lease_id)));
    }

    #[test]
    fn mismatched_result_is_refused_and_requeued() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig::default());
        farm.submit("x".into(), None, 0, s, 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let g = farm.lease(w, 0).expect("lease").expect("work");
        let g2 = farm.lease(w, 0).expect("lease").expect("work");
        let mut wrong = fake_result(&g2);
        wrong.lease_id = g.lease_id;
        assert!(matches!(farm.accept(g.lease_id, wrong, 0), Err(FarmError::ResultMismatch { .. })));
        let again = farm.lease(w, 0).expect("lease").expect("work");
        assert_eq!(again.unit, g.unit);
    }

    #[test]
    fn higher_priority_first_and_fair_share_among_equals() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig::default());
        let low = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let low2 = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let high = farm.submit("x".into(), None, 5, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let units = s.plan().unit_count();
        for _ in 0..units {
            assert_eq!(farm.lease(w, 0).expect("lease").expect("work").job_id, high);
        }
        let mut counts = HashMap::new();
        for _ in 0..10 {
            *counts.entry(farm.lease(w, 0).expect("lease").expect("work").job_id).or_insert(0) += 1;
        }
        assert_eq!(counts.get(&low), Some(&5));
        assert_eq!(counts.get(&low2), Some(&5));
    }

    #[test]
    fn repeated_failures_blocklist_the_worker_and_fail_the_job() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
        let a = farm.register("a".into(), 1, 0);
        let b = farm.register("b".into(), 1, 0);
        for _ in 0..2 {
            let g = farm.lease(a, 0).expect("lease").expect("work");
            farm.release(g.lease_id, true, "boom", 0).expect("release");
        }
        assert!(farm.job(id).expect("job").blocklist.contains(&a));
        assert_eq!(farm.lease(a, 0).expect("lease"), None);
        let g = farm.lease(b, 0).expect("lease").expect("work");
        farm.release(g.lease_id, true, "boom again", 0).expect("release");
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Failed);
        assert!(job.error.as_deref().is_some_and(|e| e.contains("boom again")), "{:?}", job.error);
    }

    #[test]
    fn a_job_every_worker_fails_fails_instead_of_waiting_forever() {
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, settings(), 0).expect("submit");
        let only = farm.register("only".into(), 1, 0);
        // Two different units fail on the only worker: it is blocklisted, no unit failed 3 times.
        for _ in 0..2 {
            let g = farm.lease(only, 0).expect("lease").expect("work");
            farm.release(g.lease_id, true, "scene does not load", 0).expect("release");
        }
        let job = farm.job(id).expect("job");
        assert_eq!(job.state, JobState::Failed);
        assert!(job.error.as_deref().is_some_and(|e| e.contains("every worker")), "{:?}", job.error);
    }

    #[test]
    fn cancel_pause_resume() {
        let s = settings();
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s, 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let g = farm.lease(w, 0).expect("lease").expect("work");
        farm.pause(id, 1).expect("pause");
        assert_eq!(farm.lease(w, 1).expect("lease"), None);
        // In-flight work still merges while paused.
        farm.accept(g.lease_id, fake_result(&g), 2).expect("accept");
        farm.resume(id, 3).expect("resume");
        let g = farm.lease(w, 3).expect("lease").expect("work");
        farm.cancel(id, 4).expect("cancel");
        assert_eq!(farm.accept(g.lease_id, fake_result(&g), 5), Err(FarmError::LeaseLost(g.lease_id)));
        assert!(farm.cancel(id, 6).is_err());
        farm.delete(id).expect("delete");
        assert_eq!(farm.job(id).err(), Some(FarmError::NoJob(id)));
    }

    // ------------------------------------------------------------- adaptive sampling

    /// 20 x 12 pixels in 16-pixel tiles (tile 0: 2 x 2 blocks), spp 7 in passes 1, 2, 4.
    fn adaptive_settings() -> RenderSettings {
        let mut s = RenderSettings::new(20, 12, 7);
        s.tile_size = 16;
        s.passes = PassSchedule::Doubling { first: 1, max: 4 };
        s.adaptive = Some(AdaptiveSettings { threshold: 0.05, min_spp: 2 });
        s
    }

    /// A fake adaptive render: pixels left of x = 8 are flat (their blocks converge once they
    /// have 2 samples), the others alternate 0.1 and 2.0 (never converge); pixels in the mask's
    /// converged blocks get no samples (empty sums), as the renderer does.
    fn adaptive_result(tile: TileRect, pass: pathfarm_common::job::Pass, mask: Option<&BlockMask>) -> TileAccum {
        let mut accum = TileAccum::new(tile);
        for y in tile.y0..tile.y1 {
            for x in tile.x0..tile.x1 {
                if mask.is_some_and(|m| m.pixel_converged(x - tile.x0, y - tile.y0)) {
                    continue;
                }
                for s in pass.samples() {
                    let v = if x < 8 {
                        0.5
                    } else if s % 2 == 0 {
                        0.1
                    } else {
                        2.0
                    };
                    let v = SampleValue { radiance: [v, v * 0.5, x as f32 * 0.01 + y as f32], ..Default::default() };
                    pathfarm_common::film::add_sample(accum.pixel_mut(x - tile.x0, y - tile.y0), &v);
                }
            }
        }
        accum
    }

    fn adaptive_grant_result(g: &LeaseGrant) -> UnitResultFrame {
        let accum = adaptive_result(g.tile, g.pass, g.mask.as_ref());
        UnitResultFrame { lease_id: g.lease_id, job_id: g.job_id, unit: g.unit, accum, splats: None }
    }

    /// The local render's loop (`pathfarm_worker::render::render_local`) over the fake renderer.
    fn adaptive_local(s: &RenderSettings) -> Film {
        let (plan, a) = (s.plan(), s.adaptive.expect("adaptive"));
        let mut film = Film::new(s.width, s.height);
        let mut masks: Vec<Option<BlockMask>> = vec![None; plan.tiles.len()];
        for key in plan.units() {
            let (tile, pass) = (plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
            let mask = masks[key.tile as usize].as_ref();
            if !mask.is_some_and(BlockMask::all_converged) {
                film.add_tile(&adaptive_result(tile, pass, mask));
            }
            masks[key.tile as usize] = Some(adaptive::converged_blocks(&film.tile(tile).sums, tile, &a, pass.s1));
        }
        film
    }

    /// Adaptive: a tile's next pass is leased only after its previous pass merged; the grants
    /// carry the converged blocks; a fully converged tile leaves the schedule (its last pass is
    /// never leased) and the frame completes; results delivered out of order give the local
    /// render's film; a result with samples in converged blocks is refused; progress ends at
    /// 1 with the samples actually taken.
    #[test]
    fn adaptive_masks_gate_passes_and_match_the_local_render() {
        let s = adaptive_settings();
        let plan = s.plan();
        assert_eq!((plan.tiles.len(), plan.passes.len()), (2, 3));
        let reference = adaptive_local(&s);
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        let round = |farm: &mut Farm| {
            let mut grants = Vec::new();
            while let Some(g) = farm.lease(w, 0).expect("lease") {
                grants.push(g);
            }
            grants
        };
        // Only pass 0 is pending: pass 1 waits for it.
        let g0 = round(&mut farm);
        assert_eq!(g0.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(0, 0), (0, 1)]);
        assert!(g0.iter().all(|g| g.mask.is_none()), "nothing decided before the first pass");
        // Delivered in reverse order; 1 sample is below min_spp: no mask yet.
        for g in g0.iter().rev() {
            farm.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
        }
        let g1 = round(&mut farm);
        assert_eq!(g1.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(1, 0), (1, 1)]);
        assert!(g1.iter().all(|g| g.mask.is_none()), "one sample: no pixel has an error estimate");
        for g in g1.iter().rev() {
            farm.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
        }
        // After 3 samples tile 0's left blocks converged: its pass 2 carries the mask; tile 1
        // (x 16..20) is noisy everywhere: no converged block, no mask.
        let g2 = round(&mut farm);
        assert_eq!(g2.iter().map(|g| (g.unit.pass, g.unit.tile)).collect::<Vec<_>>(), vec![(2, 0), (2, 1)]);
        let mask = g2[0].mask.as_ref().expect("tile 0 has a mask");
        assert!(mask.is_converged(0, 0) && mask.is_converged(0, 1) && !mask.is_converged(1, 0));
        assert_eq!(g2[1].mask, None);
        // A result that samples the converged blocks anyway is refused and the unit comes back.
        let mut wrong = fake_result(&g2[0]);
        wrong.accum = adaptive_result(g2[0].tile, g2[0].pass, None);
        let e = farm.accept(g2[0].lease_id, wrong, 0).expect_err("refused");
        assert!(e.to_string().contains("its block has converged"), "{e}");
        let again = farm.lease(w, 0).expect("lease").expect("the unit is pending again");
        assert_eq!(again.unit, g2[0].unit);
        assert_eq!(again.mask.as_ref(), Some(mask));
        let mut out = farm.accept(g2[1].lease_id, adaptive_grant_result(&g2[1]), 0).expect("accept");
        assert!(!out.job_completed);
        out = farm.accept(again.lease_id, adaptive_grant_result(&again), 0).expect("accept");
        assert!(out.job_completed);
        let job = farm.job(id).expect("job");
        assert_eq!(job.film(), Some(&reference), "farm film differs from the local render");
        let info = job.info(0);
        assert_eq!(info.progress, 1.0);
        assert_eq!(info.units_merged, info.units_total);
        // Tile 0's left 8 x 12 pixels stopped at 3 of 7 samples.
        assert_eq!(info.samples_total, 20 * 12 * 7 - 8 * 12 * 4);
        assert_eq!(info.samples_done, info.samples_total);
    }

    /// Adaptive with a tile that converges entirely: its remaining passes are never leased and
    /// count as merged; a checkpoint restored mid-way recomputes the masks (they are not stored)
    /// and finishes with the local render's film.
    #[test]
    fn adaptive_converged_tiles_leave_the_schedule_and_survive_a_restore() {
        let mut s = adaptive_settings();
        s.tile_size = 8; // tile (0, 0) and (0, 8) are flat: they converge after pass 1
        let plan = s.plan();
        let (tiles, passes) = (plan.tiles.len(), plan.passes.len());
        let flat = plan.tiles.iter().filter(|t| t.x1 <= 8).count();
        assert_eq!((tiles, flat), (6, 2));
        let reference = adaptive_local(&s);
        let mut farm = Farm::new(FarmConfig::default());
        let id = farm.submit("x".into(), None, 0, s.clone(), 0).expect("submit");
        let w = farm.register("w".into(), 1, 0);
        // Passes 0 and 1 everywhere, then 1 unit of pass 2: checkpoint and restore.
        for _ in 0..2 * tiles + 1 {
            let g = farm.lease(w, 0).expect("lease").expect("work");
            farm.accept(g.lease_id, adaptive_grant_result(&g), 0).expect("accept");
        }
        let cps = farm.job_mut(id).expect("job").take_checkpoints(true, 1);
        let rec = farm.job(id).expect("job").record(0);
        let before = farm.job(id).expect("job").info(0);
        let mut again = Farm::new(FarmConfig::default());
        again.restore(rec, cps, &[], 0).expect("restore");
        let after = again.job(id).expect("job").info(0);
        assert_eq!(
            (after.units_merged, after.samples_done, after.samples_total),
            (before.units_merged, before.samples_done, before.samples_total)
        );
        // Both flat tiles left the schedule: only the other tiles' pass 2 remains.
        assert_eq!(after.units_merged, (2 * tiles + 1 + flat) as u64);
        let w = again.register("w".into(), 1, 0);
        let mut left = Vec::new();
        while let Some(g) = again.lease(w, 0).expect("lease") {
            assert!(plan.tiles[g.unit.tile as usize].x1 > 8, "a converged tile was leased: {:?}", g.unit);
            left.push(g);
        }
        assert_eq!(left.len(), tiles * passes - (2 * tiles + 1) - flat);
        for g in left.iter().rev() {
            again.accept(g.lease_id, adaptive_grant_result(g), 0).expect("accept");
        }
        let job = again.job(id).expect("job");
        assert_eq!(job.state, JobState::Completed);
        assert_eq!(job.film(), Some(&reference));
        assert_eq!(job.info(0).progress, 1.0);
    }
}
