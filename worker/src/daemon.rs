//! The worker daemon: registers with a coordinator, long-polls for units, renders them on all
//! cores, heartbeats while rendering, uploads results with retries, and on SIGTERM finishes its
//! unit and leaves.
//!
//! Blocking HTTP (reqwest) on plain threads: the daemon does one thing at a time, and the render
//! itself runs on a rayon pool.

use crate::render::wide::SimdLevel;
use crate::render::{Renderer, UnitResult};
use anyhow::{Context, bail};
use pathfarm_common::protocol::{
    API, DenoiseInput, JobId, LeaseGrant, LeaseKind, RegisterRequest, Registered, ReleaseRequest, UnitResultFrame,
    WORKER_SECRET_HEADER, WorkerId,
};
use pathfarm_common::routes;
use pathfarm_common::scene::bundle::{is_scene_id, scene_id, unpack_bundle};
use pathfarm_common::scene::{LoadOptions, Scene, load_job_environment, load_scene};
use reqwest::StatusCode;
use reqwest::blocking::{Client, RequestBuilder, Response};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// `pathfarm-worker run` arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct RunArgs {
    /// Coordinator base URL, e.g. http://127.0.0.1:8080
    #[arg(long, env = "PATHFARM_COORDINATOR")]
    pub coordinator: String,
    /// Worker token (bearer).
    #[arg(long, env = "PATHFARM_WORKER_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Where downloaded scenes are kept (default: a pathfarm folder in the system temp dir).
    #[arg(long)]
    pub cache_dir: Option<PathBuf>,
    /// Most disk the scene cache may use, in MiB: least recently used scenes are removed beyond
    /// it (never the one in use).
    #[arg(long, env = "PATHFARM_CACHE_MAX_MB", default_value_t = 4096)]
    pub cache_max_mb: u64,
    /// Name shown on the dashboard (default: host name and process id).
    #[arg(long)]
    pub name: Option<String>,
    /// Tags this worker offers besides its automatic ones (`cpu`, `avx2`/`avx512f`, `denoise`),
    /// a comma list such as `highmem,fast`: jobs that `require` tags are leased only to workers
    /// having all of them. Lowercase letters, digits, `_` and `-`; 16 tags at most in all.
    #[arg(long, env = "PATHFARM_WORKER_TAGS", value_delimiter = ',')]
    pub tags: Vec<String>,
    /// PEM certificate(s) to trust for an https:// coordinator besides the system's roots (a
    /// private CA or a self-signed certificate).
    #[arg(long, env = "PATHFARM_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// Take no denoise steps even when built with OIDN (the tag `denoise` is not reported).
    #[arg(long, env = "PATHFARM_WORKER_NO_DENOISE")]
    pub no_denoise: bool,
}

/// Tags every worker reports by itself: `cpu`; the SIMD level its renderer runs at
/// ([`simd_tag`]); `denoise` when the binary was built with OIDN.
pub fn automatic_tags() -> Vec<String> {
    automatic_tags_at(SimdLevel::detect())
}

/// [`automatic_tags`] of a worker whose renderer runs at `level`.
fn automatic_tags_at(level: SimdLevel) -> Vec<String> {
    let mut tags = vec!["cpu".to_string()];
    tags.extend(simd_tag(level).map(String::from));
    if crate::denoise::AVAILABLE {
        tags.push("denoise".into());
    }
    tags
}

/// The tag of the level the renderer's kernels run at: `avx512f` where they run compiled for
/// x86-64-v4 (AVX-512 F, VL, BW, DQ and CD), `avx2` for x86-64-v3 (AVX2 with FMA, BMI1/2,
/// LZCNT and POPCNT), none for the baseline. From the level, not from one CPU flag: a CPU
/// (or a virtual machine's masked one) with `avx512f` but not the rest renders with the AVX2
/// kernels, and one with AVX2 but not FMA with the baseline, and a job that requires a tag is
/// asking for the speed that goes with it.
pub fn simd_tag(level: SimdLevel) -> Option<&'static str> {
    match level {
        SimdLevel::Avx512 => Some("avx512f"),
        SimdLevel::Avx2 => Some("avx2"),
        SimdLevel::Baseline => None,
    }
}

/// The automatic tags followed by `extra` (trimmed, empty entries and repeats dropped),
/// validated as the coordinator does.
pub fn worker_tags(extra: &[String]) -> anyhow::Result<Vec<String>> {
    let mut tags = automatic_tags();
    for t in extra.iter().map(|t| t.trim()).filter(|t| !t.is_empty()) {
        if !tags.iter().any(|have| have == t) {
            tags.push(t.to_string());
        }
    }
    pathfarm_common::protocol::validate_tags(&tags, "--tags").map_err(anyhow::Error::msg)?;
    Ok(tags)
}

/// Daemon settings.
#[derive(Clone, Debug)]
pub struct DaemonConfig {
    pub coordinator: String,
    pub token: Option<String>,
    pub threads: usize,
    pub cache_dir: PathBuf,
    /// Disk budget of the scene cache, in bytes (see [`prune_scene_cache`]).
    pub cache_max_bytes: u64,
    pub name: String,
    /// Long-poll time of a lease request.
    pub lease_wait: Duration,
    /// Sent at registration (see [`worker_tags`]).
    pub tags: Vec<String>,
    /// Extra trusted certificates (`--ca-cert`); `None`: `PATHFARM_CA_CERT` if set.
    pub ca_cert: Option<PathBuf>,
}

impl DaemonConfig {
    pub fn from_args(args: RunArgs) -> anyhow::Result<Self> {
        let threads = args.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
        let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "worker".into());
        Ok(Self {
            tags: worker_tags(&args.tags)?.into_iter().filter(|t| !(args.no_denoise && t == "denoise")).collect(),
            coordinator: args.coordinator.trim_end_matches('/').to_string(),
            token: args.token,
            threads: threads.max(1),
            cache_dir: args.cache_dir.unwrap_or_else(|| std::env::temp_dir().join("pathfarm-worker-cache")),
            cache_max_bytes: args.cache_max_mb.saturating_mul(1 << 20),
            name: args.name.unwrap_or_else(|| format!("{host}-{}", std::process::id())),
            lease_wait: Duration::from_secs(5),
            ca_cert: args.ca_cert,
        })
    }
}

/// Runs the daemon until SIGTERM/SIGINT.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let shutdown = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(sig, shutdown.clone()).context("installing the signal handler")?;
    }
    Daemon::new(DaemonConfig::from_args(args)?)?.run(&shutdown)
}

/// Pseudo-random jitter in `[0, 1)` without a global RNG: hashes the clock.
fn jitter() -> f64 {
    let nanos = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
    let mut x = u64::from(nanos) ^ 0x9E37_79B9_7F4A_7C15;
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    (x >> 11) as f64 / (1u64 << 53) as f64
}

/// Sleeps for attempt `n`'s backoff (exponential, capped at 5 s, with full jitter), waking
/// early on shutdown. Returns false if shutting down.
fn backoff(n: u32, shutdown: &AtomicBool) -> bool {
    let cap = (100.0 * 2f64.powi(n.min(6) as i32)).min(5000.0);
    let until = Instant::now() + Duration::from_millis((cap * (0.5 + 0.5 * jitter())) as u64);
    while Instant::now() < until {
        if shutdown.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    true
}

/// The daemon's state.
pub struct Daemon {
    cfg: DaemonConfig,
    http: Client,
    pool: rayon::ThreadPool,
    worker_id: Option<WorkerId>,
    /// This worker's own secret, from the registration; sent on every lease, heartbeat, result
    /// and release request.
    secret: String,
    heartbeat: Duration,
    /// The scene of the last unit, by scene id, and the folder of its scene file.
    scene: Option<(String, Arc<Scene>, PathBuf)>,
    /// Renderers (BVH and all) of the last (job, frame)s.
    renderers: RendererCache<Renderer>,
}

/// Prepared renderers of the last few (job, settings) pairs: a sequence's units come frame by
/// frame (settings differ in `frame`), so a frame's scene is posed and its BVH built once per
/// worker, not once per unit; two frames are kept, for the tail of one frame interleaving with
/// the start of the next.
pub struct RendererCache<R> {
    entries: std::collections::VecDeque<(JobId, pathfarm_common::job::RenderSettings, Arc<R>)>,
    capacity: usize,
}

impl<R> RendererCache<R> {
    pub fn new(capacity: usize) -> Self {
        Self { entries: std::collections::VecDeque::new(), capacity: capacity.max(1) }
    }

    /// The cached renderer for (job, settings), or a new one from `build` (which then evicts
    /// the least recently used beyond the capacity).
    pub fn get_or_build(
        &mut self,
        job: JobId,
        settings: &pathfarm_common::job::RenderSettings,
        build: impl FnOnce() -> anyhow::Result<R>,
    ) -> anyhow::Result<Arc<R>> {
        if let Some(i) = self.entries.iter().position(|(j, s, _)| *j == job && s == settings) {
            let hit = self.entries.remove(i).expect("position is in range");
            let r = hit.2.clone();
            self.entries.push_back(hit);
            return Ok(r);
        }
        // Another job's renderers are of no more use: free their memory before building.
        self.entries.retain(|(j, _, _)| *j == job);
        while self.entries.len() >= self.capacity {
            self.entries.pop_front();
        }
        let r = Arc::new(build()?);
        self.entries.push_back((job, settings.clone(), r.clone()));
        Ok(r)
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

impl Daemon {
    pub fn new(cfg: DaemonConfig) -> anyhow::Result<Self> {
        let http = with_ca_cert(
            Client::builder().timeout(Duration::from_secs(120)).connect_timeout(Duration::from_secs(5)),
            cfg.ca_cert.as_deref(),
        )?
        .build()
        .context("building the HTTP client")?;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads)
            .thread_name(|i| format!("render-{i}"))
            .build()
            .context("building the render thread pool")?;
        std::fs::create_dir_all(&cfg.cache_dir)
            .with_context(|| format!("creating the cache dir {}", cfg.cache_dir.display()))?;
        Ok(Self {
            cfg,
            http,
            pool,
            worker_id: None,
            secret: String::new(),
            heartbeat: Duration::from_secs(2),
            scene: None,
            renderers: RendererCache::new(2),
        })
    }

    fn url(&self, path: &str) -> String {
        format!("{}{API}{path}", self.cfg.coordinator)
    }

    fn auth(&self, rb: RequestBuilder) -> RequestBuilder {
        match &self.cfg.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }

    /// A request of this worker: the bearer token and its own secret.
    fn as_worker(&self, rb: RequestBuilder) -> RequestBuilder {
        self.auth(rb).header(WORKER_SECRET_HEADER, &self.secret)
    }

    fn register(&mut self, shutdown: &AtomicBool) -> anyhow::Result<()> {
        let body = RegisterRequest {
            name: self.cfg.name.clone(),
            threads: self.cfg.threads as u32,
            tags: self.cfg.tags.clone(),
        };
        let mut attempt = 0;
        loop {
            let r = self.auth(self.http.post(self.url(routes::WORKER_REGISTER)).json(&body)).send();
            match r {
                Ok(resp) if resp.status().is_success() => {
                    let reg: Registered = resp.json().context("register answer")?;
                    tracing::info!(worker = reg.worker_id, name = %self.cfg.name, tags = ?self.cfg.tags, simd = SimdLevel::detect().name(), "registered");
                    self.worker_id = Some(reg.worker_id);
                    self.secret = reg.worker_secret;
                    self.heartbeat = Duration::from_millis(reg.heartbeat_ms.max(100));
                    return Ok(());
                }
                Ok(resp) if resp.status() == StatusCode::UNAUTHORIZED || resp.status() == StatusCode::FORBIDDEN => {
                    bail!("the coordinator refused the worker token: {}", resp.text().unwrap_or_default());
                }
                Ok(resp) => tracing::warn!(status = %resp.status(), "register failed; retrying"),
                Err(e) => tracing::warn!("coordinator unreachable ({e}); retrying"),
            }
            attempt += 1;
            if !backoff(attempt, shutdown) {
                bail!("shutting down before registering");
            }
        }
    }

    /// Serves units until `shutdown` is set; a unit in progress is finished and uploaded.
    pub fn run(&mut self, shutdown: &AtomicBool) -> anyhow::Result<()> {
        let mut failures = 0u32;
        while !shutdown.load(Ordering::Relaxed) {
            let Some(worker) = self.worker_id else {
                match self.register(shutdown) {
                    Ok(()) => continue,
                    Err(e) if shutdown.load(Ordering::Relaxed) => {
                        tracing::info!("{e}");
                        break;
                    }
                    Err(e) => return Err(e),
                }
            };
            let wait = self.cfg.lease_wait.as_millis();
            let resp = self
                .as_worker(
                    self.http
                        .post(self.url(&format!("{}?wait_ms={wait}", routes::fill(routes::WORKER_LEASE, &[&worker])))),
                )
                .send();
            let grant: LeaseGrant = match resp {
                Ok(r) if r.status() == StatusCode::OK => match r.json() {
                    Ok(g) => g,
                    Err(e) => {
                        tracing::warn!("unreadable lease: {e}");
                        continue;
                    }
                },
                Ok(r) if r.status() == StatusCode::NO_CONTENT => {
                    failures = 0;
                    continue;
                }
                Ok(r) if r.status() == StatusCode::NOT_FOUND || r.status() == StatusCode::FORBIDDEN => {
                    tracing::warn!(
                        status = %r.status(),
                        "the coordinator does not know this worker or its secret (restarted?); registering again"
                    );
                    self.worker_id = None;
                    continue;
                }
                Ok(r) => {
                    tracing::warn!(status = %r.status(), "lease request failed");
                    failures += 1;
                    backoff(failures, shutdown);
                    continue;
                }
                Err(e) => {
                    tracing::warn!("coordinator unreachable: {e}");
                    failures += 1;
                    backoff(failures, shutdown);
                    continue;
                }
            };
            failures = 0;
            self.work(worker, grant, shutdown);
        }
        tracing::info!("worker stopped");
        Ok(())
    }

    /// Renders one leased unit and delivers it (or reports the failure).
    fn work(&mut self, worker: WorkerId, grant: LeaseGrant, shutdown: &AtomicBool) {
        if grant.kind == LeaseKind::Denoise {
            return self.denoise_step(worker, &grant, shutdown);
        }
        let lease = grant.lease_id;
        tracing::debug!(
            lease,
            job = grant.job_id,
            frame = grant.unit.frame,
            pass = grant.unit.pass,
            tile = grant.unit.tile,
            "rendering unit"
        );
        // A panic while loading the scene or building the renderer fails this unit, never
        // the worker (a worker that exits leaves the unit to crash the next one).
        let prepared = guarded("preparing the unit", || self.renderer_for(&grant));
        let renderer = match prepared {
            Ok(r) => r,
            Err(reason) => {
                tracing::error!(lease, job = grant.job_id, "cannot render: {reason}");
                self.renderers = RendererCache::new(2);
                self.scene = None;
                self.release(lease, true, &reason);
                return;
            }
        };
        let t0 = Instant::now();
        let result = self.render_with_heartbeats(worker, &renderer, &grant);
        let result = match result {
            Ok(r) => r,
            Err(reason) => {
                tracing::error!(lease, "render failed: {reason}");
                self.release(lease, true, &reason);
                return;
            }
        };
        let frame = UnitResultFrame {
            lease_id: lease,
            job_id: grant.job_id,
            unit: grant.unit,
            accum: result.accum,
            splats: result.splats,
        };
        let body = frame.encode();
        tracing::debug!(lease, ms = t0.elapsed().as_millis() as u64, bytes = body.len(), "unit rendered");
        if shutdown.load(Ordering::Relaxed) {
            tracing::info!(lease, "stop requested: delivering the unit in progress before exiting");
        }
        self.upload(lease, body, shutdown);
    }

    /// A denoise step: fetches the frame's colour, albedo and normal, denoises them (OIDN, under
    /// catch_unwind, heartbeating meanwhile) and uploads the layer; any failure releases the
    /// lease as failed, with the reason.
    fn denoise_step(&mut self, worker: WorkerId, grant: &LeaseGrant, shutdown: &AtomicBool) {
        let lease = grant.lease_id;
        let (w, h) = (grant.settings.width, grant.settings.height);
        tracing::debug!(lease, job = grant.job_id, frame = grant.unit.frame, pass = grant.unit.pass, "denoising");
        let input = guarded("fetching the denoise input", || {
            crate::denoise::ensure_available()?;
            let resp = self
                .as_worker(self.http.get(self.url(&routes::fill(routes::LEASE_DENOISE_INPUT, &[&lease]))))
                .send()?;
            if !resp.status().is_success() {
                let status = resp.status();
                bail!("denoise input: {status} {}", text(resp));
            }
            Ok(DenoiseInput::decode_expecting(&resp.bytes()?, w, h)?)
        });
        let denoised = input.and_then(|input| {
            let t0 = Instant::now();
            let r = self.with_heartbeats(worker, |_| guarded("denoising", || crate::denoise::denoise_input(&input)));
            tracing::debug!(lease, ms = t0.elapsed().as_millis() as u64, "denoised");
            r
        });
        match denoised {
            Ok(rgb) => {
                let body = pathfarm_common::protocol::encode_denoised(w, h, &rgb);
                self.upload_to(lease, routes::LEASE_DENOISED, body, shutdown);
            }
            Err(reason) => {
                tracing::error!(lease, job = grant.job_id, "cannot denoise: {reason}");
                self.release(lease, true, &reason);
            }
        }
    }

    /// Runs `f` while a thread heartbeats every `heartbeat` (a lost registration is noticed).
    /// The thread waits on a channel, so it ends the moment `f` does.
    fn with_heartbeats<T>(&mut self, worker: WorkerId, f: impl FnOnce(&Self) -> T) -> T {
        let (done, wake) = std::sync::mpsc::channel::<()>();
        let lost = AtomicBool::new(false);
        let this: &Self = self;
        let lost_flag = &lost;
        let result = std::thread::scope(|s| {
            s.spawn(move || {
                while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = wake.recv_timeout(this.heartbeat) {
                    let r = this
                        .as_worker(this.http.post(this.url(&routes::fill(routes::WORKER_HEARTBEAT, &[&worker]))))
                        .send();
                    if let Ok(resp) = r
                        && (resp.status() == StatusCode::NOT_FOUND || resp.status() == StatusCode::FORBIDDEN)
                    {
                        lost_flag.store(true, Ordering::Relaxed);
                    }
                }
            });
            let r = f(this);
            drop(done);
            r
        });
        if lost.load(Ordering::Relaxed) {
            self.worker_id = None;
        }
        result
    }

    fn render_with_heartbeats(
        &mut self,
        worker: WorkerId,
        renderer: &Renderer,
        grant: &LeaseGrant,
    ) -> Result<UnitResult, String> {
        let result = self.with_heartbeats(worker, |this| {
            // Adaptive sampling: the lease's mask names the blocks that get no samples; a mask
            // the renderer refuses (another tile's layout, bdpt) fails the unit.
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                this.pool.install(|| renderer.render_unit_masked(grant.tile, grant.pass, grant.mask.as_ref()))
            }))
        });
        match result {
            Ok(r) => r.map_err(|e| format!("cannot render the unit: {e}")),
            Err(p) => Err(format!("the renderer panicked: {}", panic_message(p.as_ref()))),
        }
    }

    fn upload(&self, lease: u64, body: Vec<u8>, shutdown: &AtomicBool) {
        self.upload_to(lease, routes::LEASE_RESULT, body, shutdown)
    }

    /// `PUT` to `route` (a lease route) with retries; a refusal releases the lease as failed.
    fn upload_to(&self, lease: u64, route: &str, body: Vec<u8>, shutdown: &AtomicBool) {
        for attempt in 0..10u32 {
            let r = self
                .as_worker(self.http.put(self.url(&routes::fill(route, &[&lease]))))
                .header("content-type", "application/octet-stream")
                .body(body.clone())
                .send();
            match r {
                Ok(resp) if resp.status().is_success() => return,
                Ok(resp) if resp.status() == StatusCode::CONFLICT => {
                    tracing::warn!(lease, "result refused: the lease is no longer ours (expired or job ended)");
                    return;
                }
                Ok(resp) if resp.status().is_client_error() => {
                    let status = resp.status();
                    let reason = format!("result refused with {status}: {}", text(resp));
                    tracing::error!(lease, "{reason}");
                    // Give the unit back: heartbeats would otherwise keep renewing a lease
                    // whose result will never arrive.
                    self.release(lease, true, &reason);
                    return;
                }
                Ok(resp) => tracing::warn!(lease, status = %resp.status(), attempt, "upload failed; retrying"),
                Err(e) => tracing::warn!(lease, attempt, "upload failed ({e}); retrying"),
            }
            // Keep retrying through a shutdown: the finished unit is worth delivering.
            let never = AtomicBool::new(false);
            backoff(attempt + 1, if attempt < 3 { &never } else { shutdown });
        }
        tracing::error!(lease, "giving up on uploading; releasing the unit so it is redone");
        self.release(lease, true, "upload failed after 10 attempts");
    }

    fn release(&self, lease: u64, failed: bool, reason: &str) {
        let body = ReleaseRequest { failed, reason: reason.chars().take(2000).collect() };
        let r = self
            .as_worker(self.http.post(self.url(&routes::fill(routes::LEASE_RELEASE, &[&lease]))).json(&body))
            .send();
        if let Err(e) = r {
            tracing::warn!(lease, "release failed ({e}); the lease will expire");
        }
    }

    /// The renderer for the grant's job and frame: reused across units of a (job, frame); the
    /// scene is downloaded once per scene id (disk cache) and parsed once per scene.
    fn renderer_for(&mut self, grant: &LeaseGrant) -> anyhow::Result<Arc<Renderer>> {
        let mut renderers = std::mem::replace(&mut self.renderers, RendererCache::new(2));
        let r = renderers.get_or_build(grant.job_id, &grant.settings, || {
            let (scene, scene_dir) = self.scene_for(&grant.scene_id)?;
            let environment = load_job_environment(&scene_dir, &grant.settings, &LoadOptions::default())?;
            Ok(Renderer::with_environment(&scene, &grant.settings, environment)?)
        });
        self.renderers = renderers;
        r
    }

    fn scene_for(&mut self, id: &str) -> anyhow::Result<(Arc<Scene>, PathBuf)> {
        if !is_scene_id(id) {
            bail!("scene id {id:?} is not a SHA-256");
        }
        if let Some((cached, s, folder)) = &self.scene
            && cached == id
        {
            return Ok((s.clone(), folder.clone()));
        }
        let bundle_path = self.cfg.cache_dir.join(format!("{id}.bundle"));
        let bytes = match std::fs::read(&bundle_path) {
            Ok(b) if scene_id(&b) == id => {
                // Used now: the cache evicts the least recently used scenes first.
                if let Ok(f) = std::fs::File::options().append(true).open(&bundle_path) {
                    let _ = f.set_modified(std::time::SystemTime::now());
                }
                b
            }
            _ => {
                let resp = self.auth(self.http.get(self.url(&routes::fill(routes::SCENE, &[&id])))).send()?;
                if !resp.status().is_success() {
                    let status = resp.status();
                    bail!("downloading scene {id}: {status} {}", text(resp));
                }
                let b = resp.bytes()?.to_vec();
                if scene_id(&b) != id {
                    bail!("downloaded scene does not hash to {id}");
                }
                pathfarm_common::film::write_atomic(&bundle_path, &b)?;
                match prune_scene_cache(&self.cfg.cache_dir, id, self.cfg.cache_max_bytes) {
                    Ok(removed) if !removed.is_empty() => {
                        tracing::info!(
                            removed = removed.len(),
                            "scene cache over its budget: least recently used scenes removed"
                        );
                    }
                    Ok(_) => {}
                    Err(e) => tracing::warn!("pruning the scene cache: {e}"),
                }
                b
            }
        };
        // Unpack into a private folder and rename it into place: workers sharing a cache dir
        // never see each other's half-written files (bundles are immutable, so the first
        // complete folder wins).
        let dir = self.cfg.cache_dir.join(id);
        static SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let seq = SEQ.fetch_add(1, Ordering::Relaxed);
        let tmp = self.cfg.cache_dir.join(format!(".{id}.{}.{seq}", std::process::id()));
        let main = unpack_bundle(&bytes, &tmp)?;
        let rel = main.strip_prefix(&tmp).map(PathBuf::from).unwrap_or_else(|_| PathBuf::from("scene.glb"));
        if dir.exists() || std::fs::rename(&tmp, &dir).is_err() {
            let _ = std::fs::remove_dir_all(&tmp);
        }
        let main = dir.join(rel);
        let scene = Arc::new(load_scene(&main, &LoadOptions::default())?);
        let folder = main.parent().map_or_else(|| dir.clone(), PathBuf::from);
        self.scene = Some((id.to_string(), scene.clone(), folder.clone()));
        Ok((scene, folder))
    }
}

/// Keeps the scene cache in `dir` within `max_bytes`: each scene is its `ID.bundle` file plus its
/// unpacked `ID/` folder; the least recently used (by the bundle's modification time, refreshed
/// on use) go first, never `keep` (the scene being loaded). Returns the ids removed.
pub fn prune_scene_cache(dir: &std::path::Path, keep: &str, max_bytes: u64) -> std::io::Result<Vec<String>> {
    fn size(p: &std::path::Path) -> u64 {
        match std::fs::symlink_metadata(p) {
            Ok(m) if m.is_dir() => {
                std::fs::read_dir(p).map(|d| d.flatten().map(|e| size(&e.path())).sum()).unwrap_or(0)
            }
            Ok(m) => m.len(),
            Err(_) => 0,
        }
    }
    let mut scenes = Vec::new();
    for e in std::fs::read_dir(dir)?.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(id) = name.strip_suffix(".bundle").filter(|id| is_scene_id(id)) else { continue };
        let used = e.metadata().and_then(|m| m.modified()).unwrap_or(std::time::UNIX_EPOCH);
        let bytes = size(&e.path()) + size(&dir.join(id));
        scenes.push((used, id.to_string(), bytes));
    }
    let mut total: u64 = scenes.iter().map(|s| s.2).sum();
    scenes.sort();
    let mut removed = Vec::new();
    for (_, id, bytes) in scenes {
        if total <= max_bytes {
            break;
        }
        if id == keep {
            continue;
        }
        let _ = std::fs::remove_dir_all(dir.join(&id));
        std::fs::remove_file(dir.join(format!("{id}.bundle")))?;
        total = total.saturating_sub(bytes);
        removed.push(id);
    }
    Ok(removed)
}

/// Trusts the PEM certificate(s) in `ca_cert` (else in `PATHFARM_CA_CERT`, if set) as well as
/// the system's roots, for a coordinator serving HTTPS with a private CA or a self-signed
/// certificate.
pub fn with_ca_cert(
    builder: reqwest::blocking::ClientBuilder,
    ca_cert: Option<&std::path::Path>,
) -> anyhow::Result<reqwest::blocking::ClientBuilder> {
    let from_env = || std::env::var_os("PATHFARM_CA_CERT").filter(|p| !p.is_empty()).map(PathBuf::from);
    let Some(path) = ca_cert.map(PathBuf::from).or_else(from_env) else { return Ok(builder) };
    let pem = std::fs::read(&path).with_context(|| format!("PATHFARM_CA_CERT: reading {}", path.display()))?;
    let certs = reqwest::Certificate::from_pem_bundle(&pem)
        .with_context(|| format!("PATHFARM_CA_CERT: {} is not a PEM certificate", path.display()))?;
    anyhow::ensure!(!certs.is_empty(), "PATHFARM_CA_CERT: {} holds no certificate", path.display());
    Ok(certs.into_iter().fold(builder, |b, c| b.add_root_certificate(c)))
}

/// The text of a panic payload.
fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<String>()
        .cloned()
        .or_else(|| p.downcast_ref::<&str>().map(|s| (*s).to_string()))
        .unwrap_or_else(|| "unknown panic".into())
}

/// Runs `f`, turning an error or a panic into the reason given to the coordinator.
fn guarded<T>(what: &str, f: impl FnOnce() -> anyhow::Result<T>) -> Result<T, String> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(format!("{e:#}")),
        Err(p) => Err(format!("{what} panicked: {}", panic_message(p.as_ref()))),
    }
}

fn text(resp: Response) -> String {
    resp.text().unwrap_or_default().chars().take(500).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::Renderer;
    use pathfarm_common::job::RenderSettings;
    use pathfarm_common::scene::demo::cornell_demo_glb;
    use pathfarm_common::scene::load_scene_from_slice;

    /// A worker's SIMD tag names the level its renderer runs at, not a CPU flag (checked that
    /// it fails with the tags taken from `is_x86_feature_detected!("avx512f")` as before, on
    /// this AVX-512 machine: the AVX2 level's tags then said `avx512f`).
    #[test]
    fn the_simd_tag_is_the_renderers_level() {
        let simd =
            |level| automatic_tags_at(level).into_iter().filter(|t| t == "avx512f" || t == "avx2").collect::<Vec<_>>();
        assert_eq!(simd(SimdLevel::Avx512), ["avx512f"]);
        assert_eq!(simd(SimdLevel::Avx2), ["avx2"]);
        assert!(simd(SimdLevel::Baseline).is_empty());
        assert_eq!(automatic_tags(), automatic_tags_at(SimdLevel::detect()));
        assert_eq!(automatic_tags()[0], "cpu");
    }

    /// The scene cache keeps within its budget by removing the least recently used scenes
    /// (bundle and unpacked folder), never the one being loaded, and leaves other files alone.
    #[test]
    fn the_scene_cache_drops_least_recently_used_scenes_beyond_its_budget() {
        let dir = tempfile::tempdir().expect("tempdir");
        let ids: Vec<String> = (0..4u8).map(|i| hex::encode([i; 32])).collect();
        let t0 = std::time::SystemTime::now() - Duration::from_secs(1000);
        for (i, id) in ids.iter().enumerate() {
            let bundle = dir.path().join(format!("{id}.bundle"));
            std::fs::write(&bundle, vec![0u8; 1000]).expect("bundle");
            std::fs::create_dir_all(dir.path().join(id)).expect("folder");
            std::fs::write(dir.path().join(id).join("scene.glb"), vec![0u8; 1000]).expect("scene");
            // Scene 0 is the least recently used, scene 3 the most.
            let f = std::fs::File::options().append(true).open(&bundle).expect("open");
            f.set_modified(t0 + Duration::from_secs(10 * i as u64)).expect("mtime");
        }
        std::fs::write(dir.path().join("notes.txt"), b"not a scene").expect("other file");
        // 8,000 bytes in all; a 5,000-byte budget removes two scenes, oldest first, but keeps
        // scene 0 because it is being loaded.
        let removed = prune_scene_cache(dir.path(), &ids[0], 5000).expect("prune");
        assert_eq!(removed, vec![ids[1].clone(), ids[2].clone()]);
        for (i, id) in ids.iter().enumerate() {
            let kept = i == 0 || i == 3;
            assert_eq!(dir.path().join(format!("{id}.bundle")).exists(), kept, "scene {i}");
            assert_eq!(dir.path().join(id).exists(), kept, "scene {i}'s folder");
        }
        assert!(dir.path().join("notes.txt").exists());
        // Within the budget nothing goes.
        assert!(prune_scene_cache(dir.path(), &ids[3], 1 << 20).expect("prune").is_empty());
    }

    /// A renderer is built once per (job, frame); two frames are kept; another job's are dropped.
    #[test]
    fn renderers_are_cached_per_job_and_frame() {
        let mut cache = RendererCache::<i32>::new(2);
        let builds = std::cell::Cell::new(0);
        let mut get = |job: u64, f: i32| {
            let mut s = RenderSettings::new(8, 8, 1);
            s.frame = f;
            let r = cache.get_or_build(job, &s, || {
                builds.set(builds.get() + 1);
                Ok(f)
            });
            (*r.expect("build"), cache.len())
        };
        for f in [1, 1, 2, 1, 2, 2] {
            assert_eq!(get(7, f).0, f);
        }
        assert_eq!(builds.get(), 2, "one build per frame");
        get(7, 3); // evicts frame 1, the least recently used
        get(7, 2); // cached
        assert_eq!(builds.get(), 3);
        assert_eq!(get(7, 1), (1, 2), "built again, two kept");
        assert_eq!(builds.get(), 4);
        assert_eq!(get(8, 1), (1, 1), "another job: job 7's renderers are dropped");
        let mut s = RenderSettings::new(8, 8, 1);
        s.frame = 5;
        assert!(cache.get_or_build(9, &s, || anyhow::bail!("no scene")).is_err());
        assert!(cache.is_empty(), "a failed build caches nothing, and job 8's went");
    }

    #[test]
    fn a_panic_while_preparing_becomes_the_units_failure_reason() {
        let r: Result<(), String> = guarded("preparing the unit", || panic!("BVH build: bad bounds"));
        assert_eq!(r, Err("preparing the unit panicked: BVH build: bad bounds".to_string()));
        let r: Result<(), String> = guarded("preparing the unit", || anyhow::bail!("scene missing"));
        assert_eq!(r, Err("scene missing".to_string()));
        assert_eq!(guarded("x", || Ok(7)), Ok(7));
    }

    /// A scene that slipped past the loader (built in memory) with a vertex at 1e25: the
    /// renderer refuses it with a reason instead of panicking in the BVH build.
    #[test]
    fn the_renderer_refuses_huge_coordinates() {
        let mut scene =
            load_scene_from_slice(&cornell_demo_glb(), "cornell.glb", None, &LoadOptions::default()).expect("demo");
        scene.meshes[0].positions[0].x = 1e25;
        let r = guarded("preparing the unit", || Ok(Renderer::new(&scene, &RenderSettings::new(8, 8, 1))?));
        let reason = r.err().expect("refused");
        assert!(reason.contains("finite and within"), "{reason}");
    }
}
