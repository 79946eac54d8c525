//! A job: its frames, the frames in progress, progress figures and what the store keeps.

use super::frame_run::FrameRun;
use parking_lot::{MappedMutexGuard, Mutex};
use pathfarm_common::assembly::{FilmAssembly, Folded, Judged, PutFilm};
use pathfarm_common::film::Film;
use pathfarm_common::frames::FrameSet;
use pathfarm_common::job::{Plan, RenderSettings, UnitKey};
use pathfarm_common::protocol::{
    FrameInfo, FrameOrder, FrameState, FramesSummary, JobId, JobInfo, JobState, Notify, WorkerId,
};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

/// Per frame of the job, what is kept for every frame (8 bytes), started or not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct FrameStatus {
    pub(super) state: FrameState,
    pub(super) passes_done: u32,
}

/// A job and its frames' units.
///
/// A job renders a frame set (one frame unless `frames` was given). Units are (frame, pass,
/// tile); only frames in progress hold a [`FrameRun`] (film and merge state), so memory grows
/// with the frames in progress, not with the frames in the job; a queued job holds none. A
/// single-frame job (`sequence` false) writes `jobs/ID/image.exr`; once finished and written
/// there its film is dropped ([`super::Farm::final_image_written`]); a sequence's frame,
/// once every unit is merged, moves to `finishing` until the server has written
/// `jobs/ID/frames/NNNN/{image.exr,preview.png}` ([`super::Farm::frame_written`]), then its film is
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
    pub(super) started_notified: bool,
    /// Set while units are pending that no live worker may take (its tags lack some of
    /// `requires`): the reason, shown in the job's info and logged once.
    pub(super) unservable: Option<String>,
    /// Shared with the folds in progress (they run outside the farm lock).
    pub plan: Arc<Plan>,
    pub state: JobState,
    pub(super) status: Vec<FrameStatus>,
    /// Frames in progress, by index in `frames`.
    pub(super) open: BTreeMap<usize, FrameRun>,
    /// Frames fully merged whose images are not written yet (sequences only).
    pub(super) finishing: BTreeMap<usize, Arc<Film>>,
    /// Frames at or after this index may be pending; before it, none is.
    pub(super) next_unopened: usize,
    /// Frames pending (not started).
    pub(super) unstarted: usize,
    /// Frames fully merged (writing or done).
    pub(super) frames_merged: u32,
    pub(super) frames_done: u32,
    pub units_merged: u64,
    pub samples_done: u64,
    pub(super) samples_total: u64,
    pub(super) leased: u32,
    /// Units handed out so far (fair share among equal priorities).
    pub(super) served: u64,
    pub(super) unit_failures: HashMap<(usize, usize), u32>,
    pub(super) worker_failures: HashMap<WorkerId, u32>,
    pub blocklist: BTreeSet<WorkerId>,
    pub created_ms: u64,
    pub(super) started_ms: Option<u64>,
    /// Time spent running before the last pause.
    pub(super) run_ms_before: u64,
    pub finished_ms: Option<u64>,
    pub error: Option<String>,
    /// Human-readable events (retries, failures, blocklists), newest last.
    pub log: Vec<String>,
    /// Output should be written (a pass completed, a frame finished or the job ended).
    pub output_dirty: bool,
    /// A finished single-frame job whose final `image.exr` and `preview.png` are written: its
    /// film is dropped and its images are served from those files. The EV of the preview when
    /// this run wrote it (`None` after a restart).
    pub(super) image_on_disk: Option<Option<f32>>,
    /// Denoise steps and denoised layers (`farm/denoise.rs`).
    pub(super) denoise: super::denoise::JobDenoise,
}

/// Frames listed in a job's info (the rest: `GET /jobs/{id}/frames`).
pub(super) const INFO_FRAMES: usize = 64;

impl Job {
    pub(super) fn unit_key(&self, frame: usize, index: usize) -> UnitKey {
        let tiles = self.plan.tiles.len();
        UnitKey { frame: self.frames.frames()[frame], pass: (index / tiles) as u32, tile: (index % tiles) as u32 }
    }

    pub(super) fn units_per_frame(&self) -> u64 {
        self.plan.unit_count() as u64
    }

    pub(super) fn samples_per_frame(&self) -> u64 {
        u64::from(self.settings.width) * u64::from(self.settings.height) * u64::from(self.settings.spp)
    }

    pub(super) fn has_pending(&self) -> bool {
        self.open.values().any(|f| f.pending() > 0)
    }

    /// The next frame that may be started (frame order: only when no frame in progress has
    /// pending units left).
    pub(super) fn frame_to_open(&mut self) -> Option<usize> {
        while self.next_unopened < self.status.len() && self.status[self.next_unopened].state != FrameState::Pending {
            self.next_unopened += 1;
        }
        (self.next_unopened < self.status.len()).then_some(self.next_unopened)
    }

    /// Pending work, started or not (for "is anything waiting for a worker").
    pub(super) fn has_work(&self) -> bool {
        self.has_pending() || self.unstarted > 0
    }

    /// Frames this job holds (frames in progress and frames being written).
    pub fn films_held(&self) -> u64 {
        (self.open.len() + self.finishing.len()) as u64
    }

    /// Films this job holds in memory: those of `films_held` that are not on disk.
    pub fn films_resident(&self) -> u64 {
        (self.open.values().filter(|f| f.resident).count() + self.finishing.len()) as u64
    }

    /// Memory of the films this job holds now.
    pub fn film_bytes(&self) -> u64 {
        self.films_resident() * Film::bytes_for(self.settings.width, self.settings.height)
    }

    pub(super) fn open_frame(&mut self, index: usize) {
        let (w, h) = (self.settings.width, self.settings.height);
        self.open_frame_with(index, FilmAssembly::new(&self.plan, w, h));
    }

    /// Starts frame `index` merging into `asm` (restore: a checkpoint's passes).
    pub(super) fn open_frame_with(&mut self, index: usize, asm: FilmAssembly) {
        let run = FrameRun::new(&self.plan, asm, self.settings.adaptive.is_some());
        self.open.insert(index, run);
        self.status[index].state = FrameState::Rendering;
        self.unstarted -= 1;
    }

    /// Films this job needs to start its next frames: one (frame order), or every frame not
    /// started (sequence preview: all at once).
    pub(super) fn films_to_start(&self) -> u64 {
        match self.order {
            FrameOrder::Frame => 1,
            FrameOrder::SequencePreview => self.unstarted as u64,
        }
    }

    /// Starts the job's next frames (the first lease, or when the frames in progress have
    /// nothing pending): one frame in frame order, every frame not started in sequence
    /// preview. A queued job holds no film: its frames start here, when their films fit.
    pub(super) fn start_frames(&mut self) {
        while let Some(i) = self.frame_to_open() {
            self.open_frame(i);
            if self.sequence {
                self.log(format!("frame {} started", self.frames.frames()[i]));
            }
            if self.order == FrameOrder::Frame {
                break;
            }
        }
    }

    /// Every unit of frame `index` is merged: a sequence's frame waits to be written, a
    /// single-frame job keeps its film as the job's image.
    pub(super) fn frame_merged(&mut self, index: usize) {
        self.frames_merged += 1;
        self.status[index].passes_done = self.plan.passes.len() as u32;
        if self.sequence {
            if let Some(film) = self.open.remove(&index).and_then(|run| run.asm.lock().take_film()) {
                self.finishing.insert(index, Arc::new(film));
            }
            self.status[index].state = FrameState::Writing;
            self.output_dirty = true;
        } else {
            self.status[index].state = FrameState::Done;
            self.frames_done += 1;
        }
    }

    /// Records a unit that frame `index`'s assembly folded: the frame's scheduling state and the
    /// job's figures (and, adaptive sampling, what judging its tile then skipped).
    pub(super) fn record_folded(&mut self, index: usize, f: &Folded) {
        let Some(run) = self.open.get_mut(&index) else { return };
        run.advance(f.tile as usize, f.pass + 1);
        run.checkpoint_dirty = true;
        self.units_merged += 1;
        self.samples_done += f.samples;
        if let Some(j) = &f.judged {
            self.record_judged(index, f.tile, j);
        }
    }

    /// Records a judged tile of frame `index`: a tile whose every block converged skips its
    /// remaining passes (they count as merged), and its converged pixels' missing samples are
    /// taken off the job's total.
    fn record_judged(&mut self, index: usize, tile: u32, j: &Judged) {
        if let Some(run) = self.open.get_mut(&index)
            && j.tile_done
        {
            run.advance(tile as usize, self.plan.passes.len() as u32);
        }
        self.units_merged += u64::from(j.passes_skipped);
        self.samples_total = self.samples_total.saturating_sub(j.samples_skipped);
    }

    /// Puts frame `index`'s film back into its assembly (read from disk, restored, or a write
    /// that failed). A frame restored from a checkpoint counts the samples its film holds
    /// (adaptive: converged pixels hold fewer than the passes) and records the tiles the
    /// assembly judged. Returns the waiting units it folded, for [`super::Farm::settle`].
    pub(super) fn put_film(&mut self, index: usize, film: Film) -> Vec<Folded> {
        let adaptive = self.settings.adaptive.as_ref().map(|a| (a, self.settings.spp));
        let Some(run) = self.open.get_mut(&index) else { return Vec::new() };
        if std::mem::replace(&mut run.restored, false) && adaptive.is_some() {
            self.samples_done += film.sums.iter().map(|p| u64::from(p.weight)).sum::<u64>();
        }
        run.resident = true;
        let PutFilm { judged, folded } = run.asm.lock().put_film(&self.plan, adaptive, film);
        for (tile, j) in &judged {
            self.record_judged(index, *tile, j);
        }
        folded
    }

    /// A cancelled or failed sequence gives up its frames in progress (their films).
    pub(super) fn drop_open_frames(&mut self) {
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
    pub(super) fn take_unit(&mut self, lease: pathfarm_common::protocol::LeaseId) -> Option<(usize, usize)> {
        let tiles = self.plan.tiles.len().max(1);
        let frame = match self.order {
            FrameOrder::Frame => self.open.iter().find(|(_, f)| f.pending() > 0).map(|(&i, _)| i),
            FrameOrder::SequencePreview => self
                .open
                .iter_mut()
                .filter(|(_, f)| f.pending() > 0)
                .filter_map(|(&i, f)| f.peek_pending().map(|u| (u / tiles, i)))
                .min()
                .map(|(_, i)| i),
        }?;
        let unit = self.open.get_mut(&frame)?.take_pending(lease)?;
        Some((frame, unit))
    }

    pub(super) fn requeue(&mut self, frame: usize, unit: usize) {
        if let Some(f) = self.open.get_mut(&frame) {
            f.requeue(unit);
        }
    }

    pub(super) fn accepts_work(&self) -> bool {
        matches!(self.state, JobState::Queued | JobState::Running)
    }

    pub(super) fn running_ms(&self, now_ms: u64) -> u64 {
        let current = match (self.state, self.started_ms) {
            (JobState::Running, Some(s)) => now_ms.saturating_sub(s),
            _ => 0,
        };
        self.run_ms_before + current
    }

    pub(super) fn stop_clock(&mut self, now_ms: u64) {
        if let (JobState::Running, Some(s)) = (self.state, self.started_ms) {
            self.run_ms_before += now_ms.saturating_sub(s);
        }
        self.started_ms = None;
    }

    pub(super) fn log(&mut self, line: String) {
        tracing::info!(job = self.id, "{line}");
        if self.log.len() < 10_000 {
            self.log.push(line);
        }
    }

    /// Its images are to be written now: something changed, and its film is in memory (a
    /// single-frame job's film on disk is written once it is loaded again).
    pub fn output_due(&self) -> bool {
        self.output_dirty && (self.sequence || self.film().is_some())
    }

    /// A finished single-frame job's images are on disk, its film dropped: `Some(ev)` with the
    /// preview's EV when this run wrote it.
    pub fn image_on_disk(&self) -> Option<Option<f32>> {
        self.image_on_disk
    }

    /// The film shown as "the job's image": a single-frame job's film; for a sequence, `None`
    /// (each frame has its own: [`Job::frame_film`]).
    ///
    /// The film is read under its frame lock, held while the guard lives (the caller holds the
    /// farm lock: lock order farm, then frame).
    pub fn film(&self) -> Option<MappedMutexGuard<'_, Film>> {
        if self.sequence { None } else { self.open.values().next().and_then(FrameRun::film) }
    }

    /// Mutable access to a single-frame job's film (tests).
    #[cfg(test)]
    pub fn film_mut(&mut self) -> Option<MappedMutexGuard<'_, Film>> {
        if self.sequence { None } else { self.open.values_mut().next().and_then(|f| f.film()) }
    }

    /// The film of frame number `frame` while it is held (rendering or being written).
    pub fn frame_film(&self, frame: i32) -> Option<FrameFilm<'_>> {
        let index = self.frame_index(frame)?;
        if let Some(film) = self.open.get(&index).and_then(FrameRun::film) {
            return Some(FrameFilm::Open(film));
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
            Some(f) => f.next_passes().to_vec(),
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

/// A frame's film as the API reads it: under its frame lock while rendering, shared while being
/// written.
pub enum FrameFilm<'a> {
    Open(MappedMutexGuard<'a, Film>),
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
    pub(super) fn new(id: JobId, spec: JobSpec, now_ms: u64) -> Self {
        let plan = Arc::new(spec.settings.plan());
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
            image_on_disk: None,
            denoise: Default::default(),
        }
    }

    /// For at most `limit` frames in progress that merged units since the last call: the film
    /// and merged set, for a checkpoint (`all`: every frame in progress). Each is a copy of a
    /// film: the caller takes one at a time to bound the memory.
    pub fn take_checkpoints(&mut self, all: bool, limit: usize) -> Vec<Checkpoint> {
        self.checkpoint_sources(all, limit).iter().filter_map(CheckpointSource::copy).collect()
    }

    /// [`Job::take_checkpoints`] without the copies: each frame's assembly, for the caller to
    /// copy its film and merged set under the frame lock once the farm lock is released.
    pub fn checkpoint_sources(&mut self, all: bool, limit: usize) -> Vec<CheckpointSource> {
        let (id, frames) = (self.id, self.frames.frames());
        self.open
            .iter_mut()
            .filter(|(_, f)| (all || f.checkpoint_dirty) && f.resident)
            .take(limit)
            .map(|(&i, f)| {
                f.checkpoint_dirty = false;
                CheckpointSource { job_id: id, frame: frames[i], asm: f.asm.clone() }
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

/// A checkpoint without its film: what a restart reads of each frame in progress (its film is
/// read when the frame is leased again).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CheckpointHead {
    pub job_id: JobId,
    /// The frame number.
    pub frame: i32,
    pub width: u32,
    pub height: u32,
    pub next_pass: Vec<u32>,
}

/// A frame's checkpoint as restore takes it: with its film, or only its head (the film stays
/// on disk until the frame is leased).
#[derive(Clone, Debug)]
pub enum FrameCheckpoint {
    Loaded(Checkpoint),
    OnDisk(CheckpointHead),
}

impl From<Checkpoint> for FrameCheckpoint {
    fn from(cp: Checkpoint) -> Self {
        FrameCheckpoint::Loaded(cp)
    }
}

impl From<CheckpointHead> for FrameCheckpoint {
    fn from(h: CheckpointHead) -> Self {
        FrameCheckpoint::OnDisk(h)
    }
}

impl Checkpoint {
    pub fn head(&self) -> CheckpointHead {
        CheckpointHead {
            job_id: self.job_id,
            frame: self.frame,
            width: self.film.width,
            height: self.film.height,
            next_pass: self.next_pass.clone(),
        }
    }
}

/// A frame in progress to checkpoint ([`Job::checkpoint_sources`]).
pub struct CheckpointSource {
    pub job_id: JobId,
    /// The frame number.
    pub frame: i32,
    asm: Arc<Mutex<FilmAssembly>>,
}

impl CheckpointSource {
    /// The frame's checkpoint: its film and the passes it holds, read together under the frame
    /// lock (a fold in progress is either all in both or in neither). `None` while the film is
    /// on disk.
    pub fn copy(&self) -> Option<Checkpoint> {
        let asm = self.asm.lock();
        let film = asm.film()?.clone();
        Some(Checkpoint { job_id: self.job_id, frame: self.frame, next_pass: asm.next_passes().to_vec(), film })
    }
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
