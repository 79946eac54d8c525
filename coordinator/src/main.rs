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
    /// A unit whose worker stops heartbeating for this long is handed out again.
    #[arg(long, default_value_t = 10_000)]
    lease_timeout_ms: u64,
    /// Interval workers heartbeat at.
    #[arg(long, default_value_t = 2_000)]
    heartbeat_ms: u64,
    /// Largest request body (scene upload or unit result) in MiB.
    #[arg(long, default_value_t = 512)]
    max_upload_mb: usize,
    /// Refuse scenes with more triangles than this.
    #[arg(long, default_value_t = 20_000_000)]
    max_triangles: usize,
    /// Refuse scenes with a texture of more pixels (width x height) than this.
    #[arg(long, default_value_t = 16384 * 16384)]
    max_texture_pixels: u64,
    /// Refuse jobs with more pixels (width x height) than this. A job's film holds 208 bytes
    /// per pixel (13 channels of 128-bit sums): the default 8192 x 8192 is 13 GiB.
    #[arg(long, default_value_t = 8192 * 8192)]
    max_pixels: u64,
    /// Refuse jobs with more samples per pixel than this.
    #[arg(long, default_value_t = 1 << 20)]
    max_spp: u32,
    /// Refuse jobs whose integrator max_depth exceeds this.
    #[arg(long, default_value_t = 1024)]
    max_depth: u32,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    if let Some(Command::Demo(args)) = cli.command {
        return pathfarm_coordinator::demo::run(args);
    }
    let a = cli.serve;
    let mut cfg = ServerConfig::new(a.listen, a.data_dir.clone());
    cfg.farm.lease_timeout_ms = a.lease_timeout_ms;
    cfg.farm.heartbeat_ms = a.heartbeat_ms;
    cfg.max_upload_bytes = a.max_upload_mb.saturating_mul(1 << 20);
    cfg.max_triangles = a.max_triangles;
    cfg.max_texture_pixels = a.max_texture_pixels;
    cfg.farm.limits.max_pixels = a.max_pixels;
    cfg.farm.limits.max_spp = a.max_spp;
    cfg.farm.limits.max_depth = a.max_depth;
    cfg.auth = Auth { client: a.client_token, worker: a.worker_token.clone() };
    let rt = tokio::runtime::Runtime::new()?;
    let server = rt.block_on(Server::start(cfg))?;
    let _workers = if a.local_workers > 0 {
        Some(LocalWorkers::start(&server.url(), a.worker_token, a.local_workers, &a.data_dir.join("worker-cache"))?)
    } else {
        None
    };
    rt.block_on(server.run_until_signal())
}
