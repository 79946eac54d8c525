//! `pathfarm-coordinator`: the farm's coordinator service, and `demo`.

use clap::{Args, Parser, Subcommand};
use pathfarm_coordinator::local::LocalWorkers;
use pathfarm_coordinator::server::{Auth, Server, ServerConfig};
use std::net::SocketAddr;
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(name = "pathfarm-coordinator", version, about = "pathfarm coordinator: REST API, scheduler, merger")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    serve: ServeArgs,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Start a coordinator with local workers, render the bundled demo scene, write an EXR.
    Demo(pathfarm_coordinator::demo::DemoArgs),
    /// Exit 0 if the coordinator at URL answers `/healthz`, 1 otherwise (container health checks).
    Healthcheck {
        /// The coordinator's base URL (https:// trusts PATHFARM_CA_CERT too).
        #[arg(long, default_value = "http://127.0.0.1:8080")]
        url: String,
        /// Give up after this long.
        #[arg(long, default_value_t = 3_000)]
        timeout_ms: u64,
    },
}

#[derive(Args, Debug)]
struct ServeArgs {
    /// Address to listen on (port 0 = any free port; the address is written to DATA_DIR/coordinator.addr).
    #[arg(long, default_value = "127.0.0.1:8080")]
    listen: SocketAddr,
    /// Where scenes, job images and state live.
    #[arg(long, default_value = "pathfarm-data")]
    data_dir: PathBuf,
    /// Workers to run inside this process (they share the cores).
    #[arg(long, default_value_t = 0)]
    local_workers: usize,
    /// Bearer token for clients.
    #[arg(long, env = "PATHFARM_CLIENT_TOKEN", hide_env_values = true)]
    client_token: Option<String>,
    /// Bearer token for workers.
    #[arg(long, env = "PATHFARM_WORKER_TOKEN", hide_env_values = true)]
    worker_token: Option<String>,
    /// Read the client token from this file (first line; e.g. a systemd credential or a
    /// Kubernetes secret volume), so it appears in no process listing or environment.
    #[arg(long, env = "PATHFARM_CLIENT_TOKEN_FILE", conflicts_with = "client_token")]
    client_token_file: Option<PathBuf>,
    /// Read the worker token from this file.
    #[arg(long, env = "PATHFARM_WORKER_TOKEN_FILE", conflicts_with = "worker_token")]
    worker_token_file: Option<PathBuf>,
    /// Bearer token for `GET /metrics` (open when not given; the client and worker tokens do
    /// not open it).
    #[arg(long, env = "PATHFARM_METRICS_TOKEN", hide_env_values = true)]
    metrics_token: Option<String>,
    /// Run without authentication (only allowed on a loopback address).
    #[arg(long)]
    no_auth: bool,
    /// A unit whose worker stops heartbeating for this long is handed out again.
    #[arg(long, default_value_t = 10_000)]
    lease_timeout_ms: u64,
    /// Interval workers heartbeat at.
    #[arg(long, default_value_t = 2_000)]
    heartbeat_ms: u64,
    /// How often jobs whose merged units changed are checkpointed (film + merged set); a crash
    /// redoes at most this much work. Each checkpoint copies the job's film under the farm lock.
    #[arg(long, default_value_t = 1_000)]
    checkpoint_ms: u64,
    /// Largest request body (scene upload or unit result) in MiB.
    #[arg(long, default_value_t = 512)]
    max_upload_mb: usize,
    /// Refuse scenes with more triangles than this.
    #[arg(long, default_value_t = 20_000_000)]
    max_triangles: usize,
    /// Refuse scenes with a texture of more pixels (width x height) than this.
    #[arg(long, default_value_t = 16384 * 16384)]
    max_texture_pixels: u64,
    /// Memory budget for one scene's decoded images in MiB (decode buffers plus 16 bytes per
    /// texel kept), checked before each allocation.
    #[arg(long, default_value_t = 2048)]
    max_texture_mb: u64,
    /// Scene uploads decoded at once (each may use up to --max-texture-mb); more wait.
    #[arg(long, default_value_t = 2)]
    max_scene_decodes: usize,
    /// Refuse jobs with more pixels (width x height) than this (see also --film-memory-mb).
    #[arg(long, default_value_t = 8192 * 8192)]
    max_pixels: u64,
    /// Refuse jobs with more samples per pixel than this.
    #[arg(long, default_value_t = 1 << 20)]
    max_spp: u32,
    /// Refuse jobs whose integrator max_depth exceeds this.
    #[arg(long, default_value_t = 1024)]
    max_depth: u32,
    /// Serve HTTPS: the certificate chain (PEM, leaf first). Needs --tls-key. Workers and
    /// clients that do not trust its issuer take `PATHFARM_CA_CERT=ca.pem`.
    #[arg(long, env = "PATHFARM_TLS_CERT", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, env = "PATHFARM_TLS_KEY", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Refuse jobs with more work units (frames x tiles x passes) than this.
    #[arg(long, default_value_t = 1 << 22)]
    max_units: u64,
    /// Memory for the films in memory, in MiB; a film takes 64 bytes per pixel (a 1080p frame
    /// 127 MiB). Queued jobs hold none, paused and finished ones none once written to disk; a
    /// frame starts (or a film is read back) only while it fits, and a job whose films could
    /// never fit is refused with 422. Checkpoints copy one film at a time on top.
    #[arg(long, default_value_t = pathfarm_coordinator::farm::DEFAULT_FILM_BUDGET_BYTES >> 20)]
    film_memory_mb: u64,
    /// Films in memory at most, across jobs; beyond it the least recently used films of jobs
    /// of no higher priority are written to disk (their frames' checkpoints) and read back when
    /// their frames are leased again.
    #[arg(long, default_value_t = pathfarm_coordinator::farm::DEFAULT_MAX_RESIDENT_FILMS)]
    max_resident_films: usize,
    /// Frames of one sequence (frame order) holding a film at once: the frames rendering plus
    /// those being written. The next frame starts when the frames in progress have no unit
    /// left to hand out, if it fits this and --film-memory-mb.
    #[arg(long, default_value_t = 2)]
    max_open_frames: usize,
    /// A job with `denoise` waits this long for a worker with the tag `denoise` to take a
    /// frame's final denoise step; then the frame is finished without the denoised layer and
    /// the job's log says why.
    #[arg(long, default_value_t = 30_000)]
    denoise_grace_ms: u64,
    /// A connection must send a complete request head within this long of being opened (or, on
    /// a kept-alive connection, of the head's first byte); otherwise it is closed.
    #[arg(long, default_value_t = 10_000)]
    header_timeout_ms: u64,
    /// A kept-alive connection on which nothing moves for this long between requests is closed.
    /// A request being handled (a lease long poll, an event stream) is never idle.
    #[arg(long, default_value_t = 60_000)]
    idle_timeout_ms: u64,
    /// Workers not seen for this long (and holding no lease) are forgotten, in memory and in
    /// SQLite; 0 = never. One that comes back registers again.
    #[arg(long, default_value_t = 3_600_000)]
    prune_workers_after_ms: u64,
    /// Scenes that no job (of any state) references and that were uploaded longer ago than this
    /// are removed (checked with the lease expiry); 0 = never. Uploading the same scene again
    /// restarts its clock.
    #[arg(long, default_value_t = pathfarm_coordinator::server::SCENE_GC_AFTER_MS)]
    scene_gc_after_ms: u64,
    /// Worker registrations allowed per client address and minute (a token bucket; 0 =
    /// unlimited). Beyond it: 429 with Retry-After.
    #[arg(long, default_value_t = 60)]
    register_per_minute: u32,
    /// Registrations one address may make at once before the per-minute rate applies.
    #[arg(long, default_value_t = 60)]
    register_burst: u32,
    /// Key of the HMAC-SHA256 signature (`X-Pathfarm-Signature: sha256=<hex>`) of job webhooks
    /// (`notify` in a job's body); without it such jobs are refused.
    #[arg(long, env = "PATHFARM_WEBHOOK_SECRET", hide_env_values = true)]
    webhook_secret: Option<String>,
    /// Wait before the first retry of a failed webhook, doubled after each further failure (5
    /// attempts in all, 5 s each at most).
    #[arg(long, default_value_t = 1_000)]
    webhook_retry_ms: u64,
    /// Open connections at most (lowered to fit the open-file limit). Beyond it, the quietest
    /// connection that is not handling a request is closed to make room.
    #[arg(long, default_value_t = 4096)]
    max_connections: usize,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Demo(args)) => return pathfarm_coordinator::demo::run(args),
        Some(Command::Healthcheck { url, timeout_ms }) => return healthcheck(&url, timeout_ms),
        None => {}
    }
    let mut a = cli.serve;
    if let Some(path) = &a.client_token_file {
        a.client_token = Some(read_token_file(path)?);
    }
    if let Some(path) = &a.worker_token_file {
        a.worker_token = Some(read_token_file(path)?);
    }
    let mut cfg = ServerConfig::new(a.listen, a.data_dir.clone());
    cfg.farm.lease_timeout_ms = a.lease_timeout_ms;
    cfg.farm.heartbeat_ms = a.heartbeat_ms;
    cfg.checkpoint_interval = std::time::Duration::from_millis(a.checkpoint_ms.max(100));
    cfg.max_upload_bytes = a.max_upload_mb.saturating_mul(1 << 20);
    cfg.max_triangles = a.max_triangles;
    cfg.max_texture_pixels = a.max_texture_pixels;
    cfg.max_texture_bytes = a.max_texture_mb.saturating_mul(1 << 20);
    cfg.max_scene_decodes = a.max_scene_decodes.max(1);
    cfg.farm.limits.max_pixels = a.max_pixels;
    cfg.farm.limits.max_spp = a.max_spp;
    cfg.farm.limits.max_depth = a.max_depth;
    cfg.farm.limits.max_units = a.max_units;
    cfg.tls = a.tls_cert.clone().zip(a.tls_key.clone());
    cfg.farm.film_budget_bytes = Some(a.film_memory_mb.saturating_mul(1 << 20));
    cfg.farm.max_open_frames = a.max_open_frames.max(1);
    cfg.farm.max_resident_films = a.max_resident_films.max(1);
    cfg.farm.denoise_grace_ms = a.denoise_grace_ms;
    cfg.farm.worker_prune_ms = (a.prune_workers_after_ms > 0).then_some(a.prune_workers_after_ms);
    cfg.register_per_minute = a.register_per_minute;
    cfg.register_burst = a.register_burst;
    cfg.scene_gc_after_ms = (a.scene_gc_after_ms > 0).then_some(a.scene_gc_after_ms);
    if a.header_timeout_ms == 0 || a.idle_timeout_ms == 0 || a.max_connections == 0 {
        anyhow::bail!("--header-timeout-ms, --idle-timeout-ms and --max-connections must be at least 1");
    }
    cfg.conn = pathfarm_coordinator::service::ConnLimits {
        header_timeout: std::time::Duration::from_millis(a.header_timeout_ms),
        idle_timeout: std::time::Duration::from_millis(a.idle_timeout_ms),
        max_connections: a.max_connections,
    };
    let metrics_empty =
        std::env::var_os("PATHFARM_METRICS_TOKEN").is_some_and(|v| v.to_string_lossy().trim().is_empty());
    if a.metrics_token.as_deref().is_some_and(|t| t.trim().is_empty()) || (a.metrics_token.is_none() && metrics_empty) {
        anyhow::bail!(
            "--metrics-token / PATHFARM_METRICS_TOKEN is empty: an empty token is refused; give a secret or unset it"
        );
    }
    cfg.metrics_token = a.metrics_token.clone();
    if a.webhook_secret.as_deref().is_some_and(|t| t.trim().is_empty()) {
        anyhow::bail!("--webhook-secret / PATHFARM_WEBHOOK_SECRET is empty: give a secret or unset it");
    }
    cfg.webhooks.secret = a.webhook_secret.clone();
    cfg.webhooks.retry_base = std::time::Duration::from_millis(a.webhook_retry_ms);
    cfg.auth = auth(&a)?;
    let worker_token = cfg.auth.worker.clone();
    let rt = tokio::runtime::Runtime::new()?;
    let server = rt.block_on(Server::start(cfg))?;
    let _workers = if a.local_workers > 0 {
        Some(LocalWorkers::start(&server.url(), worker_token, a.local_workers, &a.data_dir.join("worker-cache"))?)
    } else {
        None
    };
    rt.block_on(server.run_until_signal())
}

/// Tokens from flags or the environment; else `--no-auth` (loopback only); else tokens made on
/// the first start and kept in DATA_DIR/tokens.json.
fn auth(a: &ServeArgs) -> anyhow::Result<Auth> {
    if a.no_auth {
        if !a.listen.ip().is_loopback() {
            anyhow::bail!("--no-auth is refused on {}: without tokens, listen on a loopback address only", a.listen);
        }
        return Ok(Auth::default());
    }
    // An empty token would let an empty `?token=` or `Bearer ` in: refuse it, whether it came
    // from a flag or from an environment variable that is set but empty.
    for (flag, var, value) in [
        ("--client-token", "PATHFARM_CLIENT_TOKEN", &a.client_token),
        ("--worker-token", "PATHFARM_WORKER_TOKEN", &a.worker_token),
    ] {
        let env_empty = std::env::var_os(var).is_some_and(|v| v.to_string_lossy().trim().is_empty());
        if value.as_deref().is_some_and(|t| t.trim().is_empty()) || (value.is_none() && env_empty) {
            anyhow::bail!(
                "{flag} / {var} is empty: an empty token is refused; give a secret, or unset it to use the \
                 tokens in DATA_DIR/tokens.json"
            );
        }
    }
    if a.client_token.is_some() || a.worker_token.is_some() {
        return Ok(Auth { client: a.client_token.clone(), worker: a.worker_token.clone() });
    }
    let path = a.data_dir.join("tokens.json");
    if let Ok(bytes) = std::fs::read(&path) {
        let t: serde_json::Value = serde_json::from_slice(&bytes)?;
        let get = |k: &str| t.get(k).and_then(|v| v.as_str()).map(str::to_string);
        let tokens = Auth { client: get("client_token"), worker: get("worker_token") };
        if [&tokens.client, &tokens.worker].iter().any(|t| t.as_deref().is_none_or(|t| t.trim().is_empty())) {
            anyhow::bail!("{} lacks a client_token or a worker_token (or one is empty)", path.display());
        }
        tracing::info!(path = %path.display(), "using the tokens made on the first start");
        return Ok(tokens);
    }
    let tokens = Auth { client: Some(random_token()?), worker: Some(random_token()?) };
    std::fs::create_dir_all(&a.data_dir)?;
    let json = serde_json::json!({"client_token": tokens.client, "worker_token": tokens.worker});
    pathfarm_common::film::write_atomic(&path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))?;
    }
    // Secrets go to a person at a terminal only: under systemd or in a container stderr is a
    // log (the journal) that others may read.
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        eprintln!(
            "pathfarm-coordinator: generated tokens (kept in {}):\n  client token: {}\n  worker token: {}",
            path.display(),
            tokens.client.as_deref().unwrap_or_default(),
            tokens.worker.as_deref().unwrap_or_default()
        );
    } else {
        tracing::info!(path = %path.display(), "generated client and worker tokens; read them in this file (mode 0600)");
    }
    Ok(tokens)
}

/// A token kept in a file: its first line, trimmed; an empty one is refused.
fn read_token_file(path: &std::path::Path) -> anyhow::Result<String> {
    use anyhow::Context;
    let text = std::fs::read_to_string(path).with_context(|| format!("reading the token file {}", path.display()))?;
    let token = text.lines().next().unwrap_or_default().trim().to_string();
    anyhow::ensure!(!token.is_empty(), "the token file {} is empty: an empty token is refused", path.display());
    Ok(token)
}

/// `pathfarm-coordinator healthcheck`: GET /healthz.
fn healthcheck(url: &str, timeout_ms: u64) -> anyhow::Result<()> {
    let timeout = std::time::Duration::from_millis(timeout_ms.max(1));
    let http =
        pathfarm_worker::daemon::with_ca_cert(reqwest::blocking::Client::builder().timeout(timeout), None)?.build()?;
    let url = format!("{}/healthz", url.trim_end_matches('/'));
    let resp = http.get(&url).send().map_err(|e| anyhow::anyhow!("{url}: {e}"))?;
    anyhow::ensure!(resp.status().is_success(), "{url}: {}", resp.status());
    Ok(())
}

/// 192 random bits from the OS, hex-encoded.
fn random_token() -> anyhow::Result<String> {
    use std::io::Read;
    let mut buf = [0u8; 24];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut buf)?;
    Ok(hex::encode(buf))
}
