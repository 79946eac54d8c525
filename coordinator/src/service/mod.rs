//! The service floor: the farm with everything that runs around it: shared state
//! ([`AppState`]), the store and checkpoints, scenes, progressive output, background loops,
//! webhooks and metrics. It knows nothing of HTTP (see `crate::http`).

use crate::farm::{Farm, FarmConfig};
use pathfarm_common::film::{Film, ImageLayers, write_atomic};
use pathfarm_common::protocol::{API, JobId, JobState, SceneCreated};
use pathfarm_common::scene::bundle::{is_scene_id, scene_id, unpack_bundle};
use pathfarm_common::scene::{LoadOptions, load_scene};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use store::{Store, write_checkpoint};
use tokio::sync::{Notify, broadcast};

/// The farm's clock, in milliseconds: the Unix time when the process started plus the
/// monotonic time since (`Instant`). Lease deadlines and heartbeats follow it, so a step of the
/// wall clock (NTP, a VM restored from a snapshot) neither expires live leases nor keeps dead
/// ones; timestamps shown (job created and finished, worker last seen) stay Unix milliseconds,
/// off by as much as the wall clock was stepped since the start.
pub fn now_ms() -> u64 {
    static BASE: std::sync::OnceLock<(u64, Instant)> = std::sync::OnceLock::new();
    let (wall, start) = BASE.get_or_init(|| {
        (SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64), Instant::now())
    });
    wall + start.elapsed().as_millis() as u64
}

pub mod error;
pub mod loops;
pub mod metrics;
pub mod outputs;
pub mod residency;
pub mod scenes;
pub mod store;
pub mod webhook;

pub use error::*;
pub use metrics::*;
pub use outputs::*;
pub use scenes::*;

/// Service configuration.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    pub listen: SocketAddr,
    pub data_dir: PathBuf,
    pub farm: FarmConfig,
    pub max_upload_bytes: usize,
    pub max_triangles: usize,
    pub max_texture_pixels: u64,
    /// Memory budget for one scene's decoded images (bytes); see `LoadOptions::max_texture_bytes`.
    pub max_texture_bytes: u64,
    /// Scene uploads parsed and decoded at once; more wait (each may use up to
    /// `max_texture_bytes`).
    pub max_scene_decodes: usize,
    /// Minimum time between two progressive writes of a job's images.
    pub output_interval: Duration,
    /// How often changed jobs are checkpointed.
    pub checkpoint_interval: Duration,
    pub auth: Auth,
    /// Header and idle timeouts, connection cap.
    pub conn: ConnLimits,
    /// When set, `/metrics` requires `Authorization: Bearer <it>`.
    pub metrics_token: Option<String>,
    /// Serve HTTPS with this certificate chain and private key (PEM files).
    pub tls: Option<(PathBuf, PathBuf)>,
    /// Worker registrations per client address: a token bucket refilled at this many per
    /// minute (0: unlimited)...
    pub register_per_minute: u32,
    /// ... holding at most this many.
    pub register_burst: u32,
    /// Scenes that no job references and that were stored (or uploaded again) longer ago than
    /// this many milliseconds are removed by the maintenance loop; `None`: never.
    pub scene_gc_after_ms: Option<u64>,
    /// Job webhooks: the signing secret, retries, timeouts.
    pub webhooks: webhook::WebhookConfig,
}

/// Connection limits (`--header-timeout-ms`, `--idle-timeout-ms`, `--max-connections`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConnLimits {
    /// Time a request head may take (from the accept for a connection's first request).
    pub header_timeout: Duration,
    /// Time a connection may stay quiet between requests.
    pub idle_timeout: Duration,
    /// Open connections at most.
    pub max_connections: usize,
}

impl Default for ConnLimits {
    fn default() -> Self {
        Self { header_timeout: Duration::from_secs(10), idle_timeout: Duration::from_secs(60), max_connections: 4096 }
    }
}

/// Default of `--scene-gc-after-ms`: a week.
pub const SCENE_GC_AFTER_MS: u64 = 7 * 24 * 3_600_000;

impl ServerConfig {
    pub fn new(listen: SocketAddr, data_dir: PathBuf) -> Self {
        Self {
            listen,
            data_dir,
            farm: FarmConfig::default(),
            max_upload_bytes: 512 << 20,
            max_triangles: 20_000_000,
            max_texture_pixels: 16384 * 16384,
            max_texture_bytes: 2 << 30,
            max_scene_decodes: 2,
            output_interval: Duration::from_secs(2),
            checkpoint_interval: Duration::from_secs(1),
            auth: Auth::default(),
            conn: ConnLimits::default(),
            tls: None,
            metrics_token: None,
            register_per_minute: 60,
            register_burst: 60,
            scene_gc_after_ms: Some(SCENE_GC_AFTER_MS),
            webhooks: webhook::WebhookConfig::default(),
        }
    }
}

/// Per-address token buckets (worker registrations).
pub struct RateLimiter {
    per_sec: f64,
    burst: f64,
    buckets: Mutex<HashMap<std::net::IpAddr, (f64, Instant)>>,
}

/// Addresses tracked at most; beyond it, buckets that are full again are dropped first.
const MAX_BUCKETS: usize = 65_536;

impl RateLimiter {
    pub fn new(per_minute: u32, burst: u32) -> Self {
        Self {
            per_sec: f64::from(per_minute) / 60.0,
            burst: f64::from(burst.max(1)),
            buckets: Mutex::new(HashMap::new()),
        }
    }

    /// Takes a token for `ip` at `now`; `Err(wait)` when the bucket is empty.
    pub fn check(&self, ip: std::net::IpAddr, now: Instant) -> Result<(), Duration> {
        if self.per_sec <= 0.0 {
            return Ok(());
        }
        let mut buckets = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        if buckets.len() >= MAX_BUCKETS && !buckets.contains_key(&ip) {
            let (rate, burst) = (self.per_sec, self.burst);
            buckets.retain(|_, (tokens, t)| *tokens + now.saturating_duration_since(*t).as_secs_f64() * rate < burst);
            if buckets.len() >= MAX_BUCKETS {
                // Every tracked address is busy: refuse newcomers rather than grow without bound.
                return Err(Duration::from_secs_f64(1.0 / self.per_sec));
            }
        }
        let (tokens, last) = buckets.entry(ip).or_insert((self.burst, now));
        *tokens = (*tokens + now.saturating_duration_since(*last).as_secs_f64() * self.per_sec).min(self.burst);
        *last = now;
        if *tokens >= 1.0 {
            *tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - *tokens) / self.per_sec))
        }
    }
}

/// Bearer tokens; with neither set, the API is open.
#[derive(Clone, Debug, Default)]
pub struct Auth {
    pub client: Option<String>,
    pub worker: Option<String>,
}

/// A mutex that survives a panicking holder (the state machine keeps no half-done updates
/// across a panic point that matters more than serving on).
pub struct FarmLock(Mutex<Farm>);

impl FarmLock {
    pub fn lock(&self) -> MutexGuard<'_, Farm> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Live event for dashboards (`GET /events` coalesces them): what changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Event {
    /// A job's state, priority or progress changed (or it was deleted).
    Job { id: JobId },
    /// A job's images were written.
    Image { id: JobId },
    /// Frame `frame` of a sequence was written.
    Frame { id: JobId, frame: i32 },
    /// A worker registered, changed or was pruned.
    Worker { id: u64 },
}

/// Everything the handlers share.
pub struct AppState {
    pub config: ServerConfig,
    pub farm: FarmLock,
    pub scenes: SceneStore,
    pub auth: Auth,
    /// Woken when units may have become available (job submitted, resumed, unit requeued).
    pub work_ready: Notify,
    /// Woken when a pass or a job completed (progressive output).
    pub output_ready: Notify,
    pub events: broadcast::Sender<Event>,
    pub metrics: Metrics,
    pub started: Instant,
    /// SQLite and checkpoints.
    pub store: Mutex<Store>,
    /// Permits for scene decodes (`ServerConfig::max_scene_decodes`).
    pub scene_decodes: tokio::sync::Semaphore,
    /// Worker registrations per client address.
    pub register_limiter: RateLimiter,
    /// Webhook deliveries waiting to be sent.
    pub webhooks: webhook::Queue,
}

impl AppState {
    /// Opens the data dir and restores every job from the store.
    pub fn new(config: ServerConfig) -> anyhow::Result<Self> {
        std::fs::create_dir_all(config.data_dir.join("jobs"))?;
        let scenes = SceneStore::open(config.data_dir.join("scenes"))?;
        let (events, _) = broadcast::channel(1024);
        let store = Store::open(&config.data_dir)?;
        let epoch = store.next_epoch()?;
        let mut farm = Farm::with_epoch(config.farm.clone(), epoch);
        // Ids of deleted jobs and of skipped rows are never given again.
        farm.reserve_job_ids_through(store.max_job_id()?);
        let now = now_ms();
        for rec in store.jobs()? {
            let id = rec.id;
            let dir = config.data_dir.join("jobs").join(id.to_string());
            let (done, checkpoints) = match &rec.frames {
                Some(frames) => store.sequence_state(id, frames),
                // A finished job whose final image is written holds no film: its checkpoint is
                // not read. (A progressive image, or a final one not marked yet, is not that.)
                None if rec.state.is_finished() && outputs::final_image_on_disk(&dir, rec.finished_ms) => {
                    (vec![0], Vec::new())
                }
                // Only the merged set: the film is read when the job is leased again.
                None => (Vec::new(), store::read_checkpoint_head(&store.checkpoint_path(id)).into_iter().collect()),
            };
            if let Err(e) = farm.restore(rec.clone(), checkpoints, &done, now) {
                tracing::error!(job = id, "{e}; restarting the job's unwritten frames from zero");
                farm.restore(rec, Vec::<crate::farm::CheckpointHead>::new(), &done, now).map_err(anyhow::Error::msg)?;
            }
        }
        tracing::info!(epoch, jobs = farm.jobs().count(), "state restored");
        // Workers of earlier runs register again (their ids carry the old epoch): rows older
        // than the prune time are of no use.
        if let Some(after) = config.farm.worker_prune_ms {
            match store.delete_workers_registered_before(now.saturating_sub(after)) {
                Ok(0) => {}
                Ok(n) => tracing::info!(rows = n, "pruned old worker rows"),
                Err(e) => tracing::error!("pruning worker rows failed: {e:#}"),
            }
        }
        Ok(Self {
            store: Mutex::new(store),
            farm: FarmLock(Mutex::new(farm)),
            scenes,
            auth: config.auth.clone(),
            work_ready: Notify::new(),
            output_ready: Notify::new(),
            events,
            metrics: Metrics::default(),
            started: Instant::now(),
            scene_decodes: tokio::sync::Semaphore::new(config.max_scene_decodes.max(1)),
            register_limiter: RateLimiter::new(config.register_per_minute, config.register_burst),
            webhooks: webhook::Queue::new(config.webhooks.queue),
            config,
        })
    }

    pub fn load_options(&self) -> LoadOptions {
        LoadOptions {
            max_triangles: Some(self.config.max_triangles),
            max_texture_pixels: Some(self.config.max_texture_pixels),
            max_texture_bytes: Some(self.config.max_texture_bytes),
        }
    }

    fn store(&self) -> MutexGuard<'_, Store> {
        self.store.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes a job's row (state, priority, times) now; used by API actions that must be
    /// durable before they are acknowledged: an error here is the request's answer (507 when
    /// the disk is full).
    pub fn persist_job(&self, id: JobId) -> ServiceResult<()> {
        // Store lock first, then the farm's: a job deleted meanwhile is not written back (a
        // delete takes the farm's lock, then the store's, to remove the row).
        let store = self.store();
        let rec = self.farm.lock().job(id).ok().map(|j| j.record(now_ms()));
        match rec {
            Some(rec) => store.put_job(&rec).map_err(|e| database_error(&e, &format!("job {id}"))),
            None => Ok(()),
        }
    }

    /// Runs `f` on the farm under its lock, takes what it changed, and applies the changes after
    /// the lock is released ([`AppState::apply`]). `f`'s error comes first; else an error applying
    /// (a job record that could not be saved: the change is in effect but not durable).
    pub fn act<T>(&self, f: impl FnOnce(&mut Farm) -> Result<T, crate::farm::FarmError>) -> ServiceResult<T> {
        let (r, changes) = self.locked(f);
        let applied = self.apply(changes);
        let v = r?;
        applied?;
        Ok(v)
    }

    /// Runs `f` on the farm under its lock and returns its result with the changes, for callers
    /// that must react to applying them (a job that cannot be saved is withdrawn).
    pub fn locked<T>(&self, f: impl FnOnce(&mut Farm) -> T) -> (T, crate::farm::Changes) {
        let mut farm = self.farm.lock();
        let r = f(&mut farm);
        (r, farm.take_changes())
    }

    /// The one place where the farm's changes take effect outside it: removed jobs lose their
    /// rows and files, changed job records are saved, worker rows are saved or deleted, waiting
    /// workers and the output writer are woken, and events are published. Every record is
    /// tried; the first error is returned (the checkpoint loop saves records again later).
    pub fn apply(&self, changes: crate::farm::Changes) -> ServiceResult<()> {
        if changes.is_empty() {
            return Ok(());
        }
        let mut first_error = None;
        for &id in &changes.removed {
            if let Err(e) = self.forget_job(id) {
                first_error.get_or_insert(e);
            }
            self.delete_job_files(id);
        }
        for &id in changes.records.difference(&changes.removed) {
            if let Err(e) = self.persist_job(id) {
                first_error.get_or_insert(e);
            }
        }
        for (id, name, threads) in &changes.registered {
            self.persist_worker(*id, name, *threads);
        }
        if !changes.pruned.is_empty()
            && let Err(e) = self.store().delete_workers(&changes.pruned)
        {
            tracing::error!("deleting pruned worker rows failed: {e:#}");
        }
        if changes.work_ready {
            self.work_ready.notify_waiters();
        }
        if changes.outputs {
            self.output_ready.notify_one();
        }
        for &(id, frame) in &changes.frames {
            self.publish(Event::Frame { id, frame });
        }
        let jobs: std::collections::BTreeSet<JobId> =
            changes.records.iter().chain(&changes.progress).chain(&changes.removed).copied().collect();
        for id in jobs {
            self.publish(Event::Job { id });
        }
        for &id in &changes.workers {
            self.publish(Event::Worker { id });
        }
        first_error.map_or(Ok(()), Err)
    }

    /// Appends a line to a job's log and publishes the change.
    pub fn log_job(&self, id: JobId, line: String) {
        let ((), changes) = self.locked(|farm| farm.log_job(id, line));
        self.apply_logged(changes, &format!("job {id}'s log line"));
    }

    /// [`AppState::apply`] where the change is in effect whatever happens: an error (a record
    /// not saved; the checkpoint loop saves it again) is logged with `what` changed.
    pub fn apply_logged(&self, changes: crate::farm::Changes, what: &str) {
        if let Err(e) = self.apply(changes) {
            tracing::error!("applying {what}'s changes: {}", e.message);
        }
    }

    pub fn persist_worker(&self, id: u64, name: &str, threads: u32) {
        if let Err(e) = self.store().put_worker(id, name, threads, now_ms()) {
            tracing::error!(worker = id, "persisting the worker failed: {e:#}");
        }
    }

    pub fn forget_job(&self, id: JobId) -> ServiceResult<()> {
        self.store().delete_job(id).map_err(|e| database_error(&e, &format!("the deletion of job {id}")))
    }

    pub fn publish(&self, event: Event) {
        let _ = self.events.send(event);
    }

    /// Frame `frame` of job `id` is written (and the job's progress changed).
    pub fn publish_frame(&self, id: JobId, frame: i32) {
        self.publish(Event::Frame { id, frame });
        self.publish(Event::Job { id });
    }

    pub fn job_dir(&self, id: JobId) -> PathBuf {
        self.config.data_dir.join("jobs").join(id.to_string())
    }

    pub fn delete_job_files(&self, id: JobId) {
        let _ = std::fs::remove_dir_all(self.job_dir(id));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registrations_are_rate_limited_per_address() {
        let limiter = RateLimiter::new(60, 3);
        let (a, b): (std::net::IpAddr, std::net::IpAddr) =
            ("10.0.0.1".parse().expect("ip"), "10.0.0.2".parse().expect("ip"));
        let t0 = Instant::now();
        for _ in 0..3 {
            assert_eq!(limiter.check(a, t0), Ok(()));
        }
        let wait = limiter.check(a, t0).expect_err("bucket empty");
        assert!(wait > Duration::from_millis(900) && wait <= Duration::from_secs(1), "{wait:?}");
        // Another address has its own bucket; one per second comes back.
        assert_eq!(limiter.check(b, t0), Ok(()));
        assert_eq!(limiter.check(a, t0 + Duration::from_millis(1000)), Ok(()));
        assert!(limiter.check(a, t0 + Duration::from_millis(1500)).is_err());
        assert!(RateLimiter::new(0, 1).check(a, t0).is_ok() && RateLimiter::new(0, 1).check(a, t0).is_ok());
    }
}
