//! The coordinator service: shared state, the background loops (lease expiry, progressive
//! output) and `serve`.

use crate::api::ApiError;
use crate::farm::{Farm, FarmConfig};
use crate::store::{Store, read_checkpoint, write_checkpoint};
use axum::http::StatusCode;
use pathfarm_common::film::{Film, ImageLayers, write_atomic};
use pathfarm_common::protocol::{JobId, JobState, SceneCreated};
use pathfarm_common::scene::bundle::{is_scene_id, scene_id, unpack_bundle};
use pathfarm_common::scene::{LoadOptions, load_scene};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
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
    pub conn: crate::conn::ConnLimits,
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
    pub webhooks: crate::webhook::WebhookConfig,
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
            conn: crate::conn::ConnLimits::default(),
            tls: None,
            metrics_token: None,
            register_per_minute: 60,
            register_burst: 60,
            scene_gc_after_ms: Some(SCENE_GC_AFTER_MS),
            webhooks: crate::webhook::WebhookConfig::default(),
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

/// A failed write on the coordinator's own disk: 507 when the disk is full (the client may retry
/// later), 500 otherwise; the message names what was not stored, never a server path.
pub fn storage_error(e: &std::io::Error, what: &str) -> ApiError {
    tracing::error!(error = %e, "storing {what} failed");
    if e.kind() == std::io::ErrorKind::StorageFull || e.raw_os_error() == Some(28) {
        ApiError::new(
            StatusCode::INSUFFICIENT_STORAGE,
            "insufficient_storage",
            format!("the coordinator's disk is full: {what} was not stored; retry later"),
        )
    } else {
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "storage_error",
            format!("the coordinator could not store {what} ({})", e.kind()),
        )
    }
}

/// A failed database write: 507 when the disk is full, 503 otherwise; the message says what was
/// not saved.
pub fn database_error(e: &anyhow::Error, what: &str) -> ApiError {
    tracing::error!(error = %format!("{e:#}"), "saving {what} failed");
    let full = e.downcast_ref::<rusqlite::Error>().and_then(rusqlite::Error::sqlite_error_code)
        == Some(rusqlite::ErrorCode::DiskFull)
        || e.downcast_ref::<std::io::Error>().is_some_and(|io| io.raw_os_error() == Some(28));
    if full {
        ApiError::new(
            StatusCode::INSUFFICIENT_STORAGE,
            "insufficient_storage",
            format!("the coordinator's disk is full: {what} was not saved; retry later"),
        )
    } else {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "storage_unavailable",
            format!("the coordinator could not save {what}; retry later"),
        )
    }
}

/// What the scene store remembers about a bundle.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneMeta {
    pub triangles: usize,
    pub cameras: usize,
    pub warnings: Vec<String>,
}

/// Content-addressed scene bundles under `data_dir/scenes`.
pub struct SceneStore {
    dir: PathBuf,
    /// Per scene: its meta and when it was stored (Unix ms; the bundle's modification time
    /// after a restart, refreshed when the same bytes are uploaded again).
    meta: Mutex<HashMap<String, (SceneMeta, u64)>>,
}

impl SceneStore {
    fn open(dir: PathBuf) -> std::io::Result<Self> {
        std::fs::create_dir_all(&dir)?;
        let mut meta = HashMap::new();
        for entry in std::fs::read_dir(&dir)? {
            let path = entry?.path();
            let Some(id) = path.file_stem().and_then(|s| s.to_str()) else { continue };
            if path.extension().is_some_and(|e| e == "json")
                && is_scene_id(id)
                && let Some(m) = std::fs::read(&path).ok().and_then(|b| serde_json::from_slice(&b).ok())
            {
                let stored = std::fs::metadata(dir.join(format!("{id}.bundle")))
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
                    .map_or_else(now_ms, |d| d.as_millis() as u64);
                meta.insert(id.to_string(), (m, stored));
            }
        }
        Ok(Self { dir, meta: Mutex::new(meta) })
    }

    pub fn bundle_path(&self, id: &str) -> PathBuf {
        self.dir.join(format!("{id}.bundle"))
    }

    fn entries(&self) -> MutexGuard<'_, HashMap<String, (SceneMeta, u64)>> {
        self.meta.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn meta(&self, id: &str) -> Option<SceneMeta> {
        self.entries().get(id).map(|(m, _)| m.clone())
    }

    /// Forgets a scene and removes its bundle and meta file; `Ok(false)` when it was not stored.
    /// Callers hold the farm lock, so no job can be submitted for the scene meanwhile
    /// (`create_job` checks the scene again under that lock).
    pub fn remove(&self, id: &str) -> std::io::Result<bool> {
        if self.entries().remove(id).is_none() {
            return Ok(false);
        }
        for path in [self.bundle_path(id), self.dir.join(format!("{id}.json"))] {
            match std::fs::remove_file(&path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        tracing::info!(scene = %id, "scene removed");
        Ok(true)
    }

    /// Scenes stored at or before `stored_before` (Unix ms) that `referenced` does not name.
    pub fn unreferenced_before(&self, stored_before: u64, referenced: &dyn Fn(&str) -> bool) -> Vec<String> {
        self.entries()
            .iter()
            .filter(|(id, (_, stored))| *stored <= stored_before && !referenced(id))
            .map(|(id, _)| id.clone())
            .collect()
    }

    /// Validates (by loading) and stores a bundle; idempotent for the same bytes.
    pub fn add(&self, bytes: &[u8], opts: &LoadOptions) -> Result<SceneCreated, ApiError> {
        let id = scene_id(bytes);
        if let Some((m, stored)) = self.entries().get_mut(&id) {
            // Uploaded again: the client is about to use it, so the GC's clock starts over
            // (also across a restart, through the bundle's modification time).
            *stored = now_ms();
            let m = m.clone();
            if let Err(e) = std::fs::File::options()
                .append(true)
                .open(self.bundle_path(&id))
                .and_then(|f| f.set_modified(SystemTime::now()))
            {
                tracing::warn!(scene = %id, error = %e, "refreshing the scene's modification time failed");
            }
            return Ok(SceneCreated { scene_id: id, triangles: m.triangles, warnings: m.warnings });
        }
        // A scratch folder per upload: concurrent uploads of the same bytes must not share one.
        static SCRATCH_SEQ: AtomicU64 = AtomicU64::new(0);
        let seq = SCRATCH_SEQ.fetch_add(1, Ordering::Relaxed);
        let scratch = self.dir.join(format!(".unpack-{id}-{}-{seq}", std::process::id()));
        let loaded = match unpack_bundle(bytes, &scratch) {
            Ok(main) => load_scene(&main, opts),
            // Unpacking writes on our disk: its I/O errors are ours, not the client's.
            Err(pathfarm_common::scene::SceneError::Io { source, .. }) => {
                let _ = std::fs::remove_dir_all(&scratch);
                return Err(storage_error(&source, "the scene"));
            }
            Err(e) => Err(e),
        };
        let _ = std::fs::remove_dir_all(&scratch);
        let scene = loaded.map_err(|e| {
            use pathfarm_common::scene::SceneError;
            match e {
                SceneError::LimitExceeded { .. } => {
                    ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "limit_exceeded", e.to_string())
                }
                SceneError::ForbiddenUri { .. } => ApiError::unprocessable("forbidden_uri", e.to_string()),
                _ => ApiError::unprocessable("invalid_scene", e.to_string()),
            }
        })?;
        let meta =
            SceneMeta { triangles: scene.triangle_count(), cameras: scene.cameras.len(), warnings: scene.warnings };
        let io = |e: pathfarm_common::film::ImageError| match e {
            pathfarm_common::film::ImageError::Io { source, .. } => storage_error(&source, "the scene"),
            _ => ApiError::internal("storing the scene failed"),
        };
        write_atomic(&self.bundle_path(&id), bytes).map_err(io)?;
        let meta_json = serde_json::to_vec(&meta).map_err(|e| ApiError::internal(e.to_string()))?;
        write_atomic(&self.dir.join(format!("{id}.json")), &meta_json).map_err(io)?;
        tracing::info!(scene = %id, triangles = meta.triangles, "scene stored");
        self.entries().insert(id.clone(), (meta.clone(), now_ms()));
        Ok(SceneCreated { scene_id: id, triangles: meta.triangles, warnings: meta.warnings })
    }
}

/// Live event for dashboards: something about a job or a worker changed.
#[derive(Clone, Debug, Serialize)]
pub struct Event {
    pub kind: &'static str,
    pub id: u64,
    /// For `frame` events: the frame number that was written.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<i32>,
}

/// Latency histogram buckets in seconds (Prometheus `le`).
const BUCKETS: [f64; 10] = [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1];

#[derive(Default)]
pub struct Histogram {
    counts: [AtomicU64; BUCKETS.len() + 1],
    sum_ns: AtomicU64,
}

impl Histogram {
    pub fn observe(&self, d: Duration) {
        let s = d.as_secs_f64();
        let i = BUCKETS.iter().position(|&b| s <= b).unwrap_or(BUCKETS.len());
        self.counts[i].fetch_add(1, Ordering::Relaxed);
        self.sum_ns.fetch_add(d.as_nanos() as u64, Ordering::Relaxed);
    }

    fn render(&self, name: &str, help: &str, out: &mut String) {
        use std::fmt::Write;
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cum = 0;
        for (i, b) in BUCKETS.iter().enumerate() {
            cum += self.counts[i].load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{b}\"}} {cum}");
        }
        cum += self.counts[BUCKETS.len()].load(Ordering::Relaxed);
        let _ = writeln!(out, "{name}_bucket{{le=\"+Inf\"}} {cum}");
        let _ = writeln!(out, "{name}_sum {}", self.sum_ns.load(Ordering::Relaxed) as f64 * 1e-9);
        let _ = writeln!(out, "{name}_count {cum}");
    }
}

#[derive(Default)]
pub struct Metrics {
    pub bytes_received: AtomicU64,
    /// Open TCP connections.
    pub connections_open: AtomicU64,
    /// Connections closed by the header or idle timeout.
    pub connections_timed_out: AtomicU64,
    /// Quiet connections closed to make room under the connection cap.
    pub connections_evicted: AtomicU64,
    /// New connections closed because the cap was reached and every connection was busy.
    pub connections_refused: AtomicU64,
    pub merge_latency: Histogram,
    pub lease_latency: Histogram,
}

impl Metrics {
    pub fn observe_merge(&self, d: Duration) {
        self.merge_latency.observe(d);
    }
    pub fn observe_lease(&self, d: Duration) {
        self.lease_latency.observe(d);
    }
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
    pub webhooks: crate::webhook::Queue,
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
            let (done, checkpoints) = match &rec.frames {
                Some(frames) => store.sequence_state(id, frames),
                None => (Vec::new(), read_checkpoint(&store.checkpoint_path(id)).into_iter().collect()),
            };
            if let Err(e) = farm.restore(rec.clone(), checkpoints, &done, now) {
                tracing::error!(job = id, "{e}; restarting the job's unwritten frames from zero");
                farm.restore(rec, Vec::new(), &done, now).map_err(anyhow::Error::msg)?;
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
            webhooks: crate::webhook::Queue::new(config.webhooks.queue),
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
    pub fn persist_job(&self, id: JobId) -> Result<(), ApiError> {
        // Store lock first, then the farm's: a job deleted meanwhile is not written back (a
        // delete takes the farm's lock, then the store's, to remove the row).
        let store = self.store();
        let rec = self.farm.lock().job(id).ok().map(|j| j.record(now_ms()));
        match rec {
            Some(rec) => store.put_job(&rec).map_err(|e| database_error(&e, &format!("job {id}"))),
            None => Ok(()),
        }
    }

    pub fn persist_worker(&self, id: u64, name: &str, threads: u32) {
        if let Err(e) = self.store().put_worker(id, name, threads, now_ms()) {
            tracing::error!(worker = id, "persisting the worker failed: {e:#}");
        }
    }

    pub fn forget_job(&self, id: JobId) -> Result<(), ApiError> {
        self.store().delete_job(id).map_err(|e| database_error(&e, &format!("the deletion of job {id}")))
    }

    pub fn publish(&self, kind: &'static str, id: u64) {
        let _ = self.events.send(Event { kind, id, frame: None });
    }

    /// Frame `frame` of job `id` is written (and the job's progress changed).
    pub fn publish_frame(&self, id: JobId, frame: i32) {
        let _ = self.events.send(Event { kind: "frame", id, frame: Some(frame) });
        self.publish("job", id);
    }

    pub fn job_dir(&self, id: JobId) -> PathBuf {
        self.config.data_dir.join("jobs").join(id.to_string())
    }

    pub fn delete_job_files(&self, id: JobId) {
        let _ = std::fs::remove_dir_all(self.job_dir(id));
    }

    /// Prometheus text exposition.
    pub fn metrics_text(&self) -> String {
        use std::fmt::Write;
        let mut out = String::new();
        let (states, workers, c, leases) = {
            let farm = self.farm.lock();
            let mut states: HashMap<&'static str, u64> = HashMap::new();
            for j in farm.jobs() {
                *states.entry(j.state.as_str()).or_default() += 1;
            }
            let mut workers: HashMap<&'static str, u64> = HashMap::new();
            for w in farm.workers(now_ms()) {
                let s = match w.state {
                    pathfarm_common::protocol::WorkerState::Idle => "idle",
                    pathfarm_common::protocol::WorkerState::Busy => "busy",
                    pathfarm_common::protocol::WorkerState::Offline => "offline",
                };
                *workers.entry(s).or_default() += 1;
            }
            (states, workers, farm.counters.clone(), farm.leases_held())
        };
        let _ = writeln!(out, "# HELP pathfarm_jobs Jobs by state.\n# TYPE pathfarm_jobs gauge");
        for s in ["queued", "running", "paused", "completed", "failed", "cancelled"] {
            let _ = writeln!(out, "pathfarm_jobs{{state=\"{s}\"}} {}", states.get(s).copied().unwrap_or(0));
        }
        let _ = writeln!(out, "# HELP pathfarm_workers Workers by state.\n# TYPE pathfarm_workers gauge");
        for s in ["idle", "busy", "offline"] {
            let _ = writeln!(out, "pathfarm_workers{{state=\"{s}\"}} {}", workers.get(s).copied().unwrap_or(0));
        }
        let counters = [
            ("pathfarm_units_leased_total", "Units handed out.", c.units_leased),
            ("pathfarm_units_merged_total", "Units merged into films.", c.units_merged),
            ("pathfarm_units_failed_total", "Units reported failed by workers.", c.units_failed),
            ("pathfarm_leases_expired_total", "Leases that expired.", c.leases_expired),
            (
                "pathfarm_results_rejected_total",
                "Results refused (lost lease, corrupt, mismatched).",
                c.results_rejected,
            ),
            ("pathfarm_samples_total", "Pixel samples merged.", c.samples_merged),
            (
                "pathfarm_bytes_received_total",
                "Request body bytes received (scenes and results).",
                self.metrics.bytes_received.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_timed_out_total",
                "Connections closed by the header or idle timeout.",
                self.metrics.connections_timed_out.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_evicted_total",
                "Quiet connections closed to make room under --max-connections.",
                self.metrics.connections_evicted.load(Ordering::Relaxed),
            ),
            (
                "pathfarm_connections_refused_total",
                "New connections closed at --max-connections with every connection busy.",
                self.metrics.connections_refused.load(Ordering::Relaxed),
            ),
        ];
        for (name, help, v) in counters {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
        }
        let _ = writeln!(
            out,
            "# HELP pathfarm_leases_held Leases currently held.\n# TYPE pathfarm_leases_held gauge\npathfarm_leases_held {leases}"
        );
        let _ = writeln!(
            out,
            "# HELP pathfarm_connections_open Open TCP connections.\n# TYPE pathfarm_connections_open gauge\npathfarm_connections_open {}",
            self.metrics.connections_open.load(Ordering::Relaxed)
        );
        self.metrics.merge_latency.render("pathfarm_merge_seconds", "Time to decode and merge a result.", &mut out);
        self.metrics.lease_latency.render("pathfarm_lease_seconds", "Time to pick a unit for a lease.", &mut out);
        out
    }
}

/// Writes `image.exr` and `preview.png` of a job atomically.
/// The PNG is exposed as the job asks (`exposure`, `auto_exposure`); returns the EV it used.
pub fn write_outputs(
    dir: &Path,
    layers: &ImageLayers,
    exposure: pathfarm_common::film::PreviewExposure,
) -> anyhow::Result<f32> {
    std::fs::create_dir_all(dir)?;
    write_atomic(&dir.join("image.exr"), &layers.encode_exr()?)?;
    let ev = layers.preview_ev(exposure);
    write_atomic(&dir.join("preview.png"), &layers.encode_png(ev)?)?;
    Ok(ev)
}

/// Expires leases every `expiry_tick_ms` (a quarter second), prunes workers, wakes lease waiters
/// when units came back, collects old scenes and queues the jobs' webhook events.
async fn maintenance_loop(state: Arc<AppState>) {
    let mut tick = tokio::time::interval(Duration::from_millis(state.config.farm.expiry_tick_ms.max(1)));
    loop {
        tick.tick().await;
        let (expired, pruned) = {
            let mut farm = state.farm.lock();
            let now = now_ms();
            (farm.expire(now), farm.prune_workers(now))
        };
        if expired > 0 {
            tracing::warn!(expired, "leases expired; units are pending again");
            state.work_ready.notify_waiters();
        }
        if !pruned.is_empty() {
            if let Err(e) = state.store().delete_workers(&pruned) {
                tracing::error!("deleting pruned worker rows failed: {e:#}");
            }
            state.publish("worker", pruned[0]);
        }
        if let Some(after) = state.config.scene_gc_after_ms {
            collect_scenes(&state, now_ms().saturating_sub(after));
        }
        crate::webhook::enqueue_pending(&state);
    }
}

/// Removes the scenes stored at or before `stored_before` (Unix ms) that no job, in any state,
/// references. The farm lock is held throughout, so no job can be submitted for a scene being
/// removed. Returns the removed ids.
pub fn collect_scenes(state: &AppState, stored_before: u64) -> Vec<String> {
    let farm = state.farm.lock();
    let referenced = |id: &str| farm.jobs().any(|j| j.scene_id == id);
    let mut removed = Vec::new();
    for id in state.scenes.unreferenced_before(stored_before, &referenced) {
        match state.scenes.remove(&id) {
            Ok(_) => {
                tracing::info!(scene = %id, "unreferenced scene garbage-collected");
                removed.push(id);
            }
            Err(e) => tracing::error!(scene = %id, error = %e, "removing an unreferenced scene failed"),
        }
    }
    removed
}

/// A sequence's merged frame: job, index in its frame set, frame number, film.
type FrameToWrite = (JobId, usize, i32, Arc<Film>, pathfarm_common::film::PreviewExposure);

type FrameWrite =
    (PathBuf, Arc<Film>, pathfarm_common::film::PreviewExposure, tokio::sync::oneshot::Sender<anyhow::Result<()>>);

/// One thread that resolves and encodes sequence frames, one after the other. A frame's
/// working set (float layers, EXR and PNG buffers: ~100 MiB at 1080p) is then reused frame
/// after frame in one allocator arena; spread over the blocking pool's threads, glibc kept a
/// copy per thread and a 1080p sequence's RSS climbed from 1 to 4.5 GiB over 40 frames.
struct FrameWriter {
    tx: std::sync::mpsc::Sender<FrameWrite>,
}

impl FrameWriter {
    fn start() -> std::io::Result<Self> {
        let (tx, rx) = std::sync::mpsc::channel::<FrameWrite>();
        std::thread::Builder::new().name("frame-writer".into()).spawn(move || {
            for (dir, film, exposure, reply) in rx {
                let r = (|| -> anyhow::Result<()> {
                    let ev = write_outputs(&dir, &film.resolve(), exposure)?;
                    tracing::debug!(dir = %dir.display(), preview_ev = ev, "frame written");
                    // The frame is written: its checkpoint is of no more use.
                    match std::fs::remove_file(dir.join("checkpoint.bin")) {
                        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e.into()),
                        _ => Ok(()),
                    }
                })();
                drop(film);
                let _ = reply.send(r);
            }
        })?;
        Ok(Self { tx })
    }

    /// Writes `dir/image.exr` and `preview.png` of `film`; `Err` also when the thread is gone.
    async fn write(
        &self,
        dir: PathBuf,
        film: Arc<Film>,
        exposure: pathfarm_common::film::PreviewExposure,
    ) -> Result<anyhow::Result<()>, String> {
        let (reply, answer) = tokio::sync::oneshot::channel();
        self.tx.send((dir, film, exposure, reply)).map_err(|_| "the frame writer thread is gone".to_string())?;
        answer.await.map_err(|_| "the frame writer thread panicked".to_string())
    }
}

/// Writes each job's EXR and PNG after a pass completes, at most every `output_interval` per
/// running job, and always when the job ends.
async fn output_loop(state: Arc<AppState>) {
    let mut last: HashMap<JobId, Instant> = HashMap::new();
    let writer = match FrameWriter::start() {
        Ok(w) => w,
        Err(e) => {
            tracing::error!("cannot start the frame writer thread: {e}");
            return;
        }
    };
    loop {
        let _ = tokio::time::timeout(Duration::from_millis(500), state.output_ready.notified()).await;
        let (due, frames): (Vec<(JobId, JobState, pathfarm_common::film::PreviewExposure)>, Vec<FrameToWrite>) = {
            let mut farm = state.farm.lock();
            let mut frames = Vec::new();
            let due = farm
                .jobs_mut()
                .filter(|j| j.output_dirty)
                .filter(|j| {
                    j.sequence
                        || j.state.is_finished()
                        || last.get(&j.id).is_none_or(|t| t.elapsed() >= state.config.output_interval)
                })
                .filter_map(|j| {
                    j.output_dirty = false;
                    let exposure = pathfarm_common::film::PreviewExposure::of(&j.settings);
                    if j.sequence {
                        frames.extend(j.frames_to_write().into_iter().map(|(i, f, film)| (j.id, i, f, film, exposure)));
                        None
                    } else {
                        Some((j.id, j.state, exposure))
                    }
                })
                .collect();
            (due, frames)
        };
        // A sequence's merged frames: written once, then their films are dropped.
        for (id, index, frame, film, exposure) in frames {
            let dir = crate::store::frame_dir(&state.job_dir(id), frame);
            match writer.write(dir, film, exposure).await {
                Ok(Ok(())) => {
                    let (written, exists) = {
                        let mut farm = state.farm.lock();
                        (farm.frame_written(id, index).is_some(), farm.job(id).is_ok())
                    };
                    if written {
                        tracing::info!(job = id, frame, "frame written");
                        state.publish_frame(id, frame);
                        // Its film is freed: the next frame may start now.
                        state.work_ready.notify_waiters();
                    } else if !exists {
                        // Deleted while its frame was being written: no files may remain.
                        state.delete_job_files(id);
                    }
                }
                Ok(Err(e)) => {
                    tracing::error!(job = id, frame, "writing the frame's images failed: {e:#}; retrying");
                    if let Ok(j) = state.farm.lock().job_mut(id) {
                        j.output_dirty = true;
                    }
                }
                Err(e) => tracing::error!(job = id, frame, "frame writer panicked: {e}"),
            }
        }
        for (id, job_state, exposure) in due {
            last.insert(id, Instant::now());
            let dir = state.job_dir(id);
            let st = state.clone();
            // Resolved band by band, so the farm lock is never held for a whole film.
            let r = tokio::task::spawn_blocking(move || -> anyhow::Result<f32> {
                let layers = crate::api::resolve_banded(&st, id).map_err(|e| anyhow::anyhow!(e.message))?;
                write_outputs(&dir, &layers, exposure)
            })
            .await;
            match r {
                Ok(Ok(ev)) => tracing::debug!(job = id, state = job_state.as_str(), preview_ev = ev, "images written"),
                Ok(Err(e)) => tracing::error!(job = id, "writing images failed: {e:#}"),
                Err(e) => tracing::error!(job = id, "image writer panicked: {e}"),
            }
            state.publish("image", id);
        }
    }
}

/// Checkpoints every job whose merged units or state changed: the film with its merged set
/// (atomically, one file), then the job's row.
async fn checkpoint_loop(state: Arc<AppState>) {
    // Per job: what the last checkpoint held, and when the next one may start. A checkpoint
    // copies the film under the farm lock and compresses it; for big films that is costly, so
    // the next one waits at least nine times as long as the last took (at most ~10% of a core),
    // unless the job's state or priority changed.
    let mut seen: HashMap<JobId, ((u64, JobState, i32), Instant)> = HashMap::new();
    loop {
        tokio::time::sleep(state.config.checkpoint_interval).await;
        let due: Vec<JobId> = {
            let farm = state.farm.lock();
            farm.jobs()
                .filter(|j| match seen.get(&j.id) {
                    None => true,
                    Some(((merged, st, prio), next)) => {
                        (*st, *prio) != (j.state, j.priority) || (*merged != j.units_merged && Instant::now() >= *next)
                    }
                })
                .map(|j| j.id)
                .collect()
        };
        for id in due {
            let t0 = Instant::now();
            // One film copy at a time: the lock is held for one copy, and a sequence's frames
            // in progress that merged units since their last checkpoint are copied and written
            // one after the other, each to its own file (the job's row with each).
            let mut outcome = None;
            loop {
                let snapshot = {
                    let mut farm = state.farm.lock();
                    farm.job_mut(id).ok().map(|j| {
                        let key = (j.units_merged, j.state, j.priority);
                        (key, j.record(now_ms()), j.sequence, j.take_checkpoints(false, 1))
                    })
                };
                let Some((key, rec, sequence, cps)) = snapshot else { break };
                let more = sequence && !cps.is_empty();
                let st = state.clone();
                let r = tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
                    for cp in &cps {
                        let path = if sequence {
                            st.store().frame_checkpoint_path(id, cp.frame)
                        } else {
                            st.store().checkpoint_path(id)
                        };
                        write_checkpoint(&path, cp)?;
                    }
                    // Only a job that still exists gets its row written back: a DELETE that ran
                    // during the snapshot or the write must not be undone (it came back after a
                    // restart). Lock order: store, then farm (as in persist_job).
                    let store = st.store();
                    if st.farm.lock().job(id).is_ok() {
                        store.put_job(&rec)?;
                    } else {
                        drop(store);
                        let _ = std::fs::remove_dir_all(st.job_dir(id));
                    }
                    Ok(())
                })
                .await;
                let ok = matches!(r, Ok(Ok(())));
                outcome = Some((key, r));
                if !ok || !more {
                    break;
                }
            }
            match outcome {
                Some((key, Ok(Ok(())))) => {
                    let took = t0.elapsed();
                    seen.insert(id, (key, Instant::now() + took * 9));
                }
                Some((_, Ok(Err(e)))) => tracing::error!(job = id, "checkpoint failed: {e:#}"),
                Some((_, Err(e))) => tracing::error!(job = id, "checkpoint task failed: {e}"),
                None => {}
            }
        }
    }
}

/// A running coordinator.
pub struct Server {
    pub addr: SocketAddr,
    pub state: Arc<AppState>,
    task: tokio::task::JoinHandle<()>,
}

impl Server {
    /// Binds, starts the background loops and serves until dropped or the task ends.
    pub async fn start(config: ServerConfig) -> anyhow::Result<Self> {
        let state = Arc::new(AppState::new(config.clone())?);
        let listener = tokio::net::TcpListener::bind(config.listen).await?;
        let addr = listener.local_addr()?;
        write_atomic(&config.data_dir.join("coordinator.addr"), addr.to_string().as_bytes())?;
        tokio::spawn(maintenance_loop(state.clone()));
        tokio::spawn(output_loop(state.clone()));
        tokio::spawn(checkpoint_loop(state.clone()));
        tokio::spawn(crate::webhook::run(state.clone()));
        let tls = match &config.tls {
            Some((cert, key)) => Some(crate::conn::tls_acceptor(cert, key)?),
            None => None,
        };
        let app = crate::api::router(state.clone());
        let mut limits = config.conn;
        limits.max_connections = crate::conn::fit_to_fd_limit(limits.max_connections);
        let scheme = if tls.is_some() { "https" } else { "http" };
        let task = tokio::spawn(crate::conn::serve(listener, app, limits, state.clone(), tls));
        tracing::info!(
            %addr,
            data_dir = %config.data_dir.display(),
            max_connections = limits.max_connections,
            header_timeout_ms = limits.header_timeout.as_millis() as u64,
            idle_timeout_ms = limits.idle_timeout.as_millis() as u64,
            scheme,
            "coordinator listening"
        );
        Ok(Self { addr, state, task })
    }

    pub fn url(&self) -> String {
        let scheme = if self.state.config.tls.is_some() { "https" } else { "http" };
        format!("{scheme}://{}", self.addr)
    }

    /// Serves until the process gets SIGINT or SIGTERM.
    pub async fn run_until_signal(self) -> anyhow::Result<()> {
        shutdown_signal().await;
        tracing::info!("shutting down");
        self.task.abort();
        Ok(())
    }
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = term => {},
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
